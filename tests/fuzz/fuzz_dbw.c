/*
 * libFuzzer target: the CAN frame decoder and the controller's CAN input path (c_src/src/dbw.c
 * over the cantools-generated ddyn_can.c). The input is a script of records, each one byte of
 * operation followed by its operands:
 *   op % 8 == 0,1  a raw frame: identifier (2 bytes), length (1), 8 data bytes, clock advance (1 byte,
 *                  x1 ms); with op % 8 == 1 the identifier is put in the protocol's block and the
 *                  checksum fixed up, so that the range and counter checks behind it are reached
 *   op % 8 == 2    a transport report (bus-off, bus error, link loss, or an invalid kind)
 *   op % 8 == 3    the operator's enable
 *   op % 8 == 4    a control period with a desired command from 3 bytes, scaled to a little beyond
 *                  the DBC ranges (in range and out of range both occur)
 *   op % 8 == 5    a raw decode of up to 64 bytes with any identifier and length
 *   op % 8 == 6    a well-formed frame from a simulated DBW unit: frame kind (1 byte), 8 bytes of
 *                  in-range values, its next rolling counter (sometimes skipped or repeated), clock
 *                  advance (1 byte, x1 ms): what reaches READY and ACTIVE
 *   op % 8 == 7    a control period with 3 raw doubles (NaN, infinities, anything)
 * Invariants checked after every step (a violation traps, which libFuzzer reports as a crash):
 * the command frame always decodes back with a valid checksum and in-range values; anything but
 * ACTIVE sends the safe command; the last good values are always finite; an unknown identifier
 * never changes the link's state.
 * Built and run by scripts/fuzz_can.sh (clang -fsanitize=fuzzer,address,undefined).
 */
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include "ddyn/dbw.h"

#define CHECK(cond) do { if (!(cond)) { __builtin_trap(); } } while (0)

typedef struct {
    const uint8_t *p;
    size_t n;
} cursor;

static int take(cursor *c, void *out, size_t k)
{
    if (c->n < k) {
        return -1;
    }
    memcpy(out, c->p, k);
    c->p += k;
    c->n -= k;
    return 0;
}

static void check_latest_finite(const ddyn_dbw *d)
{
    const ddyn_dbw_signals *s = &d->latest;
    CHECK(isfinite(s->feedback.steering) && isfinite(s->feedback.steering_rate));
    CHECK(isfinite(s->feedback.wheel_speed_front) && isfinite(s->feedback.wheel_speed_rear));
    CHECK(isfinite(s->sensors.gnss_x) && isfinite(s->sensors.gnss_y) && isfinite(s->sensors.heading));
    CHECK(isfinite(s->sensors.yaw_rate) && isfinite(s->sensors.accel_x) && isfinite(s->sensors.accel_y));
    CHECK(s->feedback.throttle_pedal >= 0.0 && s->feedback.throttle_pedal <= 1.0);
}

static void control_period(ddyn_dbw *d, uint64_t now, const double v[3])
{
    ddyn_dbw_command desired, sent;
    ddyn_dbw_signals back;
    ddyn_dbw_frame f;
    uint8_t data[DDYN_DBW_FRAME_LEN], counter;
    ddyn_dbw_state st;
    desired.throttle = v[0];
    desired.brake = v[1];
    desired.steering = v[2];
    desired.enable = true;
    desired.mode = DDYN_DBW_MODE_AUTONOMOUS;
    st = ddyn_dbw_command_frame(d, now, &desired, &sent, data);
    memset(&back, 0, sizeof(back));
    CHECK(ddyn_dbw_decode(ddyn_dbw_frame_id(DDYN_DBW_FRAME_COMMAND), data, DDYN_DBW_FRAME_LEN, &back, &f, &counter) ==
          DDYN_DBW_DECODE_OK);
    CHECK(f == DDYN_DBW_FRAME_COMMAND);
    CHECK(back.command.throttle >= 0.0 && back.command.throttle <= 1.0);
    CHECK(back.command.brake >= 0.0 && back.command.brake <= 1.0);
    CHECK(fabs(back.command.steering) <= 0.6);
    if (st != DDYN_DBW_ACTIVE) {
        CHECK(sent.mode == DDYN_DBW_MODE_SAFE_STOP && sent.throttle == 0.0 && sent.brake == d->config.safe_brake);
        CHECK(back.command.mode == DDYN_DBW_MODE_SAFE_STOP && back.command.throttle == 0.0);
    } else {
        CHECK(sent.throttle == desired.throttle && sent.steering == desired.steering);
        CHECK(back.command.mode == DDYN_DBW_MODE_AUTONOMOUS && fabs(back.command.throttle - desired.throttle) <= 0.5e-4);
    }
}

/* byte -> [lo, hi] */
static double span(uint8_t b, double lo, double hi)
{
    return lo + (hi - lo) * (double)b / 255.0;
}

/* every signal of the protocol inside its DBC range, from 8 bytes */
static void in_range_signals(const uint8_t b[8], ddyn_dbw_signals *s)
{
    memset(s, 0, sizeof(*s));
    s->feedback.steering = span(b[0], -0.6, 0.6);
    s->feedback.steering_rate = span(b[1], -10.0, 10.0);
    s->feedback.throttle_pedal = span(b[2], 0.0, 1.0);
    s->feedback.brake_pedal = span(b[3], 0.0, 1.0);
    s->feedback.mode = (ddyn_dbw_mode)(b[4] % 3u);
    s->feedback.enabled = (b[4] & 8u) != 0u;
    s->feedback.faults = (uint8_t)(b[5] % 64u);
    s->feedback.wheel_speed_front = span(b[6], -100.0, 100.0);
    s->feedback.wheel_speed_rear = span(b[7], -100.0, 100.0);
    s->sensors.yaw_rate = span(b[0], -16.0, 16.0);
    s->sensors.accel_x = span(b[1], -160.0, 160.0);
    s->sensors.accel_y = span(b[2], -160.0, 160.0);
    s->sensors.gnss_x = span(b[3], -30000.0, 30000.0);
    s->sensors.gnss_y = span(b[4], -30000.0, 30000.0);
    s->sensors.heading = span(b[5], -3.1415, 3.1415);
    s->sensors.fix_type = (uint8_t)(b[6] % 5u);
}

int LLVMFuzzerTestOneInput(const uint8_t *input, size_t size)
{
    ddyn_dbw d, unit;
    ddyn_dbw_config cfg;
    cursor c = {input, size};
    uint64_t now = 1000000u;
    unsigned steps;
    ddyn_dbw_default_config(&cfg, DDYN_DBW_MONITOR_CONTROLLER);
    cfg.recovery_good_frames = 1u; /* reach ACTIVE with short inputs */
    CHECK(ddyn_dbw_init(&d, &cfg) == 0);
    ddyn_dbw_default_config(&cfg, DDYN_DBW_MONITOR_DBW_UNIT);
    CHECK(ddyn_dbw_init(&unit, &cfg) == 0); /* only its rolling tx counters are used */
    for (steps = 0; steps < 4096u && c.n > 0; ++steps) {
        uint8_t op = 0;
        (void)take(&c, &op, 1);
        switch (op % 8u) {
        case 0:
        case 1: {
            uint16_t id = 0;
            uint8_t len = 8, data[DDYN_DBW_FRAME_LEN] = {0}, dt = 0;
            (void)take(&c, &id, 2);
            (void)take(&c, &len, 1);
            (void)take(&c, data, sizeof(data));
            (void)take(&c, &dt, 1);
            len %= 9u;
            if (op % 8u == 1u) {
                id = (uint16_t)(0x100u | (id & 0x3Fu));
                data[7] = ddyn_dbw_checksum(id, data);
            }
            now += (uint64_t)dt * 1000u;
            {
                const ddyn_dbw_state before = d.state;
                /* an unknown identifier is counted, never fatal: the state stays what it was */
                if (ddyn_dbw_on_frame(&d, id, data, len, now) == DDYN_DBW_DECODE_UNKNOWN_ID) {
                    CHECK(d.state == before);
                }
            }
            break;
        }
        case 2: {
            uint8_t kind = 0;
            (void)take(&c, &kind, 1);
            ddyn_dbw_report(&d, (ddyn_dbw_failure)(kind % (DDYN_DBW_FAIL_COUNT + 2u)), now);
            break;
        }
        case 3: (void)ddyn_dbw_enable(&d); break;
        case 4: {
            uint8_t b[3] = {0, 0, 0};
            double v[3];
            (void)take(&c, b, sizeof(b));
            v[0] = span(b[0], -0.1, 1.1);
            v[1] = span(b[1], -0.1, 1.1);
            v[2] = span(b[2], -0.7, 0.7);
            control_period(&d, now, v);
            break;
        }
        case 5: {
            uint32_t id = 0;
            uint8_t len = 0, raw[64] = {0};
            ddyn_dbw_signals s;
            ddyn_dbw_frame f;
            uint8_t counter;
            (void)take(&c, &id, 4);
            (void)take(&c, &len, 1);
            len %= 65u;
            (void)take(&c, raw, len);
            memset(&s, 0, sizeof(s));
            if (ddyn_dbw_decode(id, raw, len, &s, &f, &counter) == DDYN_DBW_DECODE_OK) {
                CHECK(len == DDYN_DBW_FRAME_LEN && counter < 16u && (unsigned)f < DDYN_DBW_FRAME_COUNT);
            }
            break;
        }
        case 6: {
            uint8_t kind = 0, b[8] = {0}, dt = 0, data[DDYN_DBW_FRAME_LEN];
            ddyn_dbw_signals s;
            ddyn_dbw_frame f;
            (void)take(&c, &kind, 1);
            (void)take(&c, b, sizeof(b));
            (void)take(&c, &dt, 1);
            f = (ddyn_dbw_frame)(DDYN_DBW_FRAME_STEERING + kind % 6u);
            if (kind & 0x80u) { /* a lost or repeated frame in the sender's sequence */
                unit.tx_counter[f] = (uint8_t)((unit.tx_counter[f] + ((kind & 0x40u) ? 1u : 15u)) % 16u);
            }
            in_range_signals(b, &s);
            CHECK(ddyn_dbw_next_frame(&unit, f, &s, data) == 0);
            now += (uint64_t)(dt % 64u) * 1000u;
            CHECK(ddyn_dbw_on_frame(&d, ddyn_dbw_frame_id(f), data, DDYN_DBW_FRAME_LEN, now) == DDYN_DBW_DECODE_OK);
            break;
        }
        default: {
            double v[3] = {0.0, 0.0, 0.0};
            (void)take(&c, v, sizeof(v));
            control_period(&d, now, v);
            break;
        }
        }
        check_latest_finite(&d);
        CHECK(d.state == DDYN_DBW_WAIT_GOOD || d.state == DDYN_DBW_READY || d.state == DDYN_DBW_ACTIVE);
    }
    return 0;
}
