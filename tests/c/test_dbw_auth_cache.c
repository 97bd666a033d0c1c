/*
 * The prepared MAC states of the frame authentication (c_src/src/dbw_auth.c, issue 35): per frame, the
 * keyed BLAKE2b state after the key block and the identifier bytes is made once by ddyn_dbw_auth_init,
 * and each MAC goes on from a copy of it (one compression instead of two). Here that MAC is checked
 * against Monocypher's one-shot crypto_blake2b_keyed over the whole message, for many keys, every
 * frame and many payloads and freshness values; a state prepared for the wrong frame, from the wrong
 * bytes or left from a previous key would fail. The key and the states are wiped on disable.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include <cmocka.h>

#include "ddyn/dbw.h"
#include "monocypher.h"

#define KEYS 24u
#define MESSAGES 40u

static uint32_t seed = 0x2545F491u;

static uint8_t next_byte(void)
{
    seed = seed * 1664525u + 1013904223u;
    return (uint8_t)(seed >> 24);
}

static void fill(uint8_t *p, size_t n)
{
    size_t i;
    for (i = 0; i < n; ++i) {
        p[i] = next_byte();
    }
}

/* the reference, written from the protocol's description (ddyn/dbw.h) straight onto Monocypher's one-shot
 * keyed BLAKE2b: identifier (2 bytes LE), payload, freshness (8 bytes LE); 8-byte digest, its first 24 bits */
static uint32_t reference_mac(const uint8_t key[DDYN_DBW_AUTH_KEY_LEN], uint32_t can_id,
                              const uint8_t data[DDYN_DBW_FRAME_LEN], uint64_t freshness)
{
    uint8_t msg[2u + DDYN_DBW_FRAME_LEN + 8u], digest[8];
    unsigned i;
    msg[0] = (uint8_t)(can_id & 0xFFu);
    msg[1] = (uint8_t)(can_id >> 8);
    memcpy(&msg[2], data, DDYN_DBW_FRAME_LEN);
    for (i = 0; i < 8u; ++i) {
        msg[2u + DDYN_DBW_FRAME_LEN + i] = (uint8_t)(freshness >> (8u * i));
    }
    crypto_blake2b_keyed(digest, sizeof digest, key, DDYN_DBW_AUTH_KEY_LEN, msg, sizeof msg);
    return ((uint32_t)digest[0] << 16) | ((uint32_t)digest[1] << 8) | (uint32_t)digest[2];
}

static void key_number(unsigned n, uint8_t key[DDYN_DBW_AUTH_KEY_LEN])
{
    if (n == 0u) {
        memset(key, 0x00, DDYN_DBW_AUTH_KEY_LEN);
    } else if (n == 1u) {
        memset(key, 0xFF, DDYN_DBW_AUTH_KEY_LEN);
    } else {
        fill(key, DDYN_DBW_AUTH_KEY_LEN);
    }
}

static uint64_t freshness_number(unsigned m)
{
    uint64_t v = 0u;
    unsigned i;
    if (m == 0u) {
        return 0u;
    }
    if (m == 1u) {
        return UINT64_MAX;
    }
    if (m < 8u) {
        return (uint64_t)m - 1u; /* the first values a link sends */
    }
    for (i = 0; i < 8u; ++i) {
        v = (v << 8) | next_byte();
    }
    return v;
}

static void test_prepared_mac_equals_one_shot_keyed_blake2b(void **state)
{
    static ddyn_dbw_auth auth;
    uint8_t key[DDYN_DBW_AUTH_KEY_LEN], data[DDYN_DBW_FRAME_LEN];
    unsigned n, m, f, checked = 0u, differ_from_other_frame = 0u;
    (void)state;
    for (n = 0; n < KEYS; ++n) {
        key_number(n, key);
        ddyn_dbw_auth_init(&auth, key, 0u);
        for (m = 0; m < MESSAGES; ++m) {
            const uint64_t fresh = freshness_number(m);
            if (m == 2u) {
                memset(data, 0, sizeof data);
            } else {
                fill(data, sizeof data);
            }
            for (f = 0; f < DDYN_DBW_FRAME_COUNT; ++f) {
                const uint32_t id = ddyn_dbw_frame_id((ddyn_dbw_frame)f);
                const uint32_t want = reference_mac(key, id, data, fresh);
                const uint32_t got = ddyn_dbw_auth_frame_mac(&auth, (ddyn_dbw_frame)f, data, fresh);
                assert_int_equal(got, want);
                /* the one-shot public function agrees too */
                assert_int_equal(ddyn_dbw_auth_mac(key, id, data, fresh), want);
                /* and a second MAC from the same state gives the same (the state is copied, not used up) */
                assert_int_equal(ddyn_dbw_auth_frame_mac(&auth, (ddyn_dbw_frame)f, data, fresh), want);
                differ_from_other_frame +=
                    want != reference_mac(key, ddyn_dbw_frame_id((ddyn_dbw_frame)((f + 1u) % DDYN_DBW_FRAME_COUNT)),
                                          data, fresh);
                ++checked;
            }
        }
    }
    assert_int_equal(checked, KEYS * MESSAGES * DDYN_DBW_FRAME_COUNT);
    /* the identifier is part of the MAC: a state prepared for another frame would have failed above */
    assert_true(differ_from_other_frame > checked - 3u);
}

static void test_signed_authenticator_equals_encoded_with_the_key(void **state)
{
    static ddyn_dbw_auth auth;
    uint8_t key[DDYN_DBW_AUTH_KEY_LEN], data[DDYN_DBW_FRAME_LEN], a[DDYN_DBW_FRAME_LEN], b[DDYN_DBW_FRAME_LEN];
    unsigned m, f;
    (void)state;
    fill(key, sizeof key);
    ddyn_dbw_auth_init(&auth, key, 0u);
    for (m = 0; m < MESSAGES; ++m) {
        const uint64_t fresh = freshness_number(m);
        fill(data, sizeof data);
        for (f = 0; f < DDYN_DBW_FRAME_COUNT; ++f) {
            assert_int_equal(ddyn_dbw_auth_sign(&auth, (ddyn_dbw_frame)f, data, fresh, (uint8_t)m, a), DDYN_OK);
            assert_int_equal(ddyn_dbw_auth_encode(key, (ddyn_dbw_frame)f, data, fresh, (uint8_t)m, b), DDYN_OK);
            assert_memory_equal(a, b, DDYN_DBW_FRAME_LEN);
        }
    }
    assert_int_equal(ddyn_dbw_auth_sign(&auth, DDYN_DBW_FRAME_COUNT, data, 0u, 0u, a), DDYN_ERR_ARGUMENT);
    assert_int_equal(ddyn_dbw_auth_sign(NULL, DDYN_DBW_FRAME_COMMAND, data, 0u, 0u, a), DDYN_ERR_ARGUMENT);
}

static void test_a_new_key_replaces_the_prepared_states(void **state)
{
    static ddyn_dbw_auth auth;
    uint8_t k1[DDYN_DBW_AUTH_KEY_LEN], k2[DDYN_DBW_AUTH_KEY_LEN], data[DDYN_DBW_FRAME_LEN];
    unsigned f;
    (void)state;
    fill(k1, sizeof k1);
    fill(k2, sizeof k2);
    fill(data, sizeof data);
    ddyn_dbw_auth_init(&auth, k1, 0u);
    ddyn_dbw_auth_init(&auth, k2, 0u);
    for (f = 0; f < DDYN_DBW_FRAME_COUNT; ++f) {
        const uint32_t id = ddyn_dbw_frame_id((ddyn_dbw_frame)f);
        assert_int_equal(ddyn_dbw_auth_frame_mac(&auth, (ddyn_dbw_frame)f, data, 7u), reference_mac(k2, id, data, 7u));
    }
    /* no key: no states, no MAC, nothing signed */
    ddyn_dbw_auth_init(&auth, NULL, 0u);
    {
        static const ddyn_dbw_auth zero;
        assert_memory_equal(auth.mac_state, zero.mac_state, sizeof auth.mac_state);
    }
    assert_int_equal(ddyn_dbw_auth_frame_mac(&auth, DDYN_DBW_FRAME_COMMAND, data, 7u), 0u);
    {
        uint8_t a[DDYN_DBW_FRAME_LEN];
        assert_int_equal(ddyn_dbw_auth_sign(&auth, DDYN_DBW_FRAME_COMMAND, data, 7u, 0u, a), DDYN_ERR_NOT_READY);
    }
}

static void test_disable_wipes_the_key_and_its_states(void **state)
{
    static ddyn_dbw dbw;
    static const ddyn_dbw_auth zero;
    uint8_t key[DDYN_DBW_AUTH_KEY_LEN], data[DDYN_DBW_FRAME_LEN], a[DDYN_DBW_FRAME_LEN];
    uint32_t aid = 0u;
    unsigned f, w, nonzero = 0u;
    (void)state;
    fill(key, sizeof key);
    fill(data, sizeof data);
    assert_int_equal(ddyn_dbw_auth_enable(&dbw, key, 0u), DDYN_OK);
    for (f = 0; f < DDYN_DBW_FRAME_COUNT; ++f) {
        for (w = 0; w < DDYN_DBW_AUTH_STATE_WORDS; ++w) {
            nonzero += dbw.auth.mac_state[f][w] != 0u;
        }
    }
    assert_true(nonzero > 0u); /* the states were made */
    assert_int_equal(ddyn_dbw_authenticator(&dbw, DDYN_DBW_FRAME_COMMAND, data, &aid, a), DDYN_OK);
    ddyn_dbw_auth_disable(&dbw);
    assert_memory_equal(&dbw.auth, &zero, sizeof zero); /* key, states and all */
    assert_int_equal(ddyn_dbw_authenticator(&dbw, DDYN_DBW_FRAME_COMMAND, data, &aid, a), DDYN_ERR_NOT_READY);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_prepared_mac_equals_one_shot_keyed_blake2b),
        cmocka_unit_test(test_signed_authenticator_equals_encoded_with_the_key),
        cmocka_unit_test(test_a_new_key_replaces_the_prepared_states),
        cmocka_unit_test(test_disable_wipes_the_key_and_its_states),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
