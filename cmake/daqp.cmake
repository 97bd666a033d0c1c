# DAQP (dual active-set QP solver, D. Arnström, MIT licence): the MPC's QP solver (c_src/src/mpc_qp_daqp.c).
#
# Its C sources come from the pinned PyPI source distribution daqp==0.11.0 (which ships csrc/),
# fetched once with pip (scripts/fetch_daqp.sh) into DDYN_THIRD_PARTY_DIR, checked against its SHA-256 and unpacked into this build
# directory; nothing of it is copied into the repository. Only the solver core is compiled: daqp.c,
# auxiliary.c, factorization.c allocate nothing (the setup in api.c/utils.c mallocs; mpc_qp_daqp.c
# replaces it with a static workspace). The licence is installed beside the library.
#
# Offline: put daqp-0.11.0.tar.gz (from `pip download daqp==0.11.0 --no-binary :all: --no-deps`) into
# DDYN_THIRD_PARTY_DIR; it is used when its hash matches.
include(GNUInstallDirs)
set(DDYN_DAQP_VERSION 0.11.0)
set(DDYN_DAQP_SHA256 2f27baf18d2acca14186498e651b34e0bed455627e777d3fd8ba655e7e40f920)
set(DDYN_THIRD_PARTY_DIR "${PROJECT_SOURCE_DIR}/build/third_party" CACHE PATH
    "Download cache of third-party source archives (DAQP's sdist)")
option(DDYN_QP_FLOAT32 "Build DAQP and the MPC's DAQP workspace in float32 (DAQP_SINGLE_PRECISION)" OFF)

set(_daqp_archive "${DDYN_THIRD_PARTY_DIR}/daqp-${DDYN_DAQP_VERSION}.tar.gz")
set(_daqp_ok FALSE)
if(EXISTS "${_daqp_archive}")
  file(SHA256 "${_daqp_archive}" _daqp_have)
  if(_daqp_have STREQUAL DDYN_DAQP_SHA256)
    set(_daqp_ok TRUE)
  else()
    message(WARNING "${_daqp_archive} has SHA-256 ${_daqp_have}, not ${DDYN_DAQP_SHA256}: fetching it again")
    file(REMOVE "${_daqp_archive}")
  endif()
endif()
if(NOT _daqp_ok)
  # pip from the configured index (PyPI or its mirror), hash-checked by the script and again here
  execute_process(COMMAND bash "${PROJECT_SOURCE_DIR}/scripts/fetch_daqp.sh" "${DDYN_THIRD_PARTY_DIR}"
                  RESULT_VARIABLE _daqp_rc)
  if(NOT _daqp_rc EQUAL 0 OR NOT EXISTS "${_daqp_archive}")
    message(FATAL_ERROR "cannot fetch DAQP ${DDYN_DAQP_VERSION} (scripts/fetch_daqp.sh): put "
                        "daqp-${DDYN_DAQP_VERSION}.tar.gz into ${DDYN_THIRD_PARTY_DIR} (see cmake/daqp.cmake)")
  endif()
  file(SHA256 "${_daqp_archive}" _daqp_have)
  if(NOT _daqp_have STREQUAL DDYN_DAQP_SHA256)
    message(FATAL_ERROR "${_daqp_archive}: SHA-256 ${_daqp_have}, expected ${DDYN_DAQP_SHA256}")
  endif()
endif()

set(DDYN_DAQP_SOURCE_DIR "${CMAKE_BINARY_DIR}/third_party/daqp-${DDYN_DAQP_VERSION}")
if(NOT EXISTS "${DDYN_DAQP_SOURCE_DIR}/csrc/src/daqp.c")
  file(ARCHIVE_EXTRACT INPUT "${_daqp_archive}" DESTINATION "${CMAKE_BINARY_DIR}/third_party")
endif()

add_library(ddyn_daqp STATIC
  ${DDYN_DAQP_SOURCE_DIR}/csrc/src/daqp.c
  ${DDYN_DAQP_SOURCE_DIR}/csrc/src/auxiliary.c
  ${DDYN_DAQP_SOURCE_DIR}/csrc/src/factorization.c)
# third-party code: its own warnings are not ours to fix (-w); C99 like the rest
target_include_directories(ddyn_daqp PUBLIC $<BUILD_INTERFACE:${DDYN_DAQP_SOURCE_DIR}/csrc/include>)
target_compile_options(ddyn_daqp PRIVATE -w)
if(DDYN_QP_FLOAT32)
  target_compile_definitions(ddyn_daqp PUBLIC DAQP_SINGLE_PRECISION DDYN_QP_FLOAT32)
endif()
target_link_libraries(ddyn_daqp PUBLIC m)
install(FILES "${DDYN_DAQP_SOURCE_DIR}/LICENSE" DESTINATION ${CMAKE_INSTALL_DATADIR}/ddyn RENAME LICENSE.daqp)
