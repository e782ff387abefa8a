# ROS layer: the detector and track fuser nodelets (one library, image_pipeline style), the executable that hosts it
# without a manager, and the rostests that drive both with rendered frames.
# Generated headers (messages, dynamic_reconfigure) live in the devel space.
set(ARUCOTAG_ROS_INCLUDES ${CATKIN_DEVEL_PREFIX}/include)

add_library(arucotag_nodelet
  src/nodelet/conversions.cpp
  src/nodelet/detector_nodelet.cpp
  src/nodelet/image_input.cpp
  src/nodelet/parameters.cpp
  src/nodelet/track_fuser_nodelet.cpp
  src/nodelet/tracks.cpp)
target_include_directories(arucotag_nodelet PRIVATE ${ARUCOTAG_ROS_INCLUDES})
target_include_directories(arucotag_nodelet SYSTEM PRIVATE ${catkin_INCLUDE_DIRS} ${pcl_conversions_INCLUDE_DIRS})
target_link_libraries(arucotag_nodelet arucotag_core ${catkin_LIBRARIES})
add_dependencies(arucotag_nodelet ${PROJECT_NAME}_generate_messages_cpp ${PROJECT_NAME}_gencfg)

add_executable(detector_node src/nodelet/detector_node.cpp)
target_include_directories(detector_node SYSTEM PRIVATE ${catkin_INCLUDE_DIRS})
target_link_libraries(detector_node ${catkin_LIBRARIES})
# The node loads the plugin at run time; build it whenever the node is built.
add_dependencies(detector_node arucotag_nodelet)

install(TARGETS arucotag_nodelet detector_node
  ARCHIVE DESTINATION ${CATKIN_PACKAGE_LIB_DESTINATION}
  LIBRARY DESTINATION ${CATKIN_PACKAGE_LIB_DESTINATION}
  RUNTIME DESTINATION ${CATKIN_PACKAGE_BIN_DESTINATION})

if(CATKIN_ENABLE_TESTING)
  # launch/*.launch parse, and every package they name is installed and declared in package.xml.
  find_package(roslaunch REQUIRED)
  roslaunch_add_file_check(launch)

  # Image encodings from real photos through image_input.cpp and the core: gtest, no master. It
  # compiles the one file it tests rather than linking the plugin library.
  catkin_add_gtest(test_ros_encodings test/ros/test_encodings.cpp src/nodelet/image_input.cpp)
  target_include_directories(test_ros_encodings SYSTEM PRIVATE ${catkin_INCLUDE_DIRS})
  target_link_libraries(test_ros_encodings arucotag_core ${catkin_LIBRARIES} ${GTEST_MAIN_LIBRARIES})
  target_compile_definitions(test_ros_encodings PRIVATE ARUCOTAG_TEST_DATA="${CMAKE_CURRENT_SOURCE_DIR}/test/data")

  # The camera_info conversion without a master: binned, cropped and fisheye renders against truth;
  # ToMessage's covariance and orientation flag; the tracks' message, markers and frame change;
  # PointCloud2 -> pcl::PointCloud (CloudFromMessage).
  catkin_add_gtest(test_camera_model test/ros/test_camera_model.cpp test/ros/test_conversions.cpp
    test/ros/test_tracks.cpp test/ros/test_cloud_conversion.cpp test/ros/rig.cpp)
  target_include_directories(test_camera_model PRIVATE ${ARUCOTAG_ROS_INCLUDES})
  target_include_directories(test_camera_model SYSTEM PRIVATE ${catkin_INCLUDE_DIRS})
  target_link_libraries(test_camera_model arucotag_nodelet arucotag_sim ${catkin_LIBRARIES} ${GTEST_MAIN_LIBRARIES})

  find_package(rostest REQUIRED)
  # Each rostest starts its own master and manager; the test node publishes frames rendered by
  # arucotag_sim (ROS-free) and checks what the real nodelet publishes.
  foreach(name detector lifecycle cameras)
    add_rostest_gtest(test_ros_${name} test/ros/${name}.test test/ros/test_${name}.cpp test/ros/rig.cpp
      test/ros/flip_search.cpp)
    target_include_directories(test_ros_${name} PRIVATE ${ARUCOTAG_ROS_INCLUDES})
    target_include_directories(test_ros_${name} SYSTEM PRIVATE ${catkin_INCLUDE_DIRS})
    target_link_libraries(test_ros_${name} arucotag_sim ${catkin_LIBRARIES} ${GTEST_LIBRARIES})
    add_dependencies(test_ros_${name} arucotag_nodelet detector_node ${PROJECT_NAME}_generate_messages_cpp)
  endforeach()

  # Malformed input of every kind, one freshly loaded detector per case (bad_input.test).
  add_rostest_gtest(test_ros_bad_input test/ros/bad_input.test test/ros/test_bad_input.cpp test/ros/rig.cpp)
  target_include_directories(test_ros_bad_input PRIVATE ${ARUCOTAG_ROS_INCLUDES})
  target_include_directories(test_ros_bad_input SYSTEM PRIVATE ${catkin_INCLUDE_DIRS})
  target_link_libraries(test_ros_bad_input arucotag_sim ${catkin_LIBRARIES} ${GTEST_LIBRARIES})
  add_dependencies(test_ros_bad_input arucotag_nodelet ${PROJECT_NAME}_generate_messages_cpp)

  # Marker bundles (config/urc_bundles.yaml) through the shipped launch file: pose, output_frame, TF.
  add_rostest_gtest(test_ros_bundles test/ros/bundles.test test/ros/test_bundles.cpp test/ros/rig.cpp)
  target_include_directories(test_ros_bundles PRIVATE ${ARUCOTAG_ROS_INCLUDES})
  target_include_directories(test_ros_bundles SYSTEM PRIVATE ${catkin_INCLUDE_DIRS})
  target_link_libraries(test_ros_bundles arucotag_sim ${catkin_LIBRARIES} ${GTEST_LIBRARIES})
  add_dependencies(test_ros_bundles arucotag_nodelet ${PROJECT_NAME}_generate_messages_cpp)

  # On the real photos in test/data: stamp patterns of real drivers and bags (stamps), and two
  # cameras' detectors fused by arucotag/TrackFuser (fuser).
  foreach(name stamps fuser)
    add_rostest_gtest(test_ros_${name} test/ros/${name}.test test/ros/test_${name}.cpp test/ros/photos.cpp
      test/ros/rig.cpp)
    target_include_directories(test_ros_${name} PRIVATE ${ARUCOTAG_ROS_INCLUDES})
    target_include_directories(test_ros_${name} SYSTEM PRIVATE ${catkin_INCLUDE_DIRS})
    target_link_libraries(test_ros_${name} arucotag_sim ${catkin_LIBRARIES} ${GTEST_LIBRARIES})
    target_compile_definitions(test_ros_${name} PRIVATE ARUCOTAG_TEST_DATA="${CMAKE_CURRENT_SOURCE_DIR}/test/data")
    add_dependencies(test_ros_${name} arucotag_nodelet ${PROJECT_NAME}_generate_messages_cpp)
  endforeach()
endif()
