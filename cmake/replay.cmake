# Bag replay: the sample-recording generator and the replay tests (launch/replay.launch drives the
# detector nodelet on a bag; scripts/demo.sh and scripts/replay_report.py score it against truth).

# The sample world is ROS-free (OpenCV and arucotag_sim); only the bag writer knows ROS.
add_library(arucotag_sample_scene STATIC src/replay/sample_scene.cpp)
target_link_libraries(arucotag_sample_scene PUBLIC arucotag_sim)

add_executable(make_sample_bag src/tools/make_sample_bag.cpp)
target_include_directories(make_sample_bag PRIVATE ${CATKIN_DEVEL_PREFIX}/include)
target_include_directories(make_sample_bag SYSTEM PRIVATE ${catkin_INCLUDE_DIRS})
target_link_libraries(make_sample_bag arucotag_sample_scene ${catkin_LIBRARIES})
add_dependencies(make_sample_bag ${PROJECT_NAME}_generate_messages_cpp)
install(TARGETS make_sample_bag RUNTIME DESTINATION ${CATKIN_PACKAGE_BIN_DESTINATION})

# Lets `rosbag play --rate-control-topic` follow the detector (see launch/replay.launch, rate_control).
add_executable(replay_pacer src/replay/replay_pacer.cpp)
target_include_directories(replay_pacer PRIVATE include ${CATKIN_DEVEL_PREFIX}/include)
target_include_directories(replay_pacer SYSTEM PRIVATE ${catkin_INCLUDE_DIRS})
target_link_libraries(replay_pacer ${catkin_LIBRARIES})
add_dependencies(replay_pacer ${PROJECT_NAME}_generate_messages_cpp)
install(TARGETS replay_pacer RUNTIME DESTINATION ${CATKIN_PACKAGE_BIN_DESTINATION})

# Sourcing the devel space sets ARUCOTAG_SAMPLE_BAG (replay.launch's default bag) to this build
# folder's sample; an install space has no sample, so no hook there.
catkin_add_env_hooks(50.arucotag_sample SHELLS sh DIRECTORY ${PROJECT_SOURCE_DIR}/cmake SKIP_INSTALL)

if(CATKIN_ENABLE_TESTING)
  find_package(rostest REQUIRED)
  # A 3 s, 5 Hz excerpt of the sample (the post at 2-3 m, two faces in view; 15 jpeg images, 5
  # clouds): 7 MB in the package's build folder, made when the tests are built, never committed.
  set(ARUCOTAG_REPLAY_TEST_BAG ${PROJECT_BINARY_DIR}/replay_test/short.bag)  # also in the .test files below
  add_custom_command(OUTPUT ${ARUCOTAG_REPLAY_TEST_BAG}
    COMMAND make_sample_bag --output ${ARUCOTAG_REPLAY_TEST_BAG} --start 8 --duration 3 --rate 5
    DEPENDS make_sample_bag
    COMMENT "Generating the replay test recording")
  add_custom_target(replay_test_bag DEPENDS ${ARUCOTAG_REPLAY_TEST_BAG})
  add_dependencies(tests replay_test_bag replay_pacer)

  # The .test files get the paths baked in, so the test names stay free of build paths.
  set(ARUCOTAG_REPLAY_TEST_DIR ${PROJECT_BINARY_DIR}/replay_test)
  set(ARUCOTAG_DEVEL_PYTHON ${CATKIN_DEVEL_PREFIX}/${CATKIN_GLOBAL_PYTHON_DESTINATION})
  set(_replay_test_deps replay_test_bag replay_pacer arucotag_nodelet ${PROJECT_NAME}_generate_messages_py)
  foreach(name replay rviz)
    configure_file(test/replay/${name}.test.in ${PROJECT_BINARY_DIR}/test/replay/${name}.test @ONLY)
    add_rostest(${PROJECT_BINARY_DIR}/test/replay/${name}.test DEPENDENCIES ${_replay_test_deps})
  endforeach()
endif()
