/*
 * Drive-by-wire protocol logic (c_src/src/dbw.c) on the host, without any CAN: frames
 * round-trip through the cantools-generated packers, every failure kind is counted once and
 * gives the safe command in the same control period, and recovery needs N good frames of
 * every monitored frame plus an explicit enable.
 */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>
#include <sys/stat.h>

#include <cmocka.h>

#include "ddyn/dbw.h"
#include "ddyn_can.h"
#include "ddyn_dbw_test_key.h" /* made at build time: cmake/dbw_test_key.cmake */
#include "dbw_auth_key.h"

#define PERIOD_US 10000u /* the controller's period in these tests: the DBC's 10 ms */

static ddyn_dbw ctl;    /* the controller's endpoint under test */
static ddyn_dbw sender; /* the DBW unit / simulator side: only its tx counters are used */
static ddyn_dbw_signals truth;
static uint64_t now;

static void fill_truth(void)
{
    memset(&truth, 0, sizeof(truth));
    truth.command.throttle = 0.25;
    truth.command.brake = 0.0;
    truth.command.steering = -0.1234;
    truth.command.enable = true;
    truth.command.mode = DDYN_DBW_MODE_AUTONOMOUS;
    truth.feedback.steering = 0.0567;
    truth.feedback.steering_rate = -1.25;
    truth.feedback.throttle_pedal = 0.5;
    truth.feedback.brake_pedal = 0.125;
    truth.feedback.mode = DDYN_DBW_MODE_AUTONOMOUS;
    truth.feedback.enabled = true;
    truth.feedback.driver_override = false;
    truth.feedback.faults = DDYN_DBW_FAULT_ACTUATOR;
    truth.feedback.wheel_speed_front = 31.415;
    truth.feedback.wheel_speed_rear = -2.5;
    truth.sensors.yaw_rate = 0.7325;
    truth.sensors.accel_x = -9.81;
    truth.sensors.accel_y = 25.005;
    truth.sensors.gnss_x = -1234.567;
    truth.sensors.gnss_y = 8765.432;
    truth.sensors.heading = -3.0;
    truth.sensors.fix_type = 4;
}

/* one frame of `frame` from the sender, received by the controller at `now` (followed by its
 * authenticator when the sender authenticates) */
static ddyn_dbw_decode_result deliver(ddyn_dbw_frame frame)
{
    uint8_t data[8], auth[8];
    uint32_t auth_id = 0u;
    ddyn_dbw_decode_result r;
    assert_int_equal(ddyn_dbw_next_frame(&sender, frame, &truth, data), 0);
    r = ddyn_dbw_on_frame(&ctl, ddyn_dbw_frame_id(frame), data, 8, now);
    if (!sender.auth.enabled) {
        return r;
    }
    assert_int_equal(ddyn_dbw_authenticator(&sender, frame, data, &auth_id, auth), 0);
    return ddyn_dbw_on_frame(&ctl, auth_id, auth, 8, now + 100u);
}

/* one control period: every feedback and sensor frame once, then the clock advances */
static void deliver_period(void)
{
    int f;
    for (f = DDYN_DBW_FRAME_STEERING; f < (int)DDYN_DBW_FRAME_COUNT; ++f) {
        assert_int_equal(deliver((ddyn_dbw_frame)f), DDYN_DBW_DECODE_OK);
    }
    now += PERIOD_US;
}

static int setup(void **state)
{
    ddyn_dbw_config c;
    (void)state;
    fill_truth();
    now = 1000000u;
    ddyn_dbw_default_config(&c, DDYN_DBW_MONITOR_CONTROLLER);
    assert_int_equal(ddyn_dbw_init(&ctl, &c), 0);
    ddyn_dbw_default_config(&c, DDYN_DBW_MONITOR_DBW_UNIT);
    assert_int_equal(ddyn_dbw_init(&sender, &c), 0);
    return 0;
}

static void bring_to_active(void)
{
    unsigned i;
    for (i = 0; i < ctl.config.recovery_good_frames; ++i) {
        deliver_period();
    }
    assert_int_equal(ddyn_dbw_check(&ctl, now), DDYN_DBW_READY);
    assert_int_equal(ddyn_dbw_enable(&ctl), 0);
    assert_int_equal(ctl.state, DDYN_DBW_ACTIVE);
}

static void assert_safe(const ddyn_dbw_command *c, double held_steering)
{
    assert_true(c->throttle == 0.0);
    assert_true(c->brake == ctl.config.safe_brake);
    assert_true(c->steering == held_steering);
    assert_true(c->enable);
    assert_int_equal(c->mode, DDYN_DBW_MODE_SAFE_STOP);
}

/* the command that goes out in this period, decoded back from its bytes */
static ddyn_dbw_state period_command(const ddyn_dbw_command *desired, ddyn_dbw_command *on_wire)
{
    ddyn_dbw_command sent;
    ddyn_dbw_signals back;
    ddyn_dbw_frame f;
    uint8_t data[8], counter;
    ddyn_dbw_state st = ddyn_dbw_command_frame(&ctl, now, desired, &sent, data);
    memset(&back, 0, sizeof(back));
    assert_int_equal(ddyn_dbw_decode(ddyn_dbw_frame_id(DDYN_DBW_FRAME_COMMAND), data, 8, &back, &f, &counter),
                     DDYN_DBW_DECODE_OK);
    assert_int_equal(f, DDYN_DBW_FRAME_COMMAND);
    *on_wire = back.command;
    assert_true(fabs(on_wire->steering - sent.steering) <= 0.5e-4 + 1e-12);
    return st;
}

static ddyn_dbw_command driving(void)
{
    ddyn_dbw_command d = {0.6, 0.0, 0.2, true, DDYN_DBW_MODE_AUTONOMOUS};
    return d;
}

/* ---- frames ---- */

static void test_checksum_is_crc8_sae_j1850(void **state)
{
    /* the identifier 0x3231 contributes the bytes "12", the data bytes 0-6 "3456789": the CRC
     * catalogue's check input, whose CRC-8/SAE-J1850 is 0x4B; byte 7 is excluded */
    const uint8_t data[8] = {'3', '4', '5', '6', '7', '8', '9', 0xAA};
    (void)state;
    assert_int_equal(ddyn_dbw_checksum(0x3231u, data), 0x4Bu);
}

static void test_every_frame_round_trips_within_half_a_bit(void **state)
{
    static const double lsb_command[3] = {1e-4, 1e-4, 1e-4};
    ddyn_dbw_signals back;
    ddyn_dbw_frame f;
    uint8_t data[8], counter;
    int i;
    (void)state;
    for (i = 0; i < (int)DDYN_DBW_FRAME_COUNT; ++i) {
        assert_int_equal(ddyn_dbw_encode((ddyn_dbw_frame)i, &truth, (uint8_t)(i + 3), data), 0);
        memset(&back, 0, sizeof(back));
        assert_int_equal(ddyn_dbw_decode(ddyn_dbw_frame_id((ddyn_dbw_frame)i), data, 8, &back, &f, &counter),
                         DDYN_DBW_DECODE_OK);
        assert_int_equal(f, i);
        assert_int_equal(counter, (i + 3) % 16);
    }
    /* the decoded values of every frame together (each frame wrote its own members) */
    memset(&back, 0, sizeof(back));
    for (i = 0; i < (int)DDYN_DBW_FRAME_COUNT; ++i) {
        assert_int_equal(ddyn_dbw_encode((ddyn_dbw_frame)i, &truth, 0, data), 0);
        assert_int_equal(ddyn_dbw_decode(ddyn_dbw_frame_id((ddyn_dbw_frame)i), data, 8, &back, &f, &counter),
                         DDYN_DBW_DECODE_OK);
    }
    assert_true(fabs(back.command.throttle - truth.command.throttle) <= lsb_command[0] / 2);
    assert_true(fabs(back.command.brake - truth.command.brake) <= lsb_command[1] / 2);
    assert_true(fabs(back.command.steering - truth.command.steering) <= lsb_command[2] / 2 + 1e-12);
    assert_true(back.command.enable);
    assert_int_equal(back.command.mode, DDYN_DBW_MODE_AUTONOMOUS);
    assert_true(fabs(back.feedback.steering - truth.feedback.steering) <= 0.5e-4 + 1e-12);
    assert_true(fabs(back.feedback.steering_rate - truth.feedback.steering_rate) <= 0.5e-3 + 1e-12);
    assert_true(fabs(back.feedback.throttle_pedal - 0.5) <= 0.5e-4);
    assert_true(fabs(back.feedback.brake_pedal - 0.125) <= 0.5e-4);
    assert_int_equal(back.feedback.faults, DDYN_DBW_FAULT_ACTUATOR);
    assert_true(back.feedback.enabled && !back.feedback.driver_override);
    assert_true(fabs(back.feedback.wheel_speed_front - 31.415) <= 0.0025 + 1e-9);
    assert_true(fabs(back.feedback.wheel_speed_rear + 2.5) <= 0.0025 + 1e-9);
    assert_true(fabs(back.sensors.yaw_rate - 0.7325) <= 0.00025 + 1e-12);
    assert_true(fabs(back.sensors.accel_x + 9.81) <= 0.0025 + 1e-9);
    assert_true(fabs(back.sensors.accel_y - 25.005) <= 0.0025 + 1e-9);
    assert_true(fabs(back.sensors.gnss_x + 1234.567) <= 0.0005 + 1e-9);
    assert_true(fabs(back.sensors.gnss_y - 8765.432) <= 0.0005 + 1e-9);
    assert_true(fabs(back.sensors.heading + 3.0) <= 0.5e-4 + 1e-12);
    assert_int_equal(back.sensors.fix_type, 4);
}

static void test_encode_refuses_out_of_range_and_non_finite(void **state)
{
    uint8_t data[8];
    ddyn_dbw_signals s = truth;
    (void)state;
    s.command.throttle = 1.0001;
    assert_int_equal(ddyn_dbw_encode(DDYN_DBW_FRAME_COMMAND, &s, 0, data), DDYN_ERR_RANGE);
    s = truth;
    s.command.steering = NAN;
    assert_int_equal(ddyn_dbw_encode(DDYN_DBW_FRAME_COMMAND, &s, 0, data), DDYN_ERR_RANGE);
    s = truth;
    s.command.brake = -0.01; /* cantools' encode would wrap this to a large raw value */
    assert_int_equal(ddyn_dbw_encode(DDYN_DBW_FRAME_COMMAND, &s, 0, data), DDYN_ERR_RANGE);
    s = truth;
    s.sensors.gnss_x = 30000.5;
    assert_int_equal(ddyn_dbw_encode(DDYN_DBW_FRAME_GNSS_POSITION, &s, 0, data), DDYN_ERR_RANGE);
    s = truth;
    s.sensors.fix_type = 5;
    assert_int_equal(ddyn_dbw_encode(DDYN_DBW_FRAME_GNSS_HEADING, &s, 0, data), DDYN_ERR_RANGE);
    s = truth;
    s.sensors.yaw_rate = INFINITY;
    assert_int_equal(ddyn_dbw_encode(DDYN_DBW_FRAME_IMU, &s, 0, data), DDYN_ERR_RANGE);
    assert_int_equal(ddyn_dbw_encode(DDYN_DBW_FRAME_COUNT, &truth, 0, data), DDYN_ERR_ARGUMENT);
}

static void test_decode_names_each_defect(void **state)
{
    ddyn_dbw_signals back;
    ddyn_dbw_frame f;
    uint8_t data[8], counter;
    const uint32_t cmd_id = ddyn_dbw_frame_id(DDYN_DBW_FRAME_COMMAND);
    (void)state;
    assert_int_equal(ddyn_dbw_encode(DDYN_DBW_FRAME_COMMAND, &truth, 1, data), 0);
    assert_int_equal(ddyn_dbw_decode(cmd_id, data, 7, &back, &f, &counter), DDYN_DBW_DECODE_BAD_LENGTH);
    assert_int_equal(ddyn_dbw_decode(0x13Fu, data, 8, &back, &f, &counter), DDYN_DBW_DECODE_UNKNOWN_ID);
    assert_int_equal(ddyn_dbw_decode(0x200u, data, 8, &back, &f, &counter), DDYN_DBW_DECODE_FOREIGN_ID);
    assert_int_equal(ddyn_dbw_decode(0x1000100u, data, 8, &back, &f, &counter), DDYN_DBW_DECODE_FOREIGN_ID);
    data[2] ^= 0x01u;
    assert_int_equal(ddyn_dbw_decode(cmd_id, data, 8, &back, &f, &counter), DDYN_DBW_DECODE_CHECKSUM);
    /* a raw throttle of 10001 (1.0001) with a correct checksum: the receiving range check */
    data[0] = 0x11u;
    data[1] = 0x27u;
    data[7] = ddyn_dbw_checksum(cmd_id, data);
    assert_int_equal(ddyn_dbw_decode(cmd_id, data, 8, &back, &f, &counter), DDYN_DBW_DECODE_RANGE);
    assert_int_equal(ddyn_dbw_decode(cmd_id, NULL, 8, &back, &f, &counter), DDYN_DBW_DECODE_ARGUMENT);
}

/* ---- the monitor ---- */

static void test_init_refuses_bad_configs(void **state)
{
    ddyn_dbw_config c;
    ddyn_dbw d;
    (void)state;
    ddyn_dbw_default_config(&c, 0u);
    assert_int_equal(ddyn_dbw_init(&d, &c), DDYN_ERR_CONFIG); /* monitors nothing */
    ddyn_dbw_default_config(&c, DDYN_DBW_MONITOR_CONTROLLER);
    c.recovery_good_frames = 0u;
    assert_int_equal(ddyn_dbw_init(&d, &c), DDYN_ERR_CONFIG);
    ddyn_dbw_default_config(&c, DDYN_DBW_MONITOR_CONTROLLER);
    c.safe_brake = NAN;
    assert_int_equal(ddyn_dbw_init(&d, &c), DDYN_ERR_CONFIG);
    c.safe_brake = 1.5;
    assert_int_equal(ddyn_dbw_init(&d, &c), DDYN_ERR_CONFIG);
    assert_int_equal(ddyn_dbw_init(NULL, &c), DDYN_ERR_ARGUMENT);
    assert_int_equal(c.deadline_us[DDYN_DBW_FRAME_IMU], 30000u);
    assert_int_equal(c.deadline_us[DDYN_DBW_FRAME_GNSS_POSITION], 60000u);
    assert_int_equal(c.deadline_us[DDYN_DBW_FRAME_COMMAND], 0u);
}

static void test_starts_safe_and_needs_good_frames_and_enable(void **state)
{
    ddyn_dbw_command d = driving(), w;
    unsigned i;
    (void)state;
    assert_int_equal(period_command(&d, &w), DDYN_DBW_WAIT_GOOD);
    assert_safe(&w, 0.0);
    assert_int_equal(ddyn_dbw_enable(&ctl), DDYN_ERR_NOT_READY); /* no feedback yet */
    for (i = 0; i + 1 < ctl.config.recovery_good_frames; ++i) {
        deliver_period();
    }
    assert_int_equal(ddyn_dbw_check(&ctl, now), DDYN_DBW_WAIT_GOOD); /* one good frame short */
    deliver_period();
    assert_int_equal(period_command(&d, &w), DDYN_DBW_READY);
    assert_safe(&w, 0.0); /* READY is still safe: nothing resumes without enable */
    assert_int_equal(ddyn_dbw_enable(&ctl), 0);
    assert_int_equal(period_command(&d, &w), DDYN_DBW_ACTIVE);
    assert_true(fabs(w.throttle - 0.6) < 1e-4 && fabs(w.steering - 0.2) < 1e-4 && w.brake == 0.0);
    assert_int_equal(w.mode, DDYN_DBW_MODE_AUTONOMOUS);
    for (i = 0; i < DDYN_DBW_FAIL_COUNT; ++i) {
        assert_int_equal(ctl.failures[i], 0u);
    }
    /* the decoded feedback is what the sender sent */
    assert_true(fabs(ctl.latest.sensors.gnss_y - truth.sensors.gnss_y) < 1e-3);
    assert_int_equal(ddyn_dbw_take_fresh(&ctl), (uint32_t)DDYN_DBW_MONITOR_CONTROLLER);
    assert_int_equal(ddyn_dbw_take_fresh(&ctl), 0u);
}

/* Drive to ACTIVE holding steering 0.2, inject one failure with `inject`, and check: exactly
 * one count of `kind`, the safe command in the same period, and explicit recovery. */
static void check_failure(ddyn_dbw_failure kind, void (*inject)(void))
{
    ddyn_dbw_command d = driving(), w;
    unsigned i;
    bring_to_active();
    assert_int_equal(period_command(&d, &w), DDYN_DBW_ACTIVE);
    inject();
    assert_int_equal(period_command(&d, &w), DDYN_DBW_WAIT_GOOD);
    assert_safe(&w, 0.2);
    for (i = 0; i < DDYN_DBW_FAIL_COUNT; ++i) {
        assert_int_equal(ctl.failures[i], i == (unsigned)kind ? 1u : 0u);
    }
    assert_int_equal(ctl.last_failure, kind);
    assert_int_equal(ddyn_dbw_take_failures(&ctl), 1u << kind);
    /* good frames resume: N periods bring READY, still safe until enabled */
    assert_int_equal(ddyn_dbw_enable(&ctl), DDYN_ERR_NOT_READY);
    for (i = 0; i < ctl.config.recovery_good_frames; ++i) {
        assert_int_equal(period_command(&d, &w), DDYN_DBW_WAIT_GOOD);
        assert_safe(&w, 0.2);
        deliver_period();
    }
    assert_int_equal(period_command(&d, &w), DDYN_DBW_READY);
    assert_safe(&w, 0.2);
    assert_int_equal(ddyn_dbw_enable(&ctl), 0);
    assert_int_equal(period_command(&d, &w), DDYN_DBW_ACTIVE);
    assert_true(fabs(w.throttle - 0.6) < 1e-4);
    assert_int_equal(ctl.failures[kind], 1u); /* the recovery itself counted nothing */
}

static void inject_stale(void)
{
    /* the IMU stops for longer than its deadline while everything else keeps coming */
    int f, p;
    for (p = 0; p < 4; ++p) {
        for (f = DDYN_DBW_FRAME_STEERING; f < (int)DDYN_DBW_FRAME_COUNT; ++f) {
            if (f != DDYN_DBW_FRAME_IMU) {
                (void)deliver((ddyn_dbw_frame)f);
            }
        }
        now += PERIOD_US;
    }
    now += 1u;
}
static void inject_counter_jump(void)
{
    sender.tx_counter[DDYN_DBW_FRAME_STATUS] = (uint8_t)((sender.tx_counter[DDYN_DBW_FRAME_STATUS] + 2u) % 16u);
    (void)deliver(DDYN_DBW_FRAME_STATUS);
}
static void inject_counter_repeat(void)
{
    sender.tx_counter[DDYN_DBW_FRAME_STEERING] = (uint8_t)((sender.tx_counter[DDYN_DBW_FRAME_STEERING] + 15u) % 16u);
    (void)deliver(DDYN_DBW_FRAME_STEERING);
}
static void inject_checksum(void)
{
    uint8_t data[8];
    assert_int_equal(ddyn_dbw_next_frame(&sender, DDYN_DBW_FRAME_WHEEL_SPEEDS, &truth, data), 0);
    data[7] ^= 0x80u;
    assert_int_equal(ddyn_dbw_on_frame(&ctl, ddyn_dbw_frame_id(DDYN_DBW_FRAME_WHEEL_SPEEDS), data, 8, now),
                     DDYN_DBW_DECODE_CHECKSUM);
}
static void inject_range(void)
{
    /* a heading of raw 32000 (3.2 rad > 3.1416) with a valid checksum and the next counter */
    uint8_t data[8];
    const uint32_t id = ddyn_dbw_frame_id(DDYN_DBW_FRAME_GNSS_HEADING);
    assert_int_equal(ddyn_dbw_next_frame(&sender, DDYN_DBW_FRAME_GNSS_HEADING, &truth, data), 0);
    data[0] = 0x00u;
    data[1] = 0x7Du;
    data[7] = ddyn_dbw_checksum(id, data);
    assert_int_equal(ddyn_dbw_on_frame(&ctl, id, data, 8, now), DDYN_DBW_DECODE_RANGE);
}
static void inject_unknown(void)
{
    const uint8_t data[8] = {0};
    assert_int_equal(ddyn_dbw_on_frame(&ctl, 0x122u, data, 8, now), DDYN_DBW_DECODE_UNKNOWN_ID);
}
static void inject_bad_length(void)
{
    uint8_t data[8];
    assert_int_equal(ddyn_dbw_next_frame(&sender, DDYN_DBW_FRAME_IMU, &truth, data), 0);
    assert_int_equal(ddyn_dbw_on_frame(&ctl, ddyn_dbw_frame_id(DDYN_DBW_FRAME_IMU), data, 6, now),
                     DDYN_DBW_DECODE_BAD_LENGTH);
}
static void inject_bus_off(void) { ddyn_dbw_report(&ctl, DDYN_DBW_FAIL_BUS_OFF, now); }
static void inject_iface_gone(void) { ddyn_dbw_report(&ctl, DDYN_DBW_FAIL_IFACE_GONE, now); }

static void test_defect_in_an_unmonitored_frame_is_counted_not_fatal(void **s)
{
    /* the controller's endpoint does not monitor the command frame (deadline 0: it sends it); a
     * corrupted one on the bus is counted, but must not drop the link the car drives on (it used to
     * send the endpoint to WAIT_GOOD and the car to its safe command) */
    ddyn_dbw_command d = driving(), w;
    uint8_t data[8];
    (void)s;
    assert_int_equal(ctl.config.deadline_us[DDYN_DBW_FRAME_COMMAND], 0u);
    bring_to_active();
    assert_int_equal(period_command(&d, &w), DDYN_DBW_ACTIVE);
    assert_int_equal(ddyn_dbw_next_frame(&sender, DDYN_DBW_FRAME_COMMAND, &truth, data), 0);
    data[7] ^= 0x80u;
    assert_int_equal(ddyn_dbw_on_frame(&ctl, ddyn_dbw_frame_id(DDYN_DBW_FRAME_COMMAND), data, 8, now),
                     DDYN_DBW_DECODE_CHECKSUM);
    assert_int_equal(ctl.failures[DDYN_DBW_FAIL_CHECKSUM], 1u);
    assert_int_equal(period_command(&d, &w), DDYN_DBW_ACTIVE);
    assert_true(fabs(w.throttle - 0.6) < 1e-4);
    /* the same defect in a monitored frame still drops it */
    inject_checksum();
    assert_int_equal(period_command(&d, &w), DDYN_DBW_WAIT_GOOD);
}

static void test_unknown_frame_is_counted_not_fatal(void **s)
{
    /* one stray node sending an identifier of the block that the DBC lacks must not stop the car:
     * the frame is counted (and named), the active link keeps driving (it used to drop to the safe
     * command, issue 35) */
    ddyn_dbw_command d = driving(), w;
    unsigned i;
    (void)s;
    bring_to_active();
    assert_int_equal(period_command(&d, &w), DDYN_DBW_ACTIVE);
    for (i = 0; i < 3u; ++i) {
        inject_unknown();
    }
    assert_int_equal(ctl.failures[DDYN_DBW_FAIL_UNKNOWN_FRAME], 3u);
    assert_int_equal(ctl.last_failure, DDYN_DBW_FAIL_UNKNOWN_FRAME);
    assert_int_equal(ddyn_dbw_take_failures(&ctl), 1u << DDYN_DBW_FAIL_UNKNOWN_FRAME);
    assert_int_equal(period_command(&d, &w), DDYN_DBW_ACTIVE);
    assert_true(fabs(w.throttle - 0.6) < 1e-4 && fabs(w.steering - 0.2) < 1e-4);
    /* nor does it count against a link that is recovering */
    deliver_period();
    for (i = 0; i < DDYN_DBW_FAIL_COUNT; ++i) {
        assert_int_equal(ctl.failures[i], i == (unsigned)DDYN_DBW_FAIL_UNKNOWN_FRAME ? 3u : 0u);
    }
}

static void test_stale(void **s) { (void)s; check_failure(DDYN_DBW_FAIL_STALE, inject_stale); }
static void test_counter_jump(void **s) { (void)s; check_failure(DDYN_DBW_FAIL_COUNTER_JUMP, inject_counter_jump); }
static void test_counter_repeat(void **s) { (void)s; check_failure(DDYN_DBW_FAIL_COUNTER_REPEAT, inject_counter_repeat); }
static void test_checksum(void **s) { (void)s; check_failure(DDYN_DBW_FAIL_CHECKSUM, inject_checksum); }
static void test_range(void **s) { (void)s; check_failure(DDYN_DBW_FAIL_RANGE, inject_range); }
static void test_bad_length(void **s) { (void)s; check_failure(DDYN_DBW_FAIL_BAD_LENGTH, inject_bad_length); }
static void test_bus_off(void **s) { (void)s; check_failure(DDYN_DBW_FAIL_BUS_OFF, inject_bus_off); }
static void test_iface_gone(void **s) { (void)s; check_failure(DDYN_DBW_FAIL_IFACE_GONE, inject_iface_gone); }

static void test_out_of_range_command_is_refused(void **state)
{
    ddyn_dbw_command d = driving(), w;
    (void)state;
    bring_to_active();
    assert_int_equal(period_command(&d, &w), DDYN_DBW_ACTIVE);
    d.steering = NAN;
    assert_int_equal(period_command(&d, &w), DDYN_DBW_WAIT_GOOD);
    assert_safe(&w, 0.2);
    assert_int_equal(ctl.failures[DDYN_DBW_FAIL_COMMAND_RANGE], 1u);
    bring_to_active();
    d = driving();
    d.throttle = 1.2;
    assert_int_equal(period_command(&d, &w), DDYN_DBW_WAIT_GOOD);
    assert_int_equal(ctl.failures[DDYN_DBW_FAIL_COMMAND_RANGE], 2u);
}

static void test_bad_frame_keeps_last_good_values(void **state)
{
    uint8_t data[8];
    const uint32_t id = ddyn_dbw_frame_id(DDYN_DBW_FRAME_GNSS_POSITION);
    double x;
    (void)state;
    deliver_period();
    x = ctl.latest.sensors.gnss_x;
    truth.sensors.gnss_x = 42.0;
    assert_int_equal(ddyn_dbw_next_frame(&sender, DDYN_DBW_FRAME_GNSS_POSITION, &truth, data), 0);
    data[7] ^= 0x01u;
    assert_int_equal(ddyn_dbw_on_frame(&ctl, id, data, 8, now), DDYN_DBW_DECODE_CHECKSUM);
    assert_true(ctl.latest.sensors.gnss_x == x);
    assert_int_equal(ddyn_dbw_take_fresh(&ctl) & (1u << DDYN_DBW_FRAME_GNSS_POSITION), 1u << DDYN_DBW_FRAME_GNSS_POSITION);
    assert_int_equal(ddyn_dbw_take_fresh(&ctl), 0u);
}

static void test_stale_is_counted_once_per_lapse(void **state)
{
    unsigned i;
    (void)state;
    bring_to_active();
    for (i = 0; i < 20; ++i) { /* nothing arrives for 200 ms */
        now += PERIOD_US;
        (void)ddyn_dbw_check(&ctl, now);
    }
    /* one lapse of each of the six monitored frames, not one per period */
    assert_int_equal(ctl.failures[DDYN_DBW_FAIL_STALE], 6u);
    /* after the gap any counter is accepted: the first frames back are good, not jumps */
    sender.tx_counter[DDYN_DBW_FRAME_IMU] = 9u;
    deliver_period();
    assert_int_equal(ctl.failures[DDYN_DBW_FAIL_COUNTER_JUMP], 0u);
}

static void test_fault_bits_for_the_status_frame(void **state)
{
    (void)state;
    assert_int_equal(ddyn_dbw_fault_bits(1u << DDYN_DBW_FAIL_STALE), DDYN_DBW_FAULT_CMD_TIMEOUT);
    assert_int_equal(ddyn_dbw_fault_bits(1u << DDYN_DBW_FAIL_COUNTER_REPEAT), DDYN_DBW_FAULT_CMD_COUNTER);
    assert_int_equal(ddyn_dbw_fault_bits((1u << DDYN_DBW_FAIL_CHECKSUM) | (1u << DDYN_DBW_FAIL_RANGE)),
                     DDYN_DBW_FAULT_CMD_CHECKSUM | DDYN_DBW_FAULT_CMD_RANGE);
    assert_int_equal(ddyn_dbw_fault_bits(0u), 0u);
    assert_string_equal(ddyn_dbw_failure_name(DDYN_DBW_FAIL_BUS_OFF), "bus_off");
    assert_string_equal(ddyn_dbw_frame_name(DDYN_DBW_FRAME_IMU), "IMU");
}

/* ---- authentication (SecOC-style authenticator frames, c_src/src/dbw_auth.c) ---- */

static int setup_auth(void **state)
{
    (void)setup(state);
    assert_int_equal(ddyn_dbw_auth_enable(&ctl, DDYN_DBW_TEST_KEY, 0u), 0);
    assert_int_equal(ddyn_dbw_auth_enable(&sender, DDYN_DBW_TEST_KEY, 0u), 0);
    return 0;
}

static unsigned auth_failures(void)
{
    return ctl.failures[DDYN_DBW_FAIL_AUTH_FORGED] + ctl.failures[DDYN_DBW_FAIL_AUTH_REPLAY] +
           ctl.failures[DDYN_DBW_FAIL_AUTH_STALE];
}

/* every failure count but the authentication ones is zero */
static void assert_no_link_failure(void)
{
    unsigned i;
    for (i = 0; i < DDYN_DBW_FAIL_AUTH_FORGED; ++i) {
        assert_int_equal(ctl.failures[i], 0u);
    }
}

static void test_auth_mac_is_keyed_blake2b(void **state)
{
    /* known answer from an independent BLAKE2b (Python's hashlib.blake2b(msg, key=key,
     * digest_size=8)): key 00..1f, identifier 0x100, data 01..08, freshness 0x0102030405060708 */
    uint8_t key[32], data[8];
    unsigned i;
    (void)state;
    for (i = 0; i < 32u; ++i) {
        key[i] = (uint8_t)i;
    }
    for (i = 0; i < 8u; ++i) {
        data[i] = (uint8_t)(i + 1u);
    }
    assert_int_equal(ddyn_dbw_auth_mac(key, 0x100u, data, 0x0102030405060708ull), 0xA3DC4Du);
    /* each input matters */
    assert_int_not_equal(ddyn_dbw_auth_mac(key, 0x110u, data, 0x0102030405060708ull), 0xA3DC4Du);
    assert_int_not_equal(ddyn_dbw_auth_mac(key, 0x100u, data, 0x0102030405060709ull), 0xA3DC4Du);
    data[3] ^= 1u;
    assert_int_not_equal(ddyn_dbw_auth_mac(key, 0x100u, data, 0x0102030405060708ull), 0xA3DC4Du);
}

static void test_auth_frames_share_one_layout(void **state)
{
    /* dbw_auth.c packs all three authenticators with SecOC_Controller's packer: the DBC gives them
     * one layout, and the generated packers of the other two agree byte for byte */
    struct ddyn_can_sec_oc_controller_t a = {0x11u, 0x2ABCDEu, 0x987654u, 9u, 0u};
    struct ddyn_can_sec_oc_dbw_t b = {0x11u, 0x2ABCDEu, 0x987654u, 9u, 0u};
    struct ddyn_can_sec_oc_sensors_t c = {0x11u, 0x2ABCDEu, 0x987654u, 9u, 0u};
    uint8_t pa[8], pb[8], pc[8];
    (void)state;
    assert_int_equal(ddyn_can_sec_oc_controller_pack(pa, &a, 8), 8);
    assert_int_equal(ddyn_can_sec_oc_dbw_pack(pb, &b, 8), 8);
    assert_int_equal(ddyn_can_sec_oc_sensors_pack(pc, &c, 8), 8);
    assert_memory_equal(pa, pb, 8);
    assert_memory_equal(pa, pc, 8);
    assert_int_equal(ddyn_dbw_auth_id(DDYN_DBW_FRAME_COMMAND), DDYN_CAN_SEC_OC_CONTROLLER_FRAME_ID);
    assert_int_equal(ddyn_dbw_auth_id(DDYN_DBW_FRAME_STATUS), DDYN_CAN_SEC_OC_DBW_FRAME_ID);
    assert_int_equal(ddyn_dbw_auth_id(DDYN_DBW_FRAME_GNSS_HEADING), DDYN_CAN_SEC_OC_SENSORS_FRAME_ID);
}

static void test_auth_valid_frames_are_accepted(void **state)
{
    ddyn_dbw_command d = driving(), w;
    uint8_t data[8];
    (void)state;
    /* a protected frame alone is held, not applied */
    assert_int_equal(ddyn_dbw_next_frame(&sender, DDYN_DBW_FRAME_IMU, &truth, data), 0);
    assert_int_equal(ddyn_dbw_on_frame(&ctl, ddyn_dbw_frame_id(DDYN_DBW_FRAME_IMU), data, 8, now),
                     DDYN_DBW_DECODE_AUTH_PENDING);
    assert_int_equal(ddyn_dbw_take_fresh(&ctl), 0u);
    sender.tx_counter[DDYN_DBW_FRAME_IMU] = 0u;
    /* with their authenticators, frames go through and the link comes up as without authentication */
    bring_to_active();
    assert_int_equal(period_command(&d, &w), DDYN_DBW_ACTIVE);
    assert_true(fabs(ctl.latest.sensors.yaw_rate - truth.sensors.yaw_rate) < 1e-3);
    assert_int_equal(ctl.auth.accepted, 6u * ctl.config.recovery_good_frames);
    assert_no_link_failure();
    /* the held IMU frame above was displaced by the first authenticated one: one stale frame */
    assert_int_equal(ctl.failures[DDYN_DBW_FAIL_AUTH_STALE], 1u);
    assert_int_equal(ctl.failures[DDYN_DBW_FAIL_AUTH_FORGED] + ctl.failures[DDYN_DBW_FAIL_AUTH_REPLAY], 0u);
}

static void test_auth_forged_mac_is_dropped_and_counted(void **state)
{
    /* a node without the key sends a steering measurement of its own, with a good counter and CRC
     * and an authenticator made with another key: counted, dropped, and the car keeps driving */
    ddyn_dbw_command d = driving(), w;
    uint8_t data[8], auth[8], wrong_key[32];
    ddyn_dbw_signals forged = truth;
    const double before = truth.feedback.steering;
    (void)state;
    bring_to_active();
    memset(wrong_key, 0x5A, sizeof wrong_key);
    forged.feedback.steering = 0.5;
    assert_int_equal(ddyn_dbw_encode(DDYN_DBW_FRAME_STEERING, &forged, sender.tx_counter[DDYN_DBW_FRAME_STEERING], data), 0);
    assert_int_equal(ddyn_dbw_on_frame(&ctl, ddyn_dbw_frame_id(DDYN_DBW_FRAME_STEERING), data, 8, now),
                     DDYN_DBW_DECODE_AUTH_PENDING);
    assert_int_equal(ddyn_dbw_auth_encode(wrong_key, DDYN_DBW_FRAME_STEERING, data,
                                          sender.auth.tx_freshness[DDYN_DBW_FRAME_STEERING], 0u, auth), 0);
    assert_int_equal(ddyn_dbw_on_frame(&ctl, DDYN_CAN_SEC_OC_DBW_FRAME_ID, auth, 8, now),
                     DDYN_DBW_DECODE_AUTH_REJECTED);
    assert_int_equal(ctl.failures[DDYN_DBW_FAIL_AUTH_FORGED], 1u);
    assert_true(fabs(ctl.latest.feedback.steering - before) < 1e-3); /* never applied */
    /* a forged authenticator with a flipped MAC bit for a genuine frame: the same */
    assert_int_equal(ddyn_dbw_next_frame(&sender, DDYN_DBW_FRAME_STEERING, &truth, data), 0);
    assert_int_equal(ddyn_dbw_on_frame(&ctl, ddyn_dbw_frame_id(DDYN_DBW_FRAME_STEERING), data, 8, now),
                     DDYN_DBW_DECODE_AUTH_PENDING);
    {
        uint32_t aid;
        assert_int_equal(ddyn_dbw_authenticator(&sender, DDYN_DBW_FRAME_STEERING, data, &aid, auth), 0);
        uint8_t fake[8];
        memcpy(fake, auth, 8);
        fake[5] ^= 0x10u; /* inside the MAC */
        fake[7] = ddyn_dbw_checksum(aid, fake);
        /* injected between the genuine frame and its authenticator */
        assert_int_equal(ddyn_dbw_on_frame(&ctl, aid, fake, 8, now), DDYN_DBW_DECODE_AUTH_REJECTED);
        /* and a forged frame too: the genuine one stays held beside it */
        assert_int_equal(ddyn_dbw_encode(DDYN_DBW_FRAME_STEERING, &forged, sender.tx_counter[DDYN_DBW_FRAME_STEERING], fake), 0);
        assert_int_equal(ddyn_dbw_on_frame(&ctl, ddyn_dbw_frame_id(DDYN_DBW_FRAME_STEERING), fake, 8, now),
                         DDYN_DBW_DECODE_AUTH_PENDING);
        /* the genuine authenticator still finds its frame */
        assert_int_equal(ddyn_dbw_on_frame(&ctl, aid, auth, 8, now), DDYN_DBW_DECODE_OK);
    }
    assert_int_equal(ctl.failures[DDYN_DBW_FAIL_AUTH_FORGED], 2u);
    /* with authentication on, a frame with a bad checksum or an out-of-range value (which anyone can
     * send) is counted, not fatal: only authenticated frames move the link */
    inject_checksum();
    inject_range();
    assert_int_equal(ctl.failures[DDYN_DBW_FAIL_CHECKSUM], 1u);
    assert_int_equal(ctl.failures[DDYN_DBW_FAIL_RANGE], 1u);
    ctl.failures[DDYN_DBW_FAIL_CHECKSUM] = ctl.failures[DDYN_DBW_FAIL_RANGE] = 0u;
    /* the link is not tripped: the command of this period is still the caller's */
    assert_int_equal(period_command(&d, &w), DDYN_DBW_ACTIVE);
    assert_true(fabs(w.steering - 0.2) < 1e-4);
    assert_no_link_failure();
    /* genuine frames go on (the rejected ones did not touch the counters: no jump) */
    deliver_period();
    assert_int_equal(period_command(&d, &w), DDYN_DBW_ACTIVE);
    assert_no_link_failure();
    assert_int_equal(ddyn_dbw_take_failures(&ctl) & ~((1u << DDYN_DBW_FAIL_AUTH_FORGED) | (1u << DDYN_DBW_FAIL_AUTH_STALE) |
                                                      (1u << DDYN_DBW_FAIL_CHECKSUM) | (1u << DDYN_DBW_FAIL_RANGE)),
                     0u);
}

static void test_auth_replayed_freshness_is_dropped(void **state)
{
    /* a recorded genuine pair (frame + authenticator) sent again later: valid MAC, old freshness */
    ddyn_dbw_command d = driving(), w;
    uint8_t data[8], auth[8];
    uint32_t aid;
    double yaw;
    (void)state;
    bring_to_active();
    assert_int_equal(ddyn_dbw_next_frame(&sender, DDYN_DBW_FRAME_IMU, &truth, data), 0);
    assert_int_equal(ddyn_dbw_authenticator(&sender, DDYN_DBW_FRAME_IMU, data, &aid, auth), 0);
    assert_int_equal(ddyn_dbw_on_frame(&ctl, ddyn_dbw_frame_id(DDYN_DBW_FRAME_IMU), data, 8, now),
                     DDYN_DBW_DECODE_AUTH_PENDING);
    assert_int_equal(ddyn_dbw_on_frame(&ctl, aid, auth, 8, now), DDYN_DBW_DECODE_OK);
    now += PERIOD_US;
    truth.sensors.yaw_rate = -1.0;
    deliver_period();
    yaw = ctl.latest.sensors.yaw_rate;
    assert_true(fabs(yaw + 1.0) < 1e-3);
    /* the replay */
    assert_int_equal(ddyn_dbw_on_frame(&ctl, ddyn_dbw_frame_id(DDYN_DBW_FRAME_IMU), data, 8, now),
                     DDYN_DBW_DECODE_AUTH_PENDING);
    assert_int_equal(ddyn_dbw_on_frame(&ctl, aid, auth, 8, now), DDYN_DBW_DECODE_AUTH_REJECTED);
    assert_int_equal(ctl.failures[DDYN_DBW_FAIL_AUTH_REPLAY], 1u);
    assert_true(ctl.latest.sensors.yaw_rate == yaw); /* the old value did not come back */
    /* the replay tripped nothing: the next genuine period drives on */
    deliver_period();
    assert_int_equal(period_command(&d, &w), DDYN_DBW_ACTIVE);
    assert_no_link_failure();
}

static void test_auth_stale_frames_are_dropped(void **state)
{
    ddyn_dbw_command d = driving(), w;
    uint8_t data[8], auth[8];
    uint32_t aid;
    (void)state;
    bring_to_active();
    /* an authenticator arriving after the timeout: the frame is stale, dropped */
    assert_int_equal(ddyn_dbw_next_frame(&sender, DDYN_DBW_FRAME_GNSS_HEADING, &truth, data), 0);
    assert_int_equal(ddyn_dbw_authenticator(&sender, DDYN_DBW_FRAME_GNSS_HEADING, data, &aid, auth), 0);
    assert_int_equal(ddyn_dbw_on_frame(&ctl, ddyn_dbw_frame_id(DDYN_DBW_FRAME_GNSS_HEADING), data, 8, now),
                     DDYN_DBW_DECODE_AUTH_PENDING);
    assert_int_equal(ddyn_dbw_on_frame(&ctl, aid, auth, 8, now + DDYN_DBW_AUTH_TIMEOUT_US + 1u),
                     DDYN_DBW_DECODE_AUTH_REJECTED);
    assert_int_equal(ctl.failures[DDYN_DBW_FAIL_AUTH_STALE], 1u);
    /* the late frame itself is dropped (and counted) by the next check */
    now += DDYN_DBW_AUTH_TIMEOUT_US + 1u;
    (void)ddyn_dbw_check(&ctl, now);
    assert_int_equal(ctl.failures[DDYN_DBW_FAIL_AUTH_STALE], 2u);
    /* an authenticator with no frame to vouch for (sent again): stale */
    assert_int_equal(ddyn_dbw_on_frame(&ctl, aid, auth, 8, now), DDYN_DBW_DECODE_AUTH_REJECTED);
    assert_int_equal(ctl.failures[DDYN_DBW_FAIL_AUTH_STALE], 3u);
    /* a frame whose authenticator never comes: dropped at the next check after the timeout */
    assert_int_equal(ddyn_dbw_next_frame(&sender, DDYN_DBW_FRAME_GNSS_HEADING, &truth, data), 0);
    assert_int_equal(ddyn_dbw_on_frame(&ctl, ddyn_dbw_frame_id(DDYN_DBW_FRAME_GNSS_HEADING), data, 8, now),
                     DDYN_DBW_DECODE_AUTH_PENDING);
    (void)ddyn_dbw_check(&ctl, now + DDYN_DBW_AUTH_TIMEOUT_US + 1u);
    assert_int_equal(ctl.failures[DDYN_DBW_FAIL_AUTH_STALE], 4u);
    /* none of it tripped the link, and the two dropped frames (whose counter values the controller
     * never saw) do not come back as a counter jump of the next genuine frame */
    now += PERIOD_US;
    deliver_period();
    assert_int_equal(period_command(&d, &w), DDYN_DBW_ACTIVE);
    assert_no_link_failure();
}

static void test_auth_forged_steering_command_is_rejected_by_the_dbw_unit(void **state)
{
    /* the DBW unit's side: commands authenticated by the controller go through; a steering command
     * injected by another node (good counter, good CRC, no valid MAC) never reaches the actuators */
    ddyn_dbw unit, controller;
    ddyn_dbw_config c;
    ddyn_dbw_signals s;
    uint8_t data[8], auth[8];
    uint32_t aid;
    unsigned i;
    (void)state;
    ddyn_dbw_default_config(&c, DDYN_DBW_MONITOR_DBW_UNIT);
    assert_int_equal(ddyn_dbw_init(&unit, &c), 0);
    assert_int_equal(ddyn_dbw_auth_enable(&unit, DDYN_DBW_TEST_KEY, 0u), 0);
    ddyn_dbw_default_config(&c, DDYN_DBW_MONITOR_CONTROLLER);
    assert_int_equal(ddyn_dbw_init(&controller, &c), 0);
    assert_int_equal(ddyn_dbw_auth_enable(&controller, DDYN_DBW_TEST_KEY, 0u), 0);
    memset(&s, 0, sizeof s);
    for (i = 0; i < 10u; ++i) {
        s.command.throttle = 0.8;
        s.command.steering = 0.05;
        s.command.enable = true;
        s.command.mode = DDYN_DBW_MODE_AUTONOMOUS;
        assert_int_equal(ddyn_dbw_next_frame(&controller, DDYN_DBW_FRAME_COMMAND, &s, data), 0);
        assert_int_equal(ddyn_dbw_authenticator(&controller, DDYN_DBW_FRAME_COMMAND, data, &aid, auth), 0);
        assert_int_equal(ddyn_dbw_on_frame(&unit, ddyn_dbw_frame_id(DDYN_DBW_FRAME_COMMAND), data, 8, now),
                         DDYN_DBW_DECODE_AUTH_PENDING);
        assert_int_equal(ddyn_dbw_on_frame(&unit, aid, auth, 8, now + 50u), DDYN_DBW_DECODE_OK);
        assert_true(fabs(unit.latest.command.steering - 0.05) < 1e-4);
        if (i == 5u) {
            /* the attacker: full left, the next counter, a valid CRC, and a guessed authenticator */
            s.command.steering = 0.6;
            assert_int_equal(ddyn_dbw_encode(DDYN_DBW_FRAME_COMMAND, &s, controller.tx_counter[DDYN_DBW_FRAME_COMMAND], data), 0);
            assert_int_equal(ddyn_dbw_on_frame(&unit, ddyn_dbw_frame_id(DDYN_DBW_FRAME_COMMAND), data, 8, now + 100u),
                             DDYN_DBW_DECODE_AUTH_PENDING);
            memcpy(auth, data, 8);
            auth[0] = (uint8_t)(DDYN_CAN_DBW_COMMAND_FRAME_ID - 0x100u);
            auth[7] = ddyn_dbw_checksum(aid, auth);
            assert_int_equal(ddyn_dbw_on_frame(&unit, aid, auth, 8, now + 150u), DDYN_DBW_DECODE_AUTH_REJECTED);
            assert_true(fabs(unit.latest.command.steering - 0.05) < 1e-4);
        }
        now += PERIOD_US;
        (void)ddyn_dbw_check(&unit, now);
    }
    assert_int_equal(unit.failures[DDYN_DBW_FAIL_AUTH_FORGED] + unit.failures[DDYN_DBW_FAIL_AUTH_REPLAY], 1u);
    for (i = 0; i < DDYN_DBW_FAIL_AUTH_FORGED; ++i) {
        assert_int_equal(unit.failures[i], 0u);
    }
    assert_int_equal(ddyn_dbw_check(&unit, now), DDYN_DBW_READY);
    (void)auth_failures;
}

static void test_auth_key_file_is_read_and_a_readable_one_refused(void **state)
{
    uint8_t key[32];
    const char *why = "x";
    const char *scratch = DDYN_TEST_SCRATCH_DIR "/dbw_key_world_readable.key";
    FILE *f;
    (void)state;
    assert_int_equal(ddyn_dbw_auth_read_key_file(DDYN_DBW_TEST_KEY_FILE, key, &why), 0);
    assert_null(why);
    assert_memory_equal(key, DDYN_DBW_TEST_KEY, 32);
    assert_string_equal(ddyn_dbw_auth_key_path("/etc/car.key"), "/etc/car.key");
    /* the same key in a file others can read: refused, the buffer wiped */
    f = fopen(scratch, "w");
    assert_non_null(f);
    fputs("a4a1e444efc3eccb69541e28ded12f94509d6b135a2ba7d482d96370678aa803\n", f);
    fclose(f);
    assert_int_equal(chmod(scratch, 0644), 0);
    assert_int_equal(ddyn_dbw_auth_read_key_file(scratch, key, &why), DDYN_ERR_CONFIG);
    assert_non_null(why);
    assert_true(key[0] == 0u && key[31] == 0u);
    /* owner-only but not hex */
    f = fopen(scratch, "w");
    assert_non_null(f);
    fputs("zz", f);
    fclose(f);
    assert_int_equal(chmod(scratch, 0600), 0);
    assert_int_equal(ddyn_dbw_auth_read_key_file(scratch, key, &why), DDYN_ERR_CONFIG);
    assert_int_equal(ddyn_dbw_auth_read_key_file("/nonexistent/dbw.key", key, &why), DDYN_ERR_CONFIG);
    (void)remove(scratch);
}

/* ---- frame ages on a degraded bus (ddyn_dbw_link) ---- */

static ddyn_dbw_link_result link_frame(ddyn_dbw_link *l, ddyn_dbw_frame f, unsigned counter, unsigned *lost, double *age)
{
    return ddyn_dbw_link_on_frame(l, f, (uint8_t)(counter % 16u), lost, age);
}

static void test_link_counts_lost_late_repeated_and_bad_frames(void **state)
{
    ddyn_dbw_link l;
    unsigned lost = 99u;
    double age = -1.0;
    (void)state;
    ddyn_dbw_link_init(&l);
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 14u, &lost, &age), DDYN_DBW_LINK_NEW);
    assert_int_equal(lost, 0u);
    assert_true(age == 0.0);
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 15u, &lost, &age), DDYN_DBW_LINK_NEW);
    assert_int_equal(ddyn_dbw_link_take_faults(&l), 0u); /* a clean bus */
    /* 15 -> 2 (wrapping): frames 0 and 1 were lost */
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 2u, &lost, &age), DDYN_DBW_LINK_NEW);
    assert_int_equal(lost, 2u);
    /* frame 1 arrives after all: older than the newest, refused */
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 1u, &lost, &age), DDYN_DBW_LINK_LATE);
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 2u, &lost, &age), DDYN_DBW_LINK_REPEATED);
    ddyn_dbw_link_on_bad_frame(&l);
    assert_int_equal(l.lost, 2u);
    assert_int_equal(l.late, 1u);
    assert_int_equal(l.repeated, 1u);
    assert_int_equal(ddyn_dbw_link_take_faults(&l), 5u);
    assert_int_equal(ddyn_dbw_link_take_faults(&l), 0u); /* read and cleared */
    assert_int_equal(link_frame(NULL, DDYN_DBW_FRAME_IMU, 3u, &lost, &age), DDYN_DBW_LINK_REPEATED);
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_COUNT, 3u, NULL, NULL), DDYN_DBW_LINK_REPEATED);
    assert_true(ddyn_dbw_link_age(&l, DDYN_DBW_FRAME_GNSS_POSITION) == -1.0); /* never received */
}

static void test_link_counts_saturate_instead_of_wrapping(void **state)
{
    /* a link left running (or flooded) must not wrap its fault counts back to small numbers: they
     * stop at UINT32_MAX, and so does their sum (issue 35) */
    ddyn_dbw_link l;
    unsigned lost;
    double age;
    (void)state;
    ddyn_dbw_link_init(&l);
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 0u, &lost, &age), DDYN_DBW_LINK_NEW);
    l.lost = UINT32_MAX - 1u;
    l.late = UINT32_MAX;
    l.repeated = UINT32_MAX;
    l.bad = UINT32_MAX;
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 5u, &lost, &age), DDYN_DBW_LINK_NEW); /* 4 lost */
    assert_int_equal(lost, 4u);
    assert_true(l.lost == UINT32_MAX);
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 4u, &lost, &age), DDYN_DBW_LINK_LATE);
    assert_true(l.late == UINT32_MAX);
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 5u, &lost, &age), DDYN_DBW_LINK_REPEATED);
    assert_true(l.repeated == UINT32_MAX);
    ddyn_dbw_link_on_bad_frame(&l);
    assert_true(l.bad == UINT32_MAX);
    assert_true(ddyn_dbw_link_take_faults(&l) == UINT32_MAX);
    assert_int_equal(ddyn_dbw_link_take_faults(&l), 0u);
    l.lost = 3u;
    l.late = UINT32_MAX - 1u;
    assert_true(ddyn_dbw_link_take_faults(&l) == UINT32_MAX);
}

static void test_link_measures_the_age_of_a_delayed_frame(void **state)
{
    /* IMU (10 ms) and GNSS position (20 ms) sampled together; the GNSS frame of 20 ms arrives only
     * after the IMU frames of 30 and 40 ms: it is 20 ms older than the freshest data */
    ddyn_dbw_link l;
    double age = -1.0;
    unsigned lost;
    (void)state;
    ddyn_dbw_link_init(&l);
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 0u, &lost, &age), DDYN_DBW_LINK_NEW); /* t = 0 */
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_GNSS_POSITION, 0u, &lost, &age), DDYN_DBW_LINK_NEW);
    assert_true(age == 0.0);
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 1u, &lost, &age), DDYN_DBW_LINK_NEW); /* 10 ms */
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 2u, &lost, &age), DDYN_DBW_LINK_NEW); /* 20 ms */
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 3u, &lost, &age), DDYN_DBW_LINK_NEW); /* 30 ms */
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 4u, &lost, &age), DDYN_DBW_LINK_NEW); /* 40 ms */
    assert_true(fabs(age) < 1e-12);
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_GNSS_POSITION, 1u, &lost, &age), DDYN_DBW_LINK_NEW);
    assert_true(fabs(age - 0.020) < 1e-12);
    assert_true(fabs(ddyn_dbw_link_age(&l, DDYN_DBW_FRAME_GNSS_POSITION) - 0.020) < 1e-12);
    assert_true(fabs(ddyn_dbw_link_age(&l, DDYN_DBW_FRAME_IMU)) < 1e-12);
    /* the next one on time: fresh again; a lost frame in between does not age the stream */
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 5u, &lost, &age), DDYN_DBW_LINK_NEW);
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 6u, &lost, &age), DDYN_DBW_LINK_NEW); /* 60 ms */
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_GNSS_POSITION, 3u, &lost, &age), DDYN_DBW_LINK_NEW);
    assert_int_equal(lost, 1u);
    assert_true(fabs(age) < 1e-12);
}

static void test_link_tick_aligns_a_stream_whose_first_frame_looked_old(void **state)
{
    /* the heading frame of 20 ms arrives just before the IMU frame of the same instant: taken as
     * sampled at 10 ms, it looks 10 ms old at the period; the first tick moves its phase, and from
     * then on frames of that instant are fresh */
    ddyn_dbw_link l;
    double age;
    unsigned lost, k;
    (void)state;
    ddyn_dbw_link_init(&l);
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 0u, &lost, &age), DDYN_DBW_LINK_NEW); /* 0 */
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 1u, &lost, &age), DDYN_DBW_LINK_NEW); /* 10 ms */
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_GNSS_HEADING, 0u, &lost, &age), DDYN_DBW_LINK_NEW);
    assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 2u, &lost, &age), DDYN_DBW_LINK_NEW); /* 20 ms */
    assert_true(fabs(ddyn_dbw_link_age(&l, DDYN_DBW_FRAME_GNSS_HEADING) - 0.010) < 1e-12);
    ddyn_dbw_link_tick(&l);
    assert_true(fabs(ddyn_dbw_link_age(&l, DDYN_DBW_FRAME_GNSS_HEADING)) < 1e-12);
    for (k = 1u; k < 40u; ++k) { /* the same order for 40 more periods: stays fresh */
        assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 2u * k + 1u, &lost, &age), DDYN_DBW_LINK_NEW);
        assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_GNSS_HEADING, k, &lost, &age), DDYN_DBW_LINK_NEW);
        assert_int_equal(link_frame(&l, DDYN_DBW_FRAME_IMU, 2u * k + 2u, &lost, &age), DDYN_DBW_LINK_NEW);
        ddyn_dbw_link_tick(&l);
        assert_true(fabs(ddyn_dbw_link_age(&l, DDYN_DBW_FRAME_GNSS_HEADING)) < 1e-9);
    }
}

static void test_link_dates_each_stream_at_its_own_cycle(void **state)
{
    /* issue 34: the AV-21 sends its GNSS frames once per 40 ms period, the DBC says 20 ms. Dated at
     * the DBC's cycle, a clean GNSS stream falls 20 ms further behind the 100 Hz IMU at every frame,
     * and the phase correction (one window of 16 periods) comes too late: the controller saw every
     * period as late. Told the real cycle, the same clean bus shows no age at all. */
    ddyn_dbw_link wrong, right;
    double age, worst_wrong = 0.0, worst_right = 0.0;
    unsigned lost, k, i;
    (void)state;
    ddyn_dbw_link_init(&wrong);
    ddyn_dbw_link_init(&right);
    assert_true(fabs(ddyn_dbw_link_cycle(&right, DDYN_DBW_FRAME_GNSS_POSITION) - 0.020) < 1e-12); /* the DBC's */
    assert_int_equal(ddyn_dbw_link_set_cycle(&right, DDYN_DBW_FRAME_GNSS_POSITION, 40000u), DDYN_OK);
    assert_int_equal(ddyn_dbw_link_set_cycle(&right, DDYN_DBW_FRAME_GNSS_HEADING, 40000u), DDYN_OK);
    assert_true(fabs(ddyn_dbw_link_cycle(&right, DDYN_DBW_FRAME_GNSS_POSITION) - 0.040) < 1e-12);
    assert_true(fabs(ddyn_dbw_link_cycle(&right, DDYN_DBW_FRAME_IMU) - 0.010) < 1e-12); /* untouched */
    for (k = 1u; k <= 100u; ++k) { /* 4 s of a clean bus: four IMU frames, then heading and position */
        ddyn_dbw_link *links[2];
        links[0] = &wrong;
        links[1] = &right;
        for (i = 0u; i < 2u; ++i) {
            unsigned n;
            for (n = 0u; n < 4u; ++n) {
                assert_int_equal(link_frame(links[i], DDYN_DBW_FRAME_IMU, 4u * k + n, &lost, &age), DDYN_DBW_LINK_NEW);
            }
            assert_int_equal(link_frame(links[i], DDYN_DBW_FRAME_GNSS_HEADING, k, &lost, &age), DDYN_DBW_LINK_NEW);
            assert_int_equal(link_frame(links[i], DDYN_DBW_FRAME_GNSS_POSITION, k, &lost, &age), DDYN_DBW_LINK_NEW);
            assert_int_equal(lost, 0u);
            ddyn_dbw_link_tick(links[i]);
        }
        if (k > 1u) { /* after the first period (the first window) */
            double a = ddyn_dbw_link_age(&wrong, DDYN_DBW_FRAME_GNSS_POSITION);
            worst_wrong = a > worst_wrong ? a : worst_wrong;
            a = ddyn_dbw_link_age(&right, DDYN_DBW_FRAME_GNSS_POSITION);
            worst_right = a > worst_right ? a : worst_right;
            a = ddyn_dbw_link_age(&right, DDYN_DBW_FRAME_GNSS_HEADING);
            worst_right = a > worst_right ? a : worst_right;
            a = ddyn_dbw_link_age(&right, DDYN_DBW_FRAME_IMU);
            worst_right = a > worst_right ? a : worst_right;
        }
    }
    assert_int_equal(ddyn_dbw_link_take_faults(&right), 0u);
    assert_true(worst_right < 1e-9);
    assert_true(worst_wrong > 0.040); /* older than a whole 40 ms period: the old reading of a clean bus */
    /* 0 restores the DBC's; unknown frames, NULL and cycles beyond the DBC's range are refused */
    assert_int_equal(ddyn_dbw_link_set_cycle(&right, DDYN_DBW_FRAME_GNSS_HEADING, 0u), DDYN_OK);
    assert_true(fabs(ddyn_dbw_link_cycle(&right, DDYN_DBW_FRAME_GNSS_HEADING) - 0.020) < 1e-12);
    assert_int_equal(ddyn_dbw_link_set_cycle(&right, DDYN_DBW_FRAME_COUNT, 40000u), DDYN_ERR_ARGUMENT);
    assert_int_equal(ddyn_dbw_link_set_cycle(NULL, DDYN_DBW_FRAME_IMU, 40000u), DDYN_ERR_ARGUMENT);
    assert_int_equal(ddyn_dbw_link_set_cycle(&right, DDYN_DBW_FRAME_IMU, 10000001u), DDYN_ERR_ARGUMENT);
    assert_true(ddyn_dbw_link_cycle(NULL, DDYN_DBW_FRAME_IMU) == -1.0);
    assert_true(ddyn_dbw_link_cycle(&right, DDYN_DBW_FRAME_COUNT) == -1.0);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test_setup(test_checksum_is_crc8_sae_j1850, setup),
        cmocka_unit_test_setup(test_every_frame_round_trips_within_half_a_bit, setup),
        cmocka_unit_test_setup(test_encode_refuses_out_of_range_and_non_finite, setup),
        cmocka_unit_test_setup(test_decode_names_each_defect, setup),
        cmocka_unit_test_setup(test_init_refuses_bad_configs, setup),
        cmocka_unit_test_setup(test_starts_safe_and_needs_good_frames_and_enable, setup),
        cmocka_unit_test_setup(test_stale, setup),
        cmocka_unit_test_setup(test_counter_jump, setup),
        cmocka_unit_test_setup(test_counter_repeat, setup),
        cmocka_unit_test_setup(test_checksum, setup),
        cmocka_unit_test_setup(test_defect_in_an_unmonitored_frame_is_counted_not_fatal, setup),
        cmocka_unit_test_setup(test_range, setup),
        cmocka_unit_test_setup(test_unknown_frame_is_counted_not_fatal, setup),
        cmocka_unit_test_setup(test_bad_length, setup),
        cmocka_unit_test_setup(test_bus_off, setup),
        cmocka_unit_test_setup(test_iface_gone, setup),
        cmocka_unit_test_setup(test_out_of_range_command_is_refused, setup),
        cmocka_unit_test_setup(test_bad_frame_keeps_last_good_values, setup),
        cmocka_unit_test_setup(test_stale_is_counted_once_per_lapse, setup),
        cmocka_unit_test_setup(test_fault_bits_for_the_status_frame, setup),
        cmocka_unit_test(test_auth_mac_is_keyed_blake2b),
        cmocka_unit_test(test_auth_frames_share_one_layout),
        cmocka_unit_test_setup(test_auth_valid_frames_are_accepted, setup_auth),
        cmocka_unit_test_setup(test_auth_forged_mac_is_dropped_and_counted, setup_auth),
        cmocka_unit_test_setup(test_auth_replayed_freshness_is_dropped, setup_auth),
        cmocka_unit_test_setup(test_auth_stale_frames_are_dropped, setup_auth),
        cmocka_unit_test_setup(test_auth_forged_steering_command_is_rejected_by_the_dbw_unit, setup),
        cmocka_unit_test(test_auth_key_file_is_read_and_a_readable_one_refused),
        cmocka_unit_test(test_link_counts_lost_late_repeated_and_bad_frames),
        cmocka_unit_test(test_link_counts_saturate_instead_of_wrapping),
        cmocka_unit_test(test_link_measures_the_age_of_a_delayed_frame),
        cmocka_unit_test(test_link_tick_aligns_a_stream_whose_first_frame_looked_old),
        cmocka_unit_test(test_link_dates_each_stream_at_its_own_cycle),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
