# The ROS wheels from PyPI export *__rosidl_generator_py targets whose INTERFACE_INCLUDE_DIRECTORIES
# name the Python and NumPy header folders of the machine that built them
# (/opt/python/cp311-cp311/...). Those folders do not exist here and make CMake's generate step
# fail. Our own Python extension gets this machine's Python and NumPy headers from
# rosidl_generator_py (found for -DPython3_EXECUTABLE), so include folders that do not exist are
# dropped from every imported target of this directory.
function(gls_drop_missing_include_dirs)
  get_property(targets DIRECTORY PROPERTY IMPORTED_TARGETS)
  foreach(target IN LISTS targets)
    get_target_property(dirs ${target} INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT dirs)
      continue()
    endif()
    set(kept "")
    set(dropped FALSE)
    foreach(dir IN LISTS dirs)
      if(dir MATCHES "^\\$<" OR EXISTS "${dir}")
        list(APPEND kept "${dir}")
      else()
        set(dropped TRUE)
      endif()
    endforeach()
    if(dropped)
      set_target_properties(${target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${kept}")
    endif()
  endforeach()
endfunction()
