# The fixed TEST key of the drive-by-wire frame authentication, made at build time (never committed,
# never for a car): SHA-256 of a fixed phrase, written as
#   ${CMAKE_BINARY_DIR}/dbw_test_key/ddyn_dbw_test_key.h   (const bytes, for the cmocka tests)
#   ${CMAKE_BINARY_DIR}/dbw_test_key/dbw_test.key          (64 hex digits, mode 0600, the key-file format)
# scripts/fuzz_can.sh derives the same key the same way. A car's key comes from a file outside the
# repository (DDYN_DBW_KEY_FILE, docs/can.md).
string(SHA256 DDYN_DBW_TEST_KEY_HEX "ddyn drive-by-wire TEST key: never on a car")
set(DDYN_DBW_TEST_KEY_DIR "${CMAKE_BINARY_DIR}/dbw_test_key")
string(REGEX REPLACE "([0-9a-f][0-9a-f])" "0x\\1u, " _bytes "${DDYN_DBW_TEST_KEY_HEX}")
file(WRITE "${DDYN_DBW_TEST_KEY_DIR}/ddyn_dbw_test_key.h.tmp"
     "/* GENERATED FILE - DO NOT EDIT. Made by cmake/dbw_test_key.cmake at configure time: the drive-by-wire\n"
     " * authentication's fixed TEST key (SHA-256 of a fixed phrase). Never for a car. */\n"
     "#ifndef DDYN_DBW_TEST_KEY_H\n#define DDYN_DBW_TEST_KEY_H\n#include <stdint.h>\n"
     "static const uint8_t DDYN_DBW_TEST_KEY[32] = {${_bytes}};\n#endif\n")
file(COPY_FILE "${DDYN_DBW_TEST_KEY_DIR}/ddyn_dbw_test_key.h.tmp" "${DDYN_DBW_TEST_KEY_DIR}/ddyn_dbw_test_key.h"
     ONLY_IF_DIFFERENT)
file(REMOVE "${DDYN_DBW_TEST_KEY_DIR}/ddyn_dbw_test_key.h.tmp")
file(WRITE "${DDYN_DBW_TEST_KEY_DIR}/dbw_test.key" "${DDYN_DBW_TEST_KEY_HEX}\n")
file(CHMOD "${DDYN_DBW_TEST_KEY_DIR}/dbw_test.key" PERMISSIONS OWNER_READ OWNER_WRITE)
