# Command-line tools. detect_image reads ROS camera_info yaml through camera_calibration_parsers,
# so it links that one ROS library; the core it drives does not.
add_executable(detect_image src/tools/detect_image.cpp)
target_include_directories(detect_image SYSTEM PRIVATE ${catkin_INCLUDE_DIRS})
target_link_libraries(detect_image arucotag_core ${catkin_LIBRARIES})
install(TARGETS detect_image RUNTIME DESTINATION ${CATKIN_PACKAGE_BIN_DESTINATION})
