# Injected into Pulse's configure by envs/pulse/build.sh with -DCMAKE_PROJECT_INCLUDE=<this file>,
# so Pulse's source tree is never edited. CMake includes it right after Pulse's project() call;
# it defers the real work to the end of the top-level CMakeLists.txt, when target Pulse exists.
#
# With -DCMAKE_UNITY_BUILD=ON two groups of Pulse's sources cannot share a unity translation unit:
#   - protobuf-generated *.pb.cc (each defines a file-static `schemas[]`: duplicate definitions);
#   - engine/io/protobuf/*.cpp (a forward-declared pulse::PBEnvironment becomes an incomplete type).
# They are marked SKIP_UNITY_BUILD_INCLUSION (compiled alone); everything else is batched.
# Needs CMake >= 3.19 (cmake_language(DEFER), set_source_files_properties(TARGET_DIRECTORY)).
if(NOT PROJECT_NAME STREQUAL "Pulse")
  return()
endif()
include_guard(GLOBAL)

function(_twinfalsify_pulse_unity_exclusions)
  if(NOT TARGET Pulse)
    message(FATAL_ERROR "unity-exclusions.cmake: no target Pulse at the end of the configure")
  endif()
  get_target_property(_srcs Pulse SOURCES)
  get_target_property(_dir Pulse SOURCE_DIR)
  set(_n 0)
  foreach(_s IN LISTS _srcs)
    if(_s MATCHES "\\.pb\\.cc$" OR _s MATCHES "engine/io/protobuf/")
      if(NOT IS_ABSOLUTE "${_s}")
        set(_s "${_dir}/${_s}")
      endif()
      set_source_files_properties("${_s}" TARGET_DIRECTORY Pulse
                                  PROPERTIES SKIP_UNITY_BUILD_INCLUSION ON)
      math(EXPR _n "${_n} + 1")
    endif()
  endforeach()
  if(_n EQUAL 0)
    message(FATAL_ERROR "unity-exclusions.cmake: no *.pb.cc or engine/io/protobuf/ source in Pulse")
  endif()
  message(STATUS "twinfalsify: ${_n} sources of target Pulse excluded from unity batches")
endfunction()

cmake_language(DEFER DIRECTORY "${CMAKE_SOURCE_DIR}" CALL _twinfalsify_pulse_unity_exclusions)
