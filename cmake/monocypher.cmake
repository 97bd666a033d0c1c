# Monocypher 4.0.3 (Loup Vaillant, BSD-2-Clause OR CC0-1.0): the keyed BLAKE2b behind the drive-by-wire
# frame authentication (c_src/src/dbw_auth.c). Its two C files ship in the PyPI sdist of the Python
# binding pymonocypher 4.0.3.5 (monocypher.c, monocypher.h: Monocypher's own release files), fetched
# hash-pinned and checked against the committed manifest cmake/pymonocypher-4.0.3.5.sha256 at configure
# time and before every build (cmake/third_party.cmake), like DAQP. Only monocypher.c is compiled (the
# binding's c_monocypher.c and Python files are not): portable C99, no allocation, no OS calls, so it is
# part of the Cortex-M7 build. The licence is installed beside the library.
include(GNUInstallDirs)
include(${CMAKE_CURRENT_LIST_DIR}/third_party.cmake)
set(DDYN_MONOCYPHER_SDIST_VERSION 4.0.3.5)
set(DDYN_MONOCYPHER_SDIST_SHA256 b6f96c4fa56212a7c13aee8fc27a89d7531b622ce8aabbd6e82a9d2e93071d71)
ddyn_third_party_sdist(pymonocypher ${DDYN_MONOCYPHER_SDIST_VERSION} ${DDYN_MONOCYPHER_SDIST_SHA256}
                       DDYN_MONOCYPHER_SOURCE_DIR)
set_property(GLOBAL PROPERTY DDYN_MONOCYPHER_SOURCE_DIR "${DDYN_MONOCYPHER_SOURCE_DIR}")

# only monocypher.c and monocypher.h, seen from a directory of their own (the sdist's top level also
# holds the binding's sources)
set(_mc_inc "${CMAKE_BINARY_DIR}/third_party/monocypher-include")
file(MAKE_DIRECTORY "${_mc_inc}")
configure_file("${DDYN_MONOCYPHER_SOURCE_DIR}/monocypher.h" "${_mc_inc}/monocypher.h" COPYONLY)
add_library(ddyn_monocypher STATIC ${DDYN_MONOCYPHER_SOURCE_DIR}/monocypher.c)
target_include_directories(ddyn_monocypher PUBLIC $<BUILD_INTERFACE:${_mc_inc}>)
# third-party code: its own warnings are not ours to fix (-w)
target_compile_options(ddyn_monocypher PRIVATE -w)
add_dependencies(ddyn_monocypher ddyn_pymonocypher_verify) # the unpacked tree re-checked before every build
install(FILES "${DDYN_MONOCYPHER_SOURCE_DIR}/LICENSE.txt" DESTINATION ${CMAKE_INSTALL_DATADIR}/ddyn
        RENAME LICENSE.monocypher)
