# Detection benchmark, `make bench` (bench/run.sh): frame sets rendered once into the build folder,
# OpenCV, its ArUco3 mode, AprilTag 3 and ours timed by bench_detect (core only), the nodelet by
# bench_nodelet (in a manager).
add_library(arucotag_bench_frames STATIC bench/frames.cpp)
target_link_libraries(arucotag_bench_frames PUBLIC arucotag_sim arucotag_core)

add_executable(bench_detect bench/bench_detect.cpp)
target_link_libraries(bench_detect arucotag_bench_frames)
# AprilTag 3 as a peer on the tag36h11 sets (Debian libapriltag-dev, or ROS's apriltag package);
# without it the benchmark builds and runs the other detectors.
find_package(apriltag QUIET)
if(TARGET apriltag::apriltag)
  target_link_libraries(bench_detect apriltag::apriltag)
  target_compile_definitions(bench_detect PRIVATE ARUCOTAG_BENCH_APRILTAG
                             ARUCOTAG_BENCH_APRILTAG_VERSION="${apriltag_VERSION}")
  message(STATUS "bench_detect: AprilTag ${apriltag_VERSION} found, timed on the tag36h11 sets")
else()
  message(STATUS "bench_detect: AprilTag not found (apt-get install libapriltag-dev), left out of the benchmark")
endif()

# Every marker Detect reads on the frame sets and test/data's photos, one line each: two builds' dumps
# compared with cmp show whether a change kept the results to the bit (bench/bench_dump.cpp).
add_executable(bench_dump bench/bench_dump.cpp)
target_link_libraries(bench_dump arucotag_bench_frames)

# Pose trust: flips, rotation error, NEES and time per tag for PnP, cloud and fused.
add_executable(bench_pose bench/bench_pose.cpp)
target_link_libraries(bench_pose arucotag_sim arucotag_core)

if(TARGET arucotag_nodelet)
  add_executable(bench_nodelet bench/bench_nodelet.cpp)
  target_include_directories(bench_nodelet PRIVATE ${ARUCOTAG_ROS_INCLUDES})
  target_include_directories(bench_nodelet SYSTEM PRIVATE ${catkin_INCLUDE_DIRS})
  target_link_libraries(bench_nodelet arucotag_bench_frames ${catkin_LIBRARIES})
  # It loads the plugin at run time; build it with the benchmark.
  add_dependencies(bench_nodelet arucotag_nodelet ${PROJECT_NAME}_generate_messages_cpp)
endif()

# `make soak` (scripts/soak.sh): the nodelet for SOAK_SECONDS at 30 Hz in a real manager, then 100
# load/unload cycles; fails past its memory, frame and survival budgets.
if(TARGET arucotag_nodelet)
  add_executable(soak test/soak/soak.cpp)
  target_include_directories(soak PRIVATE ${ARUCOTAG_ROS_INCLUDES})
  target_include_directories(soak SYSTEM PRIVATE ${catkin_INCLUDE_DIRS})
  target_link_libraries(soak arucotag_sim ${catkin_LIBRARIES})
  add_dependencies(soak arucotag_nodelet ${PROJECT_NAME}_generate_messages_cpp)
endif()
