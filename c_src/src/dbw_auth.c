/*
 * Frame authentication in the manner of AUTOSAR SecOC (ddyn/dbw.h, docs/can.md): a truncated MAC
 * over identifier, payload and a freshness value, carried by a separate authenticator frame.
 * The cryptography is Monocypher's keyed BLAKE2b (third-party, pinned and hash-checked:
 * cmake/monocypher.cmake); nothing here is hand-written crypto: this file only frames the message,
 * truncates the digest and keeps the freshness values. Portable C99, no allocation, bounded loops.
 */
#include <string.h>

#include "ddyn/dbw.h"
#include "ddyn_can.h"
#include "monocypher.h"

#define AUTH_STREAMS 3u
#define FRESH_MASK ((1u << DDYN_DBW_AUTH_FRESHNESS_BITS) - 1u)
#define MAC_MASK ((1u << DDYN_DBW_AUTH_MAC_BITS) - 1u)
#define AUTH_CHECKSUM_BYTE 7u

/* the authenticator identifier per sending node, and the node of every frame */
static const uint32_t AUTH_IDS[AUTH_STREAMS] = {DDYN_CAN_SEC_OC_CONTROLLER_FRAME_ID, DDYN_CAN_SEC_OC_DBW_FRAME_ID,
                                                DDYN_CAN_SEC_OC_SENSORS_FRAME_ID};
static const uint8_t FRAME_STREAM[DDYN_DBW_FRAME_COUNT] = {0u, 1u, 1u, 1u, 2u, 2u, 2u};

static int stream_of_id(uint32_t can_id)
{
    unsigned k;
    for (k = 0; k < AUTH_STREAMS; ++k) {
        if (AUTH_IDS[k] == can_id) {
            return (int)k;
        }
    }
    return -1;
}

uint32_t ddyn_dbw_auth_id(ddyn_dbw_frame frame)
{
    return (unsigned)frame < DDYN_DBW_FRAME_COUNT ? AUTH_IDS[FRAME_STREAM[frame]] : 0u;
}

static void put_le64(uint8_t *p, uint64_t v)
{
    unsigned i;
    for (i = 0; i < 8u; ++i) {
        p[i] = (uint8_t)(v >> (8u * i));
    }
}

#define MAC_DIGEST_LEN 8u
#define MAC_ID_LEN 2u
#define MAC_TAIL_LEN (DDYN_DBW_FRAME_LEN + 8u)

/* the SecOC "data to authenticate": data identifier (2 bytes LE), authentic payload, full freshness value
 * (8 bytes LE); split so that the identifier can be hashed ahead (mac_state_init) */
static void mac_id(uint8_t id[MAC_ID_LEN], uint32_t can_id)
{
    id[0] = (uint8_t)(can_id & 0xFFu);
    id[1] = (uint8_t)((can_id >> 8) & 0xFFu);
}

static void mac_tail(uint8_t tail[MAC_TAIL_LEN], const uint8_t data[DDYN_DBW_FRAME_LEN], uint64_t freshness)
{
    memcpy(tail, data, DDYN_DBW_FRAME_LEN);
    put_le64(&tail[DDYN_DBW_FRAME_LEN], freshness);
}

/* truncation to the most significant bits of the digest's first bytes (SecOC: leftmost bits) */
static uint32_t mac_of_digest(const uint8_t digest[MAC_DIGEST_LEN])
{
    return (((uint32_t)digest[0] << 16) | ((uint32_t)digest[1] << 8) | (uint32_t)digest[2]) & MAC_MASK;
}

uint32_t ddyn_dbw_auth_mac(const uint8_t key[DDYN_DBW_AUTH_KEY_LEN], uint32_t can_id,
                           const uint8_t data[DDYN_DBW_FRAME_LEN], uint64_t freshness)
{
    uint8_t msg[MAC_ID_LEN + MAC_TAIL_LEN];
    uint8_t digest[MAC_DIGEST_LEN];
    uint32_t mac;
    mac_id(msg, can_id);
    mac_tail(&msg[MAC_ID_LEN], data, freshness);
    crypto_blake2b_keyed(digest, sizeof digest, key, DDYN_DBW_AUTH_KEY_LEN, msg, sizeof msg);
    mac = mac_of_digest(digest);
    crypto_wipe(digest, sizeof digest);
    return mac;
}

/* ---- the prepared MAC states (issue 35) ----
 * A keyed BLAKE2b of the 18-byte message is two compressions: the 32-byte key padded to a 128-byte
 * block, then the message block (RFC 7693). The first depends on the key alone, so it is done once per
 * key: ddyn_dbw_auth_init keeps, per frame, the state after crypto_blake2b_keyed_init and
 * crypto_blake2b_update of the frame's 2 identifier bytes (Monocypher compresses a full block only when
 * more input follows, so these 2 bytes are what makes it compress the key block; they are the same for
 * every MAC of the frame). A MAC copies that state and goes on with crypto_blake2b_update (the other 16
 * bytes: no compression) and crypto_blake2b_final (one compression). Only Monocypher's public functions
 * run on the state; what is assumed of its type is that a copy of it is a valid state (it holds no
 * pointers) and that it fits DDYN_DBW_AUTH_STATE_WORDS (checked below); its fields are not touched.
 * tests/c/test_dbw_auth_cache.c checks the result against crypto_blake2b_keyed. */
typedef char mac_state_fits[sizeof(crypto_blake2b_ctx) <= sizeof(((ddyn_dbw_auth *)0)->mac_state[0]) ? 1 : -1];

static void mac_state_init(ddyn_dbw_auth *auth)
{
    crypto_blake2b_ctx ctx;
    uint8_t id[MAC_ID_LEN];
    unsigned f;
    for (f = 0; f < DDYN_DBW_FRAME_COUNT; ++f) {
        crypto_blake2b_keyed_init(&ctx, MAC_DIGEST_LEN, auth->key, DDYN_DBW_AUTH_KEY_LEN);
        mac_id(id, ddyn_dbw_frame_id((ddyn_dbw_frame)f));
        crypto_blake2b_update(&ctx, id, sizeof id);
        memcpy(auth->mac_state[f], &ctx, sizeof ctx);
    }
    crypto_wipe(&ctx, sizeof ctx);
}

uint32_t ddyn_dbw_auth_frame_mac(const ddyn_dbw_auth *auth, ddyn_dbw_frame frame, const uint8_t data[DDYN_DBW_FRAME_LEN],
                                 uint64_t freshness)
{
    crypto_blake2b_ctx ctx;
    uint8_t tail[MAC_TAIL_LEN];
    uint8_t digest[MAC_DIGEST_LEN];
    uint32_t mac;
    if (auth == NULL || data == NULL || !auth->enabled || (unsigned)frame >= DDYN_DBW_FRAME_COUNT) {
        return 0u;
    }
    memcpy(&ctx, auth->mac_state[frame], sizeof ctx);
    mac_tail(tail, data, freshness);
    crypto_blake2b_update(&ctx, tail, sizeof tail);
    crypto_blake2b_final(&ctx, digest); /* wipes ctx */
    mac = mac_of_digest(digest);
    crypto_wipe(digest, sizeof digest);
    return mac;
}

/* the authenticator frame of `frame` carrying `mac` (frame, data and auth_data checked by the caller) */
static ddyn_status pack_authenticator(ddyn_dbw_frame frame, uint32_t mac, uint64_t freshness, uint8_t counter,
                                      uint8_t auth_data[DDYN_DBW_FRAME_LEN])
{
    /* the three authenticator frames share one layout (can/ddyn_dbw.dbc); SecOC_Controller's packer
     * serves all three (tests/c/test_dbw.c checks the others give the same bytes) */
    struct ddyn_can_sec_oc_controller_t m;
    m.authenticated_id = (uint8_t)(ddyn_dbw_frame_id(frame) - DDYN_DBW_ID_BLOCK_BASE);
    m.freshness = (uint32_t)(freshness & FRESH_MASK);
    m.mac = mac;
    m.counter = (uint8_t)(counter % DDYN_DBW_COUNTER_MODULO);
    m.checksum = 0u;
    if (ddyn_can_sec_oc_controller_pack(auth_data, &m, DDYN_DBW_FRAME_LEN) != (int)DDYN_DBW_FRAME_LEN) {
        return DDYN_ERR_ARGUMENT;
    }
    auth_data[AUTH_CHECKSUM_BYTE] = ddyn_dbw_checksum(ddyn_dbw_auth_id(frame), auth_data);
    return DDYN_OK;
}

ddyn_status ddyn_dbw_auth_encode(const uint8_t key[DDYN_DBW_AUTH_KEY_LEN], ddyn_dbw_frame frame,
                                 const uint8_t data[DDYN_DBW_FRAME_LEN], uint64_t freshness, uint8_t counter,
                                 uint8_t auth_data[DDYN_DBW_FRAME_LEN])
{
    if (key == NULL || data == NULL || auth_data == NULL || (unsigned)frame >= DDYN_DBW_FRAME_COUNT) {
        return DDYN_ERR_ARGUMENT;
    }
    return pack_authenticator(frame, ddyn_dbw_auth_mac(key, ddyn_dbw_frame_id(frame), data, freshness), freshness,
                              counter, auth_data);
}

ddyn_status ddyn_dbw_auth_sign(const ddyn_dbw_auth *auth, ddyn_dbw_frame frame, const uint8_t data[DDYN_DBW_FRAME_LEN],
                               uint64_t freshness, uint8_t counter, uint8_t auth_data[DDYN_DBW_FRAME_LEN])
{
    if (auth == NULL || data == NULL || auth_data == NULL || (unsigned)frame >= DDYN_DBW_FRAME_COUNT) {
        return DDYN_ERR_ARGUMENT;
    }
    if (!auth->enabled) {
        return DDYN_ERR_NOT_READY;
    }
    return pack_authenticator(frame, ddyn_dbw_auth_frame_mac(auth, frame, data, freshness), freshness, counter,
                              auth_data);
}

ddyn_dbw_decode_result ddyn_dbw_auth_decode(uint32_t can_id, const uint8_t *data, size_t len, ddyn_dbw_frame *frame,
                                            uint32_t *freshness_low, uint32_t *mac, uint8_t *counter)
{
    struct ddyn_can_sec_oc_controller_t m;
    int stream, f;
    if (data == NULL || frame == NULL || freshness_low == NULL || mac == NULL || counter == NULL) {
        return DDYN_DBW_DECODE_ARGUMENT;
    }
    stream = stream_of_id(can_id);
    if (stream < 0) {
        return DDYN_DBW_DECODE_UNKNOWN_ID;
    }
    if (len != DDYN_DBW_FRAME_LEN) {
        return DDYN_DBW_DECODE_BAD_LENGTH;
    }
    if (data[AUTH_CHECKSUM_BYTE] != ddyn_dbw_checksum(can_id, data)) {
        return DDYN_DBW_DECODE_CHECKSUM;
    }
    (void)ddyn_can_sec_oc_controller_unpack(&m, data, DDYN_DBW_FRAME_LEN);
    f = ddyn_dbw_frame_of_id(DDYN_DBW_ID_BLOCK_BASE + m.authenticated_id);
    /* a frame of another node's: an authenticator may only vouch for its own sender's frames */
    if (f < 0 || FRAME_STREAM[f] != (uint8_t)stream) {
        return DDYN_DBW_DECODE_RANGE;
    }
    *frame = (ddyn_dbw_frame)f;
    *freshness_low = m.freshness & FRESH_MASK;
    *mac = m.mac & MAC_MASK;
    *counter = m.counter;
    return DDYN_DBW_DECODE_AUTHENTICATOR;
}

void ddyn_dbw_auth_init(ddyn_dbw_auth *auth, const uint8_t key[DDYN_DBW_AUTH_KEY_LEN], uint32_t timeout_us)
{
    if (auth == NULL) {
        return;
    }
    crypto_wipe(auth, sizeof *auth); /* a previous key's states too */
    if (key != NULL) {
        memcpy(auth->key, key, DDYN_DBW_AUTH_KEY_LEN);
        mac_state_init(auth);
        auth->enabled = true;
    }
    auth->timeout_us = timeout_us != 0u ? timeout_us : DDYN_DBW_AUTH_TIMEOUT_US;
}

bool ddyn_dbw_auth_hold(ddyn_dbw_auth *auth, ddyn_dbw_frame frame, const uint8_t data[DDYN_DBW_FRAME_LEN],
                        uint64_t t_us)
{
    unsigned k, slot = 0u;
    bool displaced;
    if (auth == NULL || data == NULL || (unsigned)frame >= DDYN_DBW_FRAME_COUNT) {
        return false;
    }
    /* a free slot, else the oldest */
    for (k = 0; k < DDYN_DBW_AUTH_HOLD; ++k) {
        if (!auth->pending_valid[frame][k]) {
            slot = k;
            break;
        }
        if (auth->pending_us[frame][k] < auth->pending_us[frame][slot]) {
            slot = k;
        }
    }
    displaced = auth->pending_valid[frame][slot];
    memcpy(auth->pending[frame][slot], data, DDYN_DBW_FRAME_LEN);
    auth->pending_us[frame][slot] = t_us;
    auth->pending_valid[frame][slot] = true;
    return displaced;
}

static bool too_old(const ddyn_dbw_auth *auth, uint64_t t_frame_us, uint64_t now_us)
{
    return now_us > t_frame_us && now_us - t_frame_us > (uint64_t)auth->timeout_us;
}

static bool usable(const ddyn_dbw_auth *auth, ddyn_dbw_frame f, unsigned k, uint64_t t_us)
{
    return auth->pending_valid[f][k] && !too_old(auth, auth->pending_us[f][k], t_us);
}

ddyn_dbw_failure ddyn_dbw_auth_verify(ddyn_dbw_auth *auth, uint32_t can_id, const uint8_t *auth_data, size_t len,
                                      uint64_t t_us, ddyn_dbw_frame *frame, uint8_t data[DDYN_DBW_FRAME_LEN],
                                      uint64_t *data_t_us)
{
    ddyn_dbw_frame f = DDYN_DBW_FRAME_COUNT;
    uint32_t low = 0u, mac = 0u, delta;
    uint64_t full;
    uint8_t counter = 0u;
    unsigned k, held = 0u;
    int match = -1;
    if (auth == NULL || frame == NULL || data == NULL || data_t_us == NULL || !auth->enabled) {
        return DDYN_DBW_FAIL_AUTH_FORGED;
    }
    if (ddyn_dbw_auth_decode(can_id, auth_data, len, &f, &low, &mac, &counter) != DDYN_DBW_DECODE_AUTHENTICATOR) {
        return DDYN_DBW_FAIL_AUTH_FORGED; /* a broken authenticator vouches for nothing */
    }
    *frame = f;
    /* a held frame older than the timeout is not a candidate (ddyn_dbw_auth_expire drops and counts it) */
    for (k = 0; k < DDYN_DBW_AUTH_HOLD; ++k) {
        held += usable(auth, f, k, t_us) ? 1u : 0u;
    }
    if (held == 0u) {
        return DDYN_DBW_FAIL_AUTH_STALE;
    }
    /* the full freshness value: the first one newer than the last accepted whose low bits match;
     * a value not newer (delta 0, or "behind" by up to half the range) is a replay */
    if (auth->rx_freshness_valid[f]) {
        delta = (low - (uint32_t)(auth->rx_freshness[f] & FRESH_MASK)) & FRESH_MASK;
        if (delta == 0u || delta > (FRESH_MASK >> 1)) {
            return DDYN_DBW_FAIL_AUTH_REPLAY; /* the held frames stay: their genuine authenticator may follow */
        }
        full = auth->rx_freshness[f] > UINT64_MAX - delta ? UINT64_MAX : auth->rx_freshness[f] + delta;
    } else {
        full = low; /* both ends start at 0 (docs/can.md: a receiver restarted mid-run resynchronises
                     * only while the sender is below 2^22 frames of that identifier) */
    }
    for (k = 0; k < DDYN_DBW_AUTH_HOLD; ++k) {
        /* every held frame is tried (no early exit on the first match) */
        if (usable(auth, f, k, t_us) &&
            (ddyn_dbw_auth_frame_mac(auth, f, auth->pending[f][k], full) ^ mac) == 0u) {
            match = (int)k;
        }
    }
    if (match < 0) {
        return DDYN_DBW_FAIL_AUTH_FORGED;
    }
    auth->rx_freshness[f] = full;
    auth->rx_freshness_valid[f] = true;
    memcpy(data, auth->pending[f][match], DDYN_DBW_FRAME_LEN);
    *data_t_us = auth->pending_us[f][match];
    auth->pending_valid[f][match] = false; /* any other held frame had no authenticator: it expires as stale */
    if (auth->accepted < UINT32_MAX) {
        auth->accepted++;
    }
    return DDYN_DBW_FAIL_COUNT;
}

uint32_t ddyn_dbw_auth_expire(ddyn_dbw_auth *auth, uint64_t now_us, uint32_t *frames)
{
    unsigned f, k;
    uint32_t n = 0u;
    if (frames != NULL) {
        *frames = 0u;
    }
    if (auth == NULL) {
        return 0u;
    }
    for (f = 0; f < DDYN_DBW_FRAME_COUNT; ++f) {
        for (k = 0; k < DDYN_DBW_AUTH_HOLD; ++k) {
            if (auth->pending_valid[f][k] && too_old(auth, auth->pending_us[f][k], now_us)) {
                auth->pending_valid[f][k] = false;
                ++n;
                if (frames != NULL) {
                    *frames |= 1u << f;
                }
            }
        }
    }
    return n;
}

ddyn_status ddyn_dbw_auth_enable(ddyn_dbw *dbw, const uint8_t key[DDYN_DBW_AUTH_KEY_LEN], uint32_t timeout_us)
{
    if (dbw == NULL || key == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    ddyn_dbw_auth_init(&dbw->auth, key, timeout_us);
    return DDYN_OK;
}

void ddyn_dbw_auth_disable(ddyn_dbw *dbw)
{
    if (dbw != NULL) {
        crypto_wipe(&dbw->auth, sizeof dbw->auth);
    }
}

ddyn_status ddyn_dbw_authenticator(ddyn_dbw *dbw, ddyn_dbw_frame frame, const uint8_t data[DDYN_DBW_FRAME_LEN],
                                   uint32_t *auth_id, uint8_t auth_data[DDYN_DBW_FRAME_LEN])
{
    ddyn_dbw_auth *a;
    ddyn_status rc;
    unsigned k;
    if (dbw == NULL || data == NULL || auth_id == NULL || auth_data == NULL ||
        (unsigned)frame >= DDYN_DBW_FRAME_COUNT) {
        return DDYN_ERR_ARGUMENT;
    }
    a = &dbw->auth;
    if (!a->enabled) {
        return DDYN_ERR_NOT_READY;
    }
    k = FRAME_STREAM[frame];
    rc = ddyn_dbw_auth_sign(a, frame, data, a->tx_freshness[frame], a->tx_counter[k], auth_data);
    if (rc != DDYN_OK) {
        return rc;
    }
    a->tx_counter[k] = (uint8_t)((a->tx_counter[k] + 1u) % DDYN_DBW_COUNTER_MODULO);
    if (a->tx_freshness[frame] < UINT64_MAX) {
        a->tx_freshness[frame]++;
    }
    *auth_id = AUTH_IDS[k];
    return DDYN_OK;
}
