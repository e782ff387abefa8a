# Fuzzing (test/fuzz): one harness per source, each defining LLVMFuzzerTestOneInput.
# - ARUCOTAG_FUZZ=ON (scripts/fuzz.sh, a clang build of its own): libFuzzer executables fuzz_<name>.
# - Otherwise, with testing: test_fuzz_<name>, a gtest that replays test/fuzz/corpus/<name> through
#   the same harness, so `make test`, `make sanitize` and CI run the corpus with gcc.
option(ARUCOTAG_FUZZ "Build the libFuzzer harnesses (clang with -fsanitize=fuzzer-no-link)" OFF)

set(ARUCOTAG_FUZZ_CORE_HARNESSES core pose)
# The ROS harnesses read the nodelet's conversions and parameters (and generated headers).
set(ARUCOTAG_FUZZ_ROS_HARNESSES)
if(TARGET arucotag_nodelet)
  set(ARUCOTAG_FUZZ_ROS_HARNESSES ros config)
endif()

function(arucotag_fuzz_harness target name)
  if(name IN_LIST ARUCOTAG_FUZZ_ROS_HARNESSES)
    target_include_directories(${target} PRIVATE ${ARUCOTAG_ROS_INCLUDES})
    target_include_directories(${target} SYSTEM PRIVATE ${catkin_INCLUDE_DIRS})
    target_link_libraries(${target} arucotag_nodelet ${catkin_LIBRARIES})
    add_dependencies(${target} ${PROJECT_NAME}_generate_messages_cpp ${PROJECT_NAME}_gencfg)
  else()
    target_link_libraries(${target} arucotag_core)
  endif()
endfunction()

foreach(name ${ARUCOTAG_FUZZ_CORE_HARNESSES} ${ARUCOTAG_FUZZ_ROS_HARNESSES})
  if(ARUCOTAG_FUZZ)
    add_executable(fuzz_${name} test/fuzz/fuzz_${name}.cpp)
    target_link_options(fuzz_${name} PRIVATE -fsanitize=fuzzer)
    arucotag_fuzz_harness(fuzz_${name} ${name})
  elseif(CATKIN_ENABLE_TESTING)
    catkin_add_gtest(test_fuzz_${name} test/fuzz/fuzz_${name}.cpp test/fuzz/replay.cpp)
    arucotag_fuzz_harness(test_fuzz_${name} ${name})
    target_link_libraries(test_fuzz_${name} ${GTEST_MAIN_LIBRARIES})
    target_compile_definitions(test_fuzz_${name} PRIVATE
      ARUCOTAG_FUZZ_CORPUS="${CMAKE_CURRENT_SOURCE_DIR}/test/fuzz/corpus/${name}")
  endif()
endforeach()

if(ARUCOTAG_FUZZ AND TARGET arucotag_nodelet)
  # Writes the starting seeds (test/fuzz/make_seeds.cpp); run by hand, not by the fuzzer.
  add_executable(fuzz_make_seeds test/fuzz/make_seeds.cpp)
  target_include_directories(fuzz_make_seeds PRIVATE ${ARUCOTAG_ROS_INCLUDES})
  target_include_directories(fuzz_make_seeds SYSTEM PRIVATE ${catkin_INCLUDE_DIRS})
  target_link_libraries(fuzz_make_seeds arucotag_nodelet arucotag_sim ${catkin_LIBRARIES})
  add_dependencies(fuzz_make_seeds ${PROJECT_NAME}_gencfg)
endif()
