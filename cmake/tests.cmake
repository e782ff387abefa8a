# Unit tests of the ROS-free core: gtest, no ROS master. They link the core and the renderer only.
set(ARUCOTAG_TEST_DATA "${CMAKE_CURRENT_SOURCE_DIR}/test/data")

catkin_add_gtest(test_core
  test/core/test_bad_input.cpp
  test/core/test_bundle.cpp
  test/core/test_depth_noise.cpp
  test/core/test_draw.cpp
  test/core/test_camera_model.cpp
  test/core/test_contours.cpp
  test/core/test_fast_path.cpp
  test/core/test_pcl_cloud.cpp
  test/core/test_point_cloud.cpp
  test/core/test_pose_covariance.cpp
  test/core/test_preprocess.cpp
  test/core/test_preprocess_recall.cpp
  test/core/test_real_photos.cpp
  test/core/test_small_markers.cpp
  test/core/test_refine_pattern.cpp
  test/core/test_no_ros.cpp
  test/core/test_synthetic.cpp
  test/core/test_tracker.cpp)
target_link_libraries(test_core arucotag_sim arucotag_core ${GTEST_MAIN_LIBRARIES})
# Some tests check the core's internal bounds directly (src/core/*.hpp).
target_include_directories(test_core PRIVATE src/core)
target_compile_definitions(test_core PRIVATE
  ARUCOTAG_TEST_DATA="${ARUCOTAG_TEST_DATA}"
  ARUCOTAG_CORE_LIBRARY="$<TARGET_FILE:arucotag_core>"
  ARUCOTAG_SOURCE_DIR="${CMAKE_CURRENT_SOURCE_DIR}")

# The scripts that write and count CI's JUnit results (scripts/junit.py, scripts/count_results.py):
# a Python unittest, run through rosunit for its JUnit output. No build, no ROS master.
catkin_run_tests_target("rosunit" "test_junit" "rosunit-test_junit.xml"
  COMMAND "/usr/bin/python3 ${CMAKE_CURRENT_SOURCE_DIR}/test/scripts/test_junit.py --gtest_output=xml:${CATKIN_TEST_RESULTS_DIR}/${PROJECT_NAME}/rosunit-test_junit.xml"
  WORKING_DIRECTORY "${CMAKE_CURRENT_SOURCE_DIR}")
