/* The drive-by-wire authentication key from a file (dbw_auth_key.h). */
#define _POSIX_C_SOURCE 200809L
#include "dbw_auth_key.h"

#include <fcntl.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

const char *ddyn_dbw_auth_key_path(const char *configured)
{
    const char *env;
    if (configured != NULL && configured[0] != '\0') {
        return configured;
    }
    env = getenv(DDYN_DBW_KEY_FILE_ENV);
    return env != NULL && env[0] != '\0' ? env : NULL;
}

static int hex_value(char c)
{
    if (c >= '0' && c <= '9') {
        return c - '0';
    }
    if (c >= 'a' && c <= 'f') {
        return c - 'a' + 10;
    }
    if (c >= 'A' && c <= 'F') {
        return c - 'A' + 10;
    }
    return -1;
}

static ddyn_status refuse(uint8_t *key, char *text, const char **why, const char *reason)
{
    memset(key, 0, DDYN_DBW_AUTH_KEY_LEN);
    memset(text, 0, 2u * DDYN_DBW_AUTH_KEY_LEN + 16u);
    if (why != NULL) {
        *why = reason;
    }
    return DDYN_ERR_CONFIG;
}

ddyn_status ddyn_dbw_auth_read_key_file(const char *path, uint8_t key[DDYN_DBW_AUTH_KEY_LEN], const char **why)
{
    char text[2u * DDYN_DBW_AUTH_KEY_LEN + 16u];
    struct stat st;
    ssize_t n;
    size_t i;
    int fd;
    if (path == NULL || key == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    memset(text, 0, sizeof text);
    fd = open(path, O_RDONLY | O_CLOEXEC | O_NOFOLLOW);
    if (fd < 0) {
        return refuse(key, text, why, "cannot open the key file");
    }
    if (fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {
        (void)close(fd);
        return refuse(key, text, why, "the key file is not a regular file");
    }
    if ((st.st_mode & (S_IRWXG | S_IRWXO)) != 0) {
        (void)close(fd);
        return refuse(key, text, why, "the key file is accessible to group or others (chmod 600)");
    }
    n = read(fd, text, sizeof text - 1u);
    (void)close(fd);
    if (n < (ssize_t)(2u * DDYN_DBW_AUTH_KEY_LEN)) {
        return refuse(key, text, why, "the key file holds fewer than 64 hex digits");
    }
    for (i = 2u * DDYN_DBW_AUTH_KEY_LEN; i < (size_t)n; ++i) {
        if (text[i] != '\n' && text[i] != '\r' && text[i] != ' ' && text[i] != '\t') {
            return refuse(key, text, why, "the key file holds more than 64 hex digits");
        }
    }
    for (i = 0; i < DDYN_DBW_AUTH_KEY_LEN; ++i) {
        int hi = hex_value(text[2u * i]), lo = hex_value(text[2u * i + 1u]);
        if (hi < 0 || lo < 0) {
            return refuse(key, text, why, "the key file holds a character that is not a hex digit");
        }
        key[i] = (uint8_t)((hi << 4) | lo);
    }
    memset(text, 0, sizeof text);
    if (why != NULL) {
        *why = NULL;
    }
    return DDYN_OK;
}
