# ctest third_party_sources_are_verified (tests/c/CMakeLists.txt): the checks of cmake/third_party.cmake
# refuse what they must.
#   cmake -DSRC=<unpacked daqp tree> -DMANIFEST=<cmake/daqp-0.11.0.sha256> -DWORK=<scratch dir>
#         -DFETCH=<cmake/fetch_sdist.py> -DPYTHON=<python> -P test_third_party.cmake
# 1. the unpacked tree matches its manifest; a copy with one byte changed in a source, or with an extra
#    header dropped in, does not (and the build-time check, run as a script, fails on it);
# 2. fetch_sdist.py, pointed at a local index whose archive does not have the pinned hash, refuses it
#    and keeps nothing; with the right hash it keeps the file; it never unpacks or runs the archive.
include(${CMAKE_CURRENT_LIST_DIR}/verify_manifest.cmake)
file(REMOVE_RECURSE "${WORK}")
file(MAKE_DIRECTORY "${WORK}")

ddyn_verify_manifest("${MANIFEST}" "${SRC}" _p)
if(NOT _p STREQUAL "")
  message(FATAL_ERROR "the unpacked tree does not match its manifest: ${_p}")
endif()

file(COPY "${SRC}/" DESTINATION "${WORK}/edited")
file(APPEND "${WORK}/edited/csrc/src/daqp.c" " ")
ddyn_verify_manifest("${MANIFEST}" "${WORK}/edited" _p)
if(NOT _p MATCHES "csrc/src/daqp.c has SHA-256")
  message(FATAL_ERROR "an edited source was not refused: '${_p}'")
endif()
execute_process(COMMAND ${CMAKE_COMMAND} -DMANIFEST=${MANIFEST} -DROOT=${WORK}/edited
                        -P ${CMAKE_CURRENT_LIST_DIR}/verify_manifest.cmake RESULT_VARIABLE _rc OUTPUT_QUIET ERROR_QUIET)
if(_rc EQUAL 0)
  message(FATAL_ERROR "the build-time check passed an edited source")
endif()

file(COPY "${SRC}/" DESTINATION "${WORK}/extra")
file(WRITE "${WORK}/extra/csrc/include/stdlib.h" "/* a shadowing header */\n")
ddyn_verify_manifest("${MANIFEST}" "${WORK}/extra" _p)
if(NOT _p MATCHES "unlisted file csrc/include/stdlib.h")
  message(FATAL_ERROR "an extra header was not refused: '${_p}'")
endif()

# a local PEP 503 index with one archive
file(MAKE_DIRECTORY "${WORK}/index/demo" "${WORK}/payload/demo-1.0")
file(WRITE "${WORK}/payload/demo-1.0/setup.py" "open('${WORK}/RAN', 'w').write('x')\n")
file(ARCHIVE_CREATE OUTPUT "${WORK}/index/demo/demo-1.0.tar.gz" PATHS "${WORK}/payload/demo-1.0" FORMAT gnutar
     COMPRESSION GZip)
file(SHA256 "${WORK}/index/demo/demo-1.0.tar.gz" _good)
file(WRITE "${WORK}/index/demo/index.html" "<html><body><a href=\"demo-1.0.tar.gz\">demo-1.0.tar.gz</a></body></html>\n")
set(ENV{DDYN_INDEX_URL} "file://${WORK}/index")
set(_bad "0000000000000000000000000000000000000000000000000000000000000000")
execute_process(COMMAND ${PYTHON} ${FETCH} demo 1.0 ${_bad} ${WORK}/cache RESULT_VARIABLE _rc OUTPUT_QUIET ERROR_VARIABLE _err)
if(_rc EQUAL 0 OR EXISTS "${WORK}/cache/demo-1.0.tar.gz" OR NOT _err MATCHES "not the pinned")
  message(FATAL_ERROR "fetch_sdist.py kept an archive with the wrong hash (exit ${_rc})")
endif()
file(GLOB _left "${WORK}/cache/*" "${WORK}/cache/.*")
if(_left)
  message(FATAL_ERROR "fetch_sdist.py left files behind after refusing: ${_left}")
endif()
execute_process(COMMAND ${PYTHON} ${FETCH} demo 1.0 ${_good} ${WORK}/cache RESULT_VARIABLE _rc ERROR_VARIABLE _err)
if(NOT _rc EQUAL 0 OR NOT EXISTS "${WORK}/cache/demo-1.0.tar.gz")
  message(FATAL_ERROR "fetch_sdist.py refused the archive with the pinned hash (exit ${_rc}): ${_err}")
endif()
if(EXISTS "${WORK}/RAN")
  message(FATAL_ERROR "the archive's setup.py ran")
endif()
message(STATUS "third-party checks refuse an edited source, an extra header and a wrong archive hash")
