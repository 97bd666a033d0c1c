# DAQP (dual active-set QP solver, D. Arnström, MIT licence): the MPC's QP solver (c_src/src/mpc_qp_daqp.c).
#
# Its C sources come from the pinned PyPI source distribution daqp==0.11.0 (which ships csrc/), fetched
# hash-pinned by scripts/fetch_daqp.sh (cmake/fetch_sdist.py: the exact file, its SHA-256 checked before
# it is kept, nothing of it executed) into DDYN_THIRD_PARTY_DIR, unpacked into this build directory and
# checked against the committed manifest cmake/daqp-0.11.0.sha256, again before every build
# (cmake/third_party.cmake); nothing of it is copied into the repository. Only the solver core is
# compiled: daqp.c, auxiliary.c, factorization.c allocate nothing (the setup in api.c/utils.c mallocs;
# mpc_qp_daqp.c replaces it with a static workspace). The licence is installed beside the library.
#
# Offline: put daqp-0.11.0.tar.gz into DDYN_THIRD_PARTY_DIR; it is used when its hash matches.
include(GNUInstallDirs)
include(${CMAKE_CURRENT_LIST_DIR}/third_party.cmake)
set(DDYN_DAQP_VERSION 0.11.0)
set(DDYN_DAQP_SHA256 2f27baf18d2acca14186498e651b34e0bed455627e777d3fd8ba655e7e40f920)
option(DDYN_QP_FLOAT32 "Build DAQP and the MPC's DAQP workspace in float32 (DAQP_SINGLE_PRECISION)" OFF)

ddyn_third_party_sdist(daqp ${DDYN_DAQP_VERSION} ${DDYN_DAQP_SHA256} DDYN_DAQP_SOURCE_DIR
                       FETCH_SCRIPT "${PROJECT_SOURCE_DIR}/scripts/fetch_daqp.sh")
# for the test of the checks (tests/c/CMakeLists.txt), which lives in another directory scope
set_property(GLOBAL PROPERTY DDYN_DAQP_SOURCE_DIR "${DDYN_DAQP_SOURCE_DIR}")
set_property(GLOBAL PROPERTY DDYN_DAQP_MANIFEST "${PROJECT_SOURCE_DIR}/cmake/daqp-${DDYN_DAQP_VERSION}.sha256")

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
add_dependencies(ddyn_daqp ddyn_daqp_verify) # the unpacked tree re-checked before every build
install(FILES "${DDYN_DAQP_SOURCE_DIR}/LICENSE" DESTINATION ${CMAKE_INSTALL_DATADIR}/ddyn RENAME LICENSE.daqp)
