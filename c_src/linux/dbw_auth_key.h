/*
 * dbw_auth_key.h - the drive-by-wire authentication key from a file (Linux; not in the Cortex-M7 build,
 * where the key comes from the target's secure storage and is handed to ddyn_dbw_auth_enable()).
 *
 * The key lives OUTSIDE the repository, in a file named by the configuration or by the environment
 * variable DDYN_DBW_KEY_FILE: 64 hexadecimal digits (32 bytes), optionally followed by whitespace.
 * The file must be a regular file readable by its owner only (mode 0600 or 0400): a key that other
 * users can read is refused. Tests use the fixed test key made at build time
 * (<build>/dbw_test_key/dbw_test.key, cmake/dbw_test_key.cmake), never a car's.
 */
#ifndef DDYN_DBW_AUTH_KEY_H
#define DDYN_DBW_AUTH_KEY_H

#include <stdint.h>

#include "ddyn/dbw.h"

#ifdef __cplusplus
extern "C" {
#endif

#define DDYN_DBW_KEY_FILE_ENV "DDYN_DBW_KEY_FILE"

/* `configured` when it is non-NULL and non-empty, else $DDYN_DBW_KEY_FILE, else NULL (no key:
 * authentication off). */
const char *ddyn_dbw_auth_key_path(const char *configured);

/* Read a key file into key[32]. DDYN_OK; DDYN_ERR_ARGUMENT for NULL; DDYN_ERR_CONFIG for a file that
 * cannot be opened, is not a regular file, is readable by group or others, or does not hold exactly
 * 64 hex digits (then *why, if non-NULL, names the reason). The key buffer is wiped on failure. */
ddyn_status ddyn_dbw_auth_read_key_file(const char *path, uint8_t key[DDYN_DBW_AUTH_KEY_LEN], const char **why);

#ifdef __cplusplus
}
#endif

#endif /* DDYN_DBW_AUTH_KEY_H */
