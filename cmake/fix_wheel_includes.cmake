# Repair the include directories baked into the ROS 2 Jazzy PyPI wheels' exported CMake targets.
#
# The wheels' `<pkg>::<pkg>__rosidl_generator_py` imported targets carry the include dirs of the
# machine that built the wheels (/opt/python/cp311-cp311/include/python3.11 and its numpy include
# dir). CMake refuses targets whose INTERFACE_INCLUDE_DIRECTORIES name a non-existent path. Instead
# of editing the installed files in the venv, `make setup` passes this file as
#   -DCMAKE_PROJECT_INCLUDE=<repo>/cmake/fix_wheel_includes.cmake
# It runs after project(); it defers a function to the end of the top-level CMakeLists.txt (after
# every find_package) that, for every imported target, replaces non-existent include dirs:
#   .../include/pythonX.Y  -> this interpreter's include dir (sysconfig)
#   ...numpy...            -> numpy.get_include() of this interpreter
#   anything else missing  -> dropped (reported)
# A build against a system ROS (/opt/ros/jazzy) does not need and does not use this file.
cmake_minimum_required(VERSION 3.21)  # IMPORTED_TARGETS directory property

get_property(_tsfix_done GLOBAL PROPERTY TISSUE_SIM_WHEEL_INCLUDE_FIX)
if(NOT _tsfix_done)
  set_property(GLOBAL PROPERTY TISSUE_SIM_WHEEL_INCLUDE_FIX ON)

  if(NOT Python3_EXECUTABLE)
    find_program(Python3_EXECUTABLE NAMES python3 python REQUIRED)
  endif()
  execute_process(
    COMMAND "${Python3_EXECUTABLE}" -c
      "import sysconfig, numpy; print(sysconfig.get_paths()['include']); print(numpy.get_include())"
    OUTPUT_VARIABLE _tsfix_out
    RESULT_VARIABLE _tsfix_rc
    OUTPUT_STRIP_TRAILING_WHITESPACE)
  if(NOT _tsfix_rc EQUAL 0)
    message(FATAL_ERROR "fix_wheel_includes: ${Python3_EXECUTABLE} cannot report its include dir and numpy's")
  endif()
  string(REPLACE "\n" ";" _tsfix_out "${_tsfix_out}")
  list(GET _tsfix_out 0 TISSUE_SIM_PYTHON_INCLUDE)
  list(GET _tsfix_out 1 TISSUE_SIM_NUMPY_INCLUDE)
  if(NOT EXISTS "${TISSUE_SIM_PYTHON_INCLUDE}/Python.h")
    message(FATAL_ERROR
      "fix_wheel_includes: no Python.h in ${TISSUE_SIM_PYTHON_INCLUDE}. "
      "Install the Python development headers (Debian/Ubuntu: apt-get install python3-dev).")
  endif()

  function(_tissue_sim_fix_wheel_includes)
    get_property(_targets DIRECTORY "${CMAKE_SOURCE_DIR}" PROPERTY IMPORTED_TARGETS)
    set(_fixed 0)
    foreach(_t IN LISTS _targets)
      get_target_property(_dirs ${_t} INTERFACE_INCLUDE_DIRECTORIES)
      if(NOT _dirs)
        continue()
      endif()
      set(_new "")
      set(_changed FALSE)
      foreach(_d IN LISTS _dirs)
        if(_d MATCHES "^\\$<" OR EXISTS "${_d}")
          list(APPEND _new "${_d}")
        elseif(_d MATCHES "/include/python[0-9]")
          list(APPEND _new "${TISSUE_SIM_PYTHON_INCLUDE}")
          set(_changed TRUE)
        elseif(_d MATCHES "numpy")
          list(APPEND _new "${TISSUE_SIM_NUMPY_INCLUDE}")
          set(_changed TRUE)
        else()
          message(STATUS "fix_wheel_includes: ${_t}: dropping non-existent include dir ${_d}")
          set(_changed TRUE)
        endif()
      endforeach()
      if(_changed)
        list(REMOVE_DUPLICATES _new)
        set_target_properties(${_t} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_new}")
        math(EXPR _fixed "${_fixed} + 1")
      endif()
    endforeach()
    message(STATUS "fix_wheel_includes: repaired include dirs of ${_fixed} imported targets "
                   "(python: ${TISSUE_SIM_PYTHON_INCLUDE}; numpy: ${TISSUE_SIM_NUMPY_INCLUDE})")
  endfunction()

  cmake_language(DEFER DIRECTORY "${CMAKE_SOURCE_DIR}" CALL _tissue_sim_fix_wheel_includes)
endif()
