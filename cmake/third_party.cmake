# Third-party C sources from pinned PyPI source distributions, never copied into the repository:
#   ddyn_third_party_sdist(<name> <version> <sha256> <out_dir_var> [FETCH_SCRIPT <script>])
# 1. the archive DDYN_THIRD_PARTY_DIR/<name>-<version>.tar.gz is used only with the pinned SHA-256;
#    a missing or wrong one is fetched by cmake/fetch_sdist.py (or FETCH_SCRIPT), which downloads the
#    exact file from the index and checks the hash before the file is kept (nothing of it runs);
# 2. it is unpacked into the build directory, and the unpacked tree is checked against the committed
#    manifest cmake/<name>-<version>.sha256 (every file's SHA-256, no extra files); a tree that does
#    not match is unpacked again from the verified archive;
# 3. a target ddyn_<name>_verify re-checks the tree against the manifest at every build; the caller
#    makes its library depend on it, so a source edited after configure is refused before it compiles.
# Offline: put the archive into DDYN_THIRD_PARTY_DIR; it is used when its hash matches.
include_guard(GLOBAL)
include(${CMAKE_CURRENT_LIST_DIR}/verify_manifest.cmake)
set(DDYN_THIRD_PARTY_DIR "${PROJECT_SOURCE_DIR}/build/third_party" CACHE PATH
    "Download cache of third-party source archives (pinned PyPI sdists: DAQP, Monocypher)")

function(ddyn_third_party_sdist name version sha256 out_dir_var)
  cmake_parse_arguments(ARG "" "FETCH_SCRIPT" "" ${ARGN})
  set(_archive "${DDYN_THIRD_PARTY_DIR}/${name}-${version}.tar.gz")
  set(_manifest "${PROJECT_SOURCE_DIR}/cmake/${name}-${version}.sha256")
  set(_ok FALSE)
  if(EXISTS "${_archive}")
    file(SHA256 "${_archive}" _have)
    if(_have STREQUAL sha256)
      set(_ok TRUE)
    else()
      message(WARNING "${_archive} has SHA-256 ${_have}, not ${sha256}: fetching it again")
      file(REMOVE "${_archive}")
    endif()
  endif()
  if(NOT _ok)
    if(ARG_FETCH_SCRIPT)
      execute_process(COMMAND bash "${ARG_FETCH_SCRIPT}" "${DDYN_THIRD_PARTY_DIR}" RESULT_VARIABLE _rc)
    else()
      if(DEFINED ENV{DDYN_PYTHON})
        set(_py "$ENV{DDYN_PYTHON}")
      elseif(EXISTS "${PROJECT_SOURCE_DIR}/.venv/bin/python")
        set(_py "${PROJECT_SOURCE_DIR}/.venv/bin/python")
      else()
        set(_py python3)
      endif()
      execute_process(COMMAND "${_py}" "${PROJECT_SOURCE_DIR}/cmake/fetch_sdist.py" ${name} ${version} ${sha256}
                              "${DDYN_THIRD_PARTY_DIR}" RESULT_VARIABLE _rc)
    endif()
    if(NOT _rc EQUAL 0 OR NOT EXISTS "${_archive}")
      message(FATAL_ERROR "cannot fetch ${name} ${version}: put ${name}-${version}.tar.gz (SHA-256 ${sha256}) "
                          "into ${DDYN_THIRD_PARTY_DIR}")
    endif()
    file(SHA256 "${_archive}" _have)
    if(NOT _have STREQUAL sha256)
      message(FATAL_ERROR "${_archive}: SHA-256 ${_have}, expected ${sha256}")
    endif()
  endif()

  set(_src "${CMAKE_BINARY_DIR}/third_party/${name}-${version}")
  set(_problems "not unpacked yet")
  if(EXISTS "${_src}")
    ddyn_verify_manifest("${_manifest}" "${_src}" _problems)
    if(NOT _problems STREQUAL "")
      message(WARNING "${_src} does not match ${_manifest} (${_problems}): unpacking the verified archive again")
    endif()
  endif()
  if(NOT _problems STREQUAL "")
    file(REMOVE_RECURSE "${_src}")
    file(ARCHIVE_EXTRACT INPUT "${_archive}" DESTINATION "${CMAKE_BINARY_DIR}/third_party")
    ddyn_verify_manifest("${_manifest}" "${_src}" _problems)
    if(NOT _problems STREQUAL "")
      message(FATAL_ERROR "${_archive} unpacks to a tree that does not match ${_manifest}: ${_problems}")
    endif()
  endif()
  if(NOT TARGET ddyn_${name}_verify)
    add_custom_target(ddyn_${name}_verify
                      COMMAND ${CMAKE_COMMAND} -DMANIFEST=${_manifest} -DROOT=${_src}
                              -P ${PROJECT_SOURCE_DIR}/cmake/verify_manifest.cmake
                      COMMENT "checking ${name} ${version} against ${name}-${version}.sha256" VERBATIM)
  endif()
  set(${out_dir_var} "${_src}" PARENT_SCOPE)
endfunction()
