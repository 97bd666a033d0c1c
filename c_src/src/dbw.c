/*
 * Drive-by-wire protocol logic (ddyn/dbw.h): counters, checksums, range checks, deadlines,
 * failure counting, the safe command and explicit recovery. The bit layout of every frame
 * comes from the cantools-generated ddyn_can.{h,c}; nothing here knows a bit position
 * except the two the DBC comment fixes for every frame (Counter bits 52-55, Checksum byte 7).
 */
#include "ddyn/dbw.h"

#include <math.h>
#include <string.h>

#include "ddyn_can.h"

#define CHECKSUM_BYTE 7u

static const uint32_t FRAME_IDS[DDYN_DBW_FRAME_COUNT] = {
    DDYN_CAN_DBW_COMMAND_FRAME_ID,      DDYN_CAN_DBW_STEERING_FRAME_ID, DDYN_CAN_DBW_STATUS_FRAME_ID,
    DDYN_CAN_DBW_WHEEL_SPEEDS_FRAME_ID, DDYN_CAN_IMU_FRAME_ID,          DDYN_CAN_GNSS_POSITION_FRAME_ID,
    DDYN_CAN_GNSS_HEADING_FRAME_ID,
};

static const uint32_t CYCLE_MS[DDYN_DBW_FRAME_COUNT] = {
    DDYN_CAN_DBW_COMMAND_CYCLE_TIME_MS,      DDYN_CAN_DBW_STEERING_CYCLE_TIME_MS, DDYN_CAN_DBW_STATUS_CYCLE_TIME_MS,
    DDYN_CAN_DBW_WHEEL_SPEEDS_CYCLE_TIME_MS, DDYN_CAN_IMU_CYCLE_TIME_MS,          DDYN_CAN_GNSS_POSITION_CYCLE_TIME_MS,
    DDYN_CAN_GNSS_HEADING_CYCLE_TIME_MS,
};

uint32_t ddyn_dbw_frame_id(ddyn_dbw_frame frame)
{
    return ((unsigned)frame < DDYN_DBW_FRAME_COUNT) ? FRAME_IDS[frame] : 0u;
}

int ddyn_dbw_frame_of_id(uint32_t can_id)
{
    int f;
    for (f = 0; f < (int)DDYN_DBW_FRAME_COUNT; ++f) {
        if (FRAME_IDS[f] == can_id) {
            return f;
        }
    }
    return -1;
}

bool ddyn_dbw_is_authenticator_id(uint32_t can_id)
{
    return can_id == DDYN_CAN_SEC_OC_CONTROLLER_FRAME_ID || can_id == DDYN_CAN_SEC_OC_DBW_FRAME_ID ||
           can_id == DDYN_CAN_SEC_OC_SENSORS_FRAME_ID;
}

uint32_t ddyn_dbw_cycle_us(ddyn_dbw_frame frame)
{
    return ((unsigned)frame < DDYN_DBW_FRAME_COUNT) ? CYCLE_MS[frame] * 1000u : 0u;
}

/* CRC-8/SAE-J1850: poly 0x1D, init 0xFF, xorout 0xFF, no reflection (check value 0x4B over
 * "123456789"); bitwise rather than a table: 9 bytes per frame do not need 256 bytes of ROM. */
static uint8_t crc8_update(uint8_t crc, uint8_t byte)
{
    unsigned bit;
    crc ^= byte;
    for (bit = 0; bit < 8u; ++bit) {
        crc = (uint8_t)((crc & 0x80u) ? (uint8_t)(crc << 1) ^ 0x1Du : (uint8_t)(crc << 1));
    }
    return crc;
}

uint8_t ddyn_dbw_checksum(uint32_t can_id, const uint8_t data[DDYN_DBW_FRAME_LEN])
{
    uint8_t crc = 0xFFu;
    unsigned i;
    crc = crc8_update(crc, (uint8_t)(can_id & 0xFFu));
    crc = crc8_update(crc, (uint8_t)((can_id >> 8) & 0xFFu));
    for (i = 0; i < CHECKSUM_BYTE; ++i) {
        crc = crc8_update(crc, data[i]);
    }
    return (uint8_t)(crc ^ 0xFFu);
}

/* ---- encoding: physical -> raw -> bytes, range-checked before encoding (cantools' encode wraps) ---- */

static int encode_command(const ddyn_dbw_command *c, uint8_t counter, uint8_t *data)
{
    struct ddyn_can_dbw_command_t m;
    if (!ddyn_can_dbw_command_throttle_is_in_phys_range(c->throttle) ||
        !ddyn_can_dbw_command_brake_is_in_phys_range(c->brake) ||
        !ddyn_can_dbw_command_steering_angle_is_in_phys_range(c->steering) ||
        !ddyn_can_dbw_command_mode_is_in_range((uint8_t)c->mode) || (unsigned)c->mode > 2u) {
        return -1;
    }
    m.throttle = ddyn_can_dbw_command_throttle_encode(c->throttle);
    m.brake = ddyn_can_dbw_command_brake_encode(c->brake);
    m.steering_angle = ddyn_can_dbw_command_steering_angle_encode(c->steering);
    m.enable = c->enable ? 1u : 0u;
    m.mode = (uint8_t)c->mode;
    m.counter = counter;
    m.checksum = 0u;
    return ddyn_can_dbw_command_pack(data, &m, DDYN_DBW_FRAME_LEN) == (int)DDYN_DBW_FRAME_LEN ? 0 : -1;
}

static int encode_steering(const ddyn_dbw_feedback *f, uint8_t counter, uint8_t *data)
{
    struct ddyn_can_dbw_steering_t m;
    if (!ddyn_can_dbw_steering_steering_angle_is_in_phys_range(f->steering) ||
        !ddyn_can_dbw_steering_steering_rate_is_in_phys_range(f->steering_rate)) {
        return -1;
    }
    m.steering_angle = ddyn_can_dbw_steering_steering_angle_encode(f->steering);
    m.steering_rate = ddyn_can_dbw_steering_steering_rate_encode(f->steering_rate);
    m.counter = counter;
    m.checksum = 0u;
    return ddyn_can_dbw_steering_pack(data, &m, DDYN_DBW_FRAME_LEN) == (int)DDYN_DBW_FRAME_LEN ? 0 : -1;
}

static int encode_status(const ddyn_dbw_feedback *f, uint8_t counter, uint8_t *data)
{
    struct ddyn_can_dbw_status_t m;
    if (!ddyn_can_dbw_status_throttle_pedal_is_in_phys_range(f->throttle_pedal) ||
        !ddyn_can_dbw_status_brake_pedal_is_in_phys_range(f->brake_pedal) || (unsigned)f->mode > 2u ||
        !ddyn_can_dbw_status_faults_is_in_range(f->faults)) {
        return -1;
    }
    m.throttle_pedal = ddyn_can_dbw_status_throttle_pedal_encode(f->throttle_pedal);
    m.brake_pedal = ddyn_can_dbw_status_brake_pedal_encode(f->brake_pedal);
    m.mode = (uint8_t)f->mode;
    m.enabled = f->enabled ? 1u : 0u;
    m.driver_override = f->driver_override ? 1u : 0u;
    m.faults = f->faults;
    m.counter = counter;
    m.checksum = 0u;
    return ddyn_can_dbw_status_pack(data, &m, DDYN_DBW_FRAME_LEN) == (int)DDYN_DBW_FRAME_LEN ? 0 : -1;
}

static int encode_wheel_speeds(const ddyn_dbw_feedback *f, uint8_t counter, uint8_t *data)
{
    struct ddyn_can_dbw_wheel_speeds_t m;
    if (!ddyn_can_dbw_wheel_speeds_wheel_speed_front_is_in_phys_range(f->wheel_speed_front) ||
        !ddyn_can_dbw_wheel_speeds_wheel_speed_rear_is_in_phys_range(f->wheel_speed_rear)) {
        return -1;
    }
    m.wheel_speed_front = ddyn_can_dbw_wheel_speeds_wheel_speed_front_encode(f->wheel_speed_front);
    m.wheel_speed_rear = ddyn_can_dbw_wheel_speeds_wheel_speed_rear_encode(f->wheel_speed_rear);
    m.counter = counter;
    m.checksum = 0u;
    return ddyn_can_dbw_wheel_speeds_pack(data, &m, DDYN_DBW_FRAME_LEN) == (int)DDYN_DBW_FRAME_LEN ? 0 : -1;
}

static int encode_imu(const ddyn_dbw_sensors *s, uint8_t counter, uint8_t *data)
{
    struct ddyn_can_imu_t m;
    if (!ddyn_can_imu_yaw_rate_is_in_phys_range(s->yaw_rate) || !ddyn_can_imu_accel_x_is_in_phys_range(s->accel_x) ||
        !ddyn_can_imu_accel_y_is_in_phys_range(s->accel_y)) {
        return -1;
    }
    m.yaw_rate = ddyn_can_imu_yaw_rate_encode(s->yaw_rate);
    m.accel_x = ddyn_can_imu_accel_x_encode(s->accel_x);
    m.accel_y = ddyn_can_imu_accel_y_encode(s->accel_y);
    m.counter = counter;
    m.checksum = 0u;
    return ddyn_can_imu_pack(data, &m, DDYN_DBW_FRAME_LEN) == (int)DDYN_DBW_FRAME_LEN ? 0 : -1;
}

static int encode_gnss_position(const ddyn_dbw_sensors *s, uint8_t counter, uint8_t *data)
{
    struct ddyn_can_gnss_position_t m;
    if (!ddyn_can_gnss_position_position_x_is_in_phys_range(s->gnss_x) ||
        !ddyn_can_gnss_position_position_y_is_in_phys_range(s->gnss_y)) {
        return -1;
    }
    m.position_x = ddyn_can_gnss_position_position_x_encode(s->gnss_x);
    m.position_y = ddyn_can_gnss_position_position_y_encode(s->gnss_y);
    m.counter = counter;
    m.checksum = 0u;
    return ddyn_can_gnss_position_pack(data, &m, DDYN_DBW_FRAME_LEN) == (int)DDYN_DBW_FRAME_LEN ? 0 : -1;
}

static int encode_gnss_heading(const ddyn_dbw_sensors *s, uint8_t counter, uint8_t *data)
{
    struct ddyn_can_gnss_heading_t m;
    if (!ddyn_can_gnss_heading_heading_is_in_phys_range(s->heading) ||
        !ddyn_can_gnss_heading_fix_type_is_in_range(s->fix_type)) {
        return -1;
    }
    m.heading = ddyn_can_gnss_heading_heading_encode(s->heading);
    m.fix_type = s->fix_type;
    m.counter = counter;
    m.checksum = 0u;
    return ddyn_can_gnss_heading_pack(data, &m, DDYN_DBW_FRAME_LEN) == (int)DDYN_DBW_FRAME_LEN ? 0 : -1;
}

ddyn_status ddyn_dbw_encode(ddyn_dbw_frame frame, const ddyn_dbw_signals *s, uint8_t counter,
                            uint8_t data[DDYN_DBW_FRAME_LEN])
{
    int rc;
    if (s == NULL || data == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    counter = (uint8_t)(counter % DDYN_DBW_COUNTER_MODULO);
    switch (frame) {
    case DDYN_DBW_FRAME_COMMAND: rc = encode_command(&s->command, counter, data); break;
    case DDYN_DBW_FRAME_STEERING: rc = encode_steering(&s->feedback, counter, data); break;
    case DDYN_DBW_FRAME_STATUS: rc = encode_status(&s->feedback, counter, data); break;
    case DDYN_DBW_FRAME_WHEEL_SPEEDS: rc = encode_wheel_speeds(&s->feedback, counter, data); break;
    case DDYN_DBW_FRAME_IMU: rc = encode_imu(&s->sensors, counter, data); break;
    case DDYN_DBW_FRAME_GNSS_POSITION: rc = encode_gnss_position(&s->sensors, counter, data); break;
    case DDYN_DBW_FRAME_GNSS_HEADING: rc = encode_gnss_heading(&s->sensors, counter, data); break;
    default: return DDYN_ERR_ARGUMENT;
    }
    if (rc != 0) {
        return DDYN_ERR_RANGE;
    }
    data[CHECKSUM_BYTE] = ddyn_dbw_checksum(FRAME_IDS[frame], data);
    return DDYN_OK;
}

/* ---- decoding: bytes -> raw (range-checked) -> physical ---- */

static ddyn_dbw_decode_result decode_command(const uint8_t *data, ddyn_dbw_signals *s, uint8_t *counter)
{
    struct ddyn_can_dbw_command_t m;
    (void)ddyn_can_dbw_command_unpack(&m, data, DDYN_DBW_FRAME_LEN);
    if (!ddyn_can_dbw_command_throttle_is_in_range(m.throttle) || !ddyn_can_dbw_command_brake_is_in_range(m.brake) ||
        !ddyn_can_dbw_command_steering_angle_is_in_range(m.steering_angle) ||
        !ddyn_can_dbw_command_mode_is_in_range(m.mode)) {
        return DDYN_DBW_DECODE_RANGE;
    }
    s->command.throttle = ddyn_can_dbw_command_throttle_decode(m.throttle);
    s->command.brake = ddyn_can_dbw_command_brake_decode(m.brake);
    s->command.steering = ddyn_can_dbw_command_steering_angle_decode(m.steering_angle);
    s->command.enable = m.enable != 0u;
    s->command.mode = (ddyn_dbw_mode)m.mode;
    *counter = m.counter;
    return DDYN_DBW_DECODE_OK;
}

static ddyn_dbw_decode_result decode_steering(const uint8_t *data, ddyn_dbw_signals *s, uint8_t *counter)
{
    struct ddyn_can_dbw_steering_t m;
    (void)ddyn_can_dbw_steering_unpack(&m, data, DDYN_DBW_FRAME_LEN);
    if (!ddyn_can_dbw_steering_steering_angle_is_in_range(m.steering_angle) ||
        !ddyn_can_dbw_steering_steering_rate_is_in_range(m.steering_rate)) {
        return DDYN_DBW_DECODE_RANGE;
    }
    s->feedback.steering = ddyn_can_dbw_steering_steering_angle_decode(m.steering_angle);
    s->feedback.steering_rate = ddyn_can_dbw_steering_steering_rate_decode(m.steering_rate);
    *counter = m.counter;
    return DDYN_DBW_DECODE_OK;
}

static ddyn_dbw_decode_result decode_status(const uint8_t *data, ddyn_dbw_signals *s, uint8_t *counter)
{
    struct ddyn_can_dbw_status_t m;
    (void)ddyn_can_dbw_status_unpack(&m, data, DDYN_DBW_FRAME_LEN);
    if (!ddyn_can_dbw_status_throttle_pedal_is_in_range(m.throttle_pedal) ||
        !ddyn_can_dbw_status_brake_pedal_is_in_range(m.brake_pedal) || !ddyn_can_dbw_status_mode_is_in_range(m.mode) ||
        !ddyn_can_dbw_status_faults_is_in_range(m.faults)) {
        return DDYN_DBW_DECODE_RANGE;
    }
    s->feedback.throttle_pedal = ddyn_can_dbw_status_throttle_pedal_decode(m.throttle_pedal);
    s->feedback.brake_pedal = ddyn_can_dbw_status_brake_pedal_decode(m.brake_pedal);
    s->feedback.mode = (ddyn_dbw_mode)m.mode;
    s->feedback.enabled = m.enabled != 0u;
    s->feedback.driver_override = m.driver_override != 0u;
    s->feedback.faults = m.faults;
    *counter = m.counter;
    return DDYN_DBW_DECODE_OK;
}

static ddyn_dbw_decode_result decode_wheel_speeds(const uint8_t *data, ddyn_dbw_signals *s, uint8_t *counter)
{
    struct ddyn_can_dbw_wheel_speeds_t m;
    (void)ddyn_can_dbw_wheel_speeds_unpack(&m, data, DDYN_DBW_FRAME_LEN);
    if (!ddyn_can_dbw_wheel_speeds_wheel_speed_front_is_in_range(m.wheel_speed_front) ||
        !ddyn_can_dbw_wheel_speeds_wheel_speed_rear_is_in_range(m.wheel_speed_rear)) {
        return DDYN_DBW_DECODE_RANGE;
    }
    s->feedback.wheel_speed_front = ddyn_can_dbw_wheel_speeds_wheel_speed_front_decode(m.wheel_speed_front);
    s->feedback.wheel_speed_rear = ddyn_can_dbw_wheel_speeds_wheel_speed_rear_decode(m.wheel_speed_rear);
    *counter = m.counter;
    return DDYN_DBW_DECODE_OK;
}

static ddyn_dbw_decode_result decode_imu(const uint8_t *data, ddyn_dbw_signals *s, uint8_t *counter)
{
    struct ddyn_can_imu_t m;
    (void)ddyn_can_imu_unpack(&m, data, DDYN_DBW_FRAME_LEN);
    if (!ddyn_can_imu_yaw_rate_is_in_range(m.yaw_rate) || !ddyn_can_imu_accel_x_is_in_range(m.accel_x) ||
        !ddyn_can_imu_accel_y_is_in_range(m.accel_y)) {
        return DDYN_DBW_DECODE_RANGE;
    }
    s->sensors.yaw_rate = ddyn_can_imu_yaw_rate_decode(m.yaw_rate);
    s->sensors.accel_x = ddyn_can_imu_accel_x_decode(m.accel_x);
    s->sensors.accel_y = ddyn_can_imu_accel_y_decode(m.accel_y);
    *counter = m.counter;
    return DDYN_DBW_DECODE_OK;
}

static ddyn_dbw_decode_result decode_gnss_position(const uint8_t *data, ddyn_dbw_signals *s, uint8_t *counter)
{
    struct ddyn_can_gnss_position_t m;
    (void)ddyn_can_gnss_position_unpack(&m, data, DDYN_DBW_FRAME_LEN);
    if (!ddyn_can_gnss_position_position_x_is_in_range(m.position_x) ||
        !ddyn_can_gnss_position_position_y_is_in_range(m.position_y)) {
        return DDYN_DBW_DECODE_RANGE;
    }
    s->sensors.gnss_x = ddyn_can_gnss_position_position_x_decode(m.position_x);
    s->sensors.gnss_y = ddyn_can_gnss_position_position_y_decode(m.position_y);
    *counter = m.counter;
    return DDYN_DBW_DECODE_OK;
}

static ddyn_dbw_decode_result decode_gnss_heading(const uint8_t *data, ddyn_dbw_signals *s, uint8_t *counter)
{
    struct ddyn_can_gnss_heading_t m;
    (void)ddyn_can_gnss_heading_unpack(&m, data, DDYN_DBW_FRAME_LEN);
    if (!ddyn_can_gnss_heading_heading_is_in_range(m.heading) || !ddyn_can_gnss_heading_fix_type_is_in_range(m.fix_type)) {
        return DDYN_DBW_DECODE_RANGE;
    }
    s->sensors.heading = ddyn_can_gnss_heading_heading_decode(m.heading);
    s->sensors.fix_type = m.fix_type;
    *counter = m.counter;
    return DDYN_DBW_DECODE_OK;
}

ddyn_dbw_decode_result ddyn_dbw_decode(uint32_t can_id, const uint8_t *data, size_t len,
                                       ddyn_dbw_signals *s, ddyn_dbw_frame *frame, uint8_t *counter)
{
    int f;
    if (data == NULL || s == NULL || frame == NULL || counter == NULL) {
        return DDYN_DBW_DECODE_ARGUMENT;
    }
    /* extended identifiers (above 11 bits) are never ours */
    if (can_id > 0x7FFu || (can_id & DDYN_DBW_ID_BLOCK_MASK) != DDYN_DBW_ID_BLOCK_BASE) {
        return DDYN_DBW_DECODE_FOREIGN_ID;
    }
    f = ddyn_dbw_frame_of_id(can_id);
    if (f < 0) {
        if (ddyn_dbw_is_authenticator_id(can_id)) {
            /* a SecOC_* authenticator: checked for length and checksum here, verified by dbw_auth.c */
            *frame = DDYN_DBW_FRAME_COUNT;
            if (len != DDYN_DBW_FRAME_LEN) {
                return DDYN_DBW_DECODE_BAD_LENGTH;
            }
            return data[CHECKSUM_BYTE] != ddyn_dbw_checksum(can_id, data) ? DDYN_DBW_DECODE_CHECKSUM
                                                                          : DDYN_DBW_DECODE_AUTHENTICATOR;
        }
        return DDYN_DBW_DECODE_UNKNOWN_ID;
    }
    *frame = (ddyn_dbw_frame)f;
    if (len != DDYN_DBW_FRAME_LEN) {
        return DDYN_DBW_DECODE_BAD_LENGTH;
    }
    if (data[CHECKSUM_BYTE] != ddyn_dbw_checksum(can_id, data)) {
        return DDYN_DBW_DECODE_CHECKSUM;
    }
    switch ((ddyn_dbw_frame)f) {
    case DDYN_DBW_FRAME_COMMAND: return decode_command(data, s, counter);
    case DDYN_DBW_FRAME_STEERING: return decode_steering(data, s, counter);
    case DDYN_DBW_FRAME_STATUS: return decode_status(data, s, counter);
    case DDYN_DBW_FRAME_WHEEL_SPEEDS: return decode_wheel_speeds(data, s, counter);
    case DDYN_DBW_FRAME_IMU: return decode_imu(data, s, counter);
    case DDYN_DBW_FRAME_GNSS_POSITION: return decode_gnss_position(data, s, counter);
    case DDYN_DBW_FRAME_GNSS_HEADING: return decode_gnss_heading(data, s, counter);
    default: return DDYN_DBW_DECODE_UNKNOWN_ID;
    }
}

/* ---- the monitor ---- */

void ddyn_dbw_default_config(ddyn_dbw_config *config, uint32_t monitored_mask)
{
    unsigned f;
    if (config == NULL) {
        return;
    }
    for (f = 0; f < DDYN_DBW_FRAME_COUNT; ++f) {
        /* three cycle times: one late frame is jitter, three missing ones are a failure */
        config->deadline_us[f] = (monitored_mask & (1u << f)) ? 3u * ddyn_dbw_cycle_us((ddyn_dbw_frame)f) : 0u;
    }
    config->recovery_good_frames = 5u;
    config->safe_brake = 0.3;
}

static void reset_streaks(ddyn_dbw *dbw)
{
    unsigned f;
    for (f = 0; f < DDYN_DBW_FRAME_COUNT; ++f) {
        dbw->rx[f].good_streak = 0u;
    }
}

ddyn_status ddyn_dbw_init(ddyn_dbw *dbw, const ddyn_dbw_config *config)
{
    unsigned f, monitored = 0u;
    if (dbw == NULL || config == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    for (f = 0; f < DDYN_DBW_FRAME_COUNT; ++f) {
        monitored += config->deadline_us[f] != 0u ? 1u : 0u;
    }
    if (monitored == 0u || config->recovery_good_frames == 0u || !(config->safe_brake >= 0.0) ||
        !(config->safe_brake <= 1.0)) {
        return DDYN_ERR_CONFIG;
    }
    memset(dbw, 0, sizeof(*dbw));
    dbw->config = *config;
    dbw->state = DDYN_DBW_WAIT_GOOD;
    dbw->last_failure = DDYN_DBW_FAIL_COUNT;
    dbw->last_failure_frame = -1;
    return DDYN_OK;
}

/* count a failure (statistics, mask, last failure) without touching the link state */
static void count_failure(ddyn_dbw *dbw, ddyn_dbw_failure kind, int frame, uint64_t t_us)
{
    if (dbw->failures[kind] < UINT32_MAX) {
        dbw->failures[kind]++;
    }
    dbw->failure_mask |= 1u << kind;
    dbw->last_failure = kind;
    dbw->last_failure_frame = frame;
    dbw->last_failure_us = t_us;
    dbw->any_failure = true;
}

static void fail(ddyn_dbw *dbw, ddyn_dbw_failure kind, int frame, uint64_t t_us)
{
    if ((unsigned)kind >= DDYN_DBW_FAIL_COUNT) {
        return;
    }
    count_failure(dbw, kind, frame, t_us);
    dbw->state = DDYN_DBW_WAIT_GOOD;
    reset_streaks(dbw);
}

/* A defect of a received frame: fatal to the link only when this endpoint monitors that frame.
 * A frame it does not monitor (deadline 0, e.g. the controller's own command seen on the bus) is
 * counted for the diagnostics, but the link the car relies on is unaffected. */
static void fail_received(ddyn_dbw *dbw, ddyn_dbw_failure kind, ddyn_dbw_frame frame, uint64_t t_us)
{
    if ((unsigned)frame < (unsigned)DDYN_DBW_FRAME_COUNT && dbw->config.deadline_us[frame] == 0u &&
        (unsigned)kind < DDYN_DBW_FAIL_COUNT) {
        count_failure(dbw, kind, (int)frame, t_us);
        return;
    }
    fail(dbw, kind, (int)frame, t_us);
}

void ddyn_dbw_report(ddyn_dbw *dbw, ddyn_dbw_failure kind, uint64_t t_us)
{
    unsigned f;
    if (dbw == NULL) {
        return;
    }
    if (kind == DDYN_DBW_FAIL_BUS_OFF || kind == DDYN_DBW_FAIL_IFACE_GONE) {
        /* frames were lost for certain: the first counter after the outage starts a new sequence
         * (the outage is counted once here, not again as a jump of every frame) */
        for (f = 0; f < DDYN_DBW_FRAME_COUNT; ++f) {
            dbw->rx[f].counter_valid = false;
        }
    }
    fail(dbw, kind, -1, t_us);
}

/* a good frame (decoded, authenticated when authentication is on): counter check, then the values */
static ddyn_dbw_decode_result apply_good_frame(ddyn_dbw *dbw, ddyn_dbw_frame frame, uint8_t counter,
                                               const ddyn_dbw_signals *decoded, uint64_t t_us)
{
    ddyn_dbw_rx_track *rx = &dbw->rx[frame];
    if (rx->counter_valid) {
        uint8_t expected = (uint8_t)((rx->last_counter + 1u) % DDYN_DBW_COUNTER_MODULO);
        if (counter != expected) {
            ddyn_dbw_failure kind = counter == rx->last_counter ? DDYN_DBW_FAIL_COUNTER_REPEAT
                                                                : DDYN_DBW_FAIL_COUNTER_JUMP;
            /* follow the sender's counter so that the next in-sequence frame counts as good */
            rx->last_counter = counter;
            fail_received(dbw, kind, frame, t_us);
            return DDYN_DBW_DECODE_OK;
        }
    }
    rx->last_counter = counter;
    rx->counter_valid = true;
    rx->last_rx_us = t_us;
    rx->seen = true;
    rx->stale = false;
    if (rx->good_streak < UINT32_MAX) {
        rx->good_streak++;
    }
    if (rx->received < UINT32_MAX) {
        rx->received++;
    }
    dbw->latest = *decoded;
    dbw->fresh_mask |= 1u << frame;
    return DDYN_DBW_DECODE_OK;
}

/* an authenticator frame: verify it against the held frame, and apply that frame when it passes */
static ddyn_dbw_decode_result on_authenticator(ddyn_dbw *dbw, uint32_t can_id, const uint8_t *data, size_t len,
                                               uint64_t t_us)
{
    ddyn_dbw_frame frame = DDYN_DBW_FRAME_COUNT, f2 = DDYN_DBW_FRAME_COUNT;
    uint8_t held[DDYN_DBW_FRAME_LEN], counter = 0u;
    uint64_t held_us = 0u;
    ddyn_dbw_signals decoded;
    ddyn_dbw_failure kind = ddyn_dbw_auth_verify(&dbw->auth, can_id, data, len, t_us, &frame, held, &held_us);
    if (kind != DDYN_DBW_FAIL_COUNT) {
        /* forged, replayed or stale: counted, the frame dropped, the link untouched */
        count_failure(dbw, kind, (unsigned)frame < DDYN_DBW_FRAME_COUNT ? (int)frame : -1, t_us);
        return DDYN_DBW_DECODE_AUTH_REJECTED;
    }
    /* frames of that identifier held from before the authenticated one never got an authenticator:
     * stale, dropped, and their counter values not trusted (no counter jump of the accepted frame) */
    {
        unsigned k;
        for (k = 0; k < DDYN_DBW_AUTH_HOLD; ++k) {
            if (dbw->auth.pending_valid[frame][k] && dbw->auth.pending_us[frame][k] <= held_us) {
                dbw->auth.pending_valid[frame][k] = false;
                dbw->rx[frame].counter_valid = false;
                count_failure(dbw, DDYN_DBW_FAIL_AUTH_STALE, (int)frame, t_us);
            }
        }
    }
    decoded = dbw->latest;
    if (ddyn_dbw_decode(ddyn_dbw_frame_id(frame), held, DDYN_DBW_FRAME_LEN, &decoded, &f2, &counter) !=
            DDYN_DBW_DECODE_OK ||
        f2 != frame) {
        return DDYN_DBW_DECODE_AUTH_REJECTED; /* cannot happen: only good frames are held */
    }
    return apply_good_frame(dbw, frame, counter, &decoded, held_us);
}

ddyn_dbw_decode_result ddyn_dbw_on_frame(ddyn_dbw *dbw, uint32_t can_id, const uint8_t *data, size_t len,
                                         uint64_t t_us)
{
    ddyn_dbw_signals decoded;
    ddyn_dbw_frame frame = DDYN_DBW_FRAME_COUNT;
    uint8_t counter = 0u;
    ddyn_dbw_decode_result r;
    if (dbw == NULL) {
        return DDYN_DBW_DECODE_ARGUMENT;
    }
    /* decode into a copy: a bad frame must not touch the last good values */
    decoded = dbw->latest;
    r = ddyn_dbw_decode(can_id, data, len, &decoded, &frame, &counter);
    switch (r) {
    case DDYN_DBW_DECODE_OK: break;
    case DDYN_DBW_DECODE_FOREIGN_ID: return r;
    case DDYN_DBW_DECODE_UNKNOWN_ID:
        /* an identifier the DBC lacks is one no endpoint can monitor: counted and named, never fatal,
         * so that one stray node on the bus cannot stop the car (the frames it relies on have their
         * own deadlines, which catch a stray node that drowns them) */
        count_failure(dbw, DDYN_DBW_FAIL_UNKNOWN_FRAME, -1, t_us);
        return r;
    case DDYN_DBW_DECODE_AUTHENTICATOR:
        return dbw->auth.enabled ? on_authenticator(dbw, can_id, data, len, t_us) : r;
    case DDYN_DBW_DECODE_BAD_LENGTH:
    case DDYN_DBW_DECODE_CHECKSUM:
    case DDYN_DBW_DECODE_RANGE:
        if ((unsigned)frame >= DDYN_DBW_FRAME_COUNT) {
            /* a broken authenticator frame: it vouches for nothing; counted, not fatal */
            if (dbw->auth.enabled) {
                count_failure(dbw, DDYN_DBW_FAIL_AUTH_FORGED, -1, t_us);
            }
            return r;
        }
        /* the rejected frame used up a counter value the receiver cannot trust: accept any counter
         * next, so that one defect is counted once (recovery needs N good frames anyway) */
        dbw->rx[frame].counter_valid = false;
        if (dbw->auth.enabled) {
            /* with authentication on, only authenticated frames move the link: a broken frame cannot
             * be told from one forged to stop the car, so it is counted, not fatal; a sender whose
             * frames keep failing is caught by the deadline of its frame */
            count_failure(dbw,
                          r == DDYN_DBW_DECODE_BAD_LENGTH ? DDYN_DBW_FAIL_BAD_LENGTH
                          : r == DDYN_DBW_DECODE_CHECKSUM ? DDYN_DBW_FAIL_CHECKSUM
                                                          : DDYN_DBW_FAIL_RANGE,
                          (int)frame, t_us);
            return r;
        }
        fail_received(dbw,
                      r == DDYN_DBW_DECODE_BAD_LENGTH ? DDYN_DBW_FAIL_BAD_LENGTH
                      : r == DDYN_DBW_DECODE_CHECKSUM ? DDYN_DBW_FAIL_CHECKSUM
                                                      : DDYN_DBW_FAIL_RANGE,
                      frame, t_us);
        return r;
    default: return r;
    }
    if (dbw->auth.enabled && dbw->config.deadline_us[frame] != 0u) {
        /* a frame this endpoint relies on counts only once its authenticator has vouched for it */
        if (ddyn_dbw_auth_hold(&dbw->auth, frame, data, t_us)) {
            /* the one it replaced never was: stale, and its counter value not trusted */
            dbw->rx[frame].counter_valid = false;
            count_failure(dbw, DDYN_DBW_FAIL_AUTH_STALE, (int)frame, t_us);
        }
        return DDYN_DBW_DECODE_AUTH_PENDING;
    }
    return apply_good_frame(dbw, frame, counter, &decoded, t_us);
}

static bool frame_is_late(const ddyn_dbw_rx_track *rx, uint32_t deadline_us, uint64_t now_us)
{
    /* a receive time in the future (clock step) counts as age 0, not as a huge age */
    return now_us > rx->last_rx_us && now_us - rx->last_rx_us > (uint64_t)deadline_us;
}

ddyn_dbw_state ddyn_dbw_check(ddyn_dbw *dbw, uint64_t now_us)
{
    unsigned f;
    bool all_good = true;
    if (dbw == NULL) {
        return DDYN_DBW_WAIT_GOOD;
    }
    if (dbw->auth.enabled) {
        /* held frames whose authenticator never came: stale, counted, dropped; the counter value they
         * used is not trusted, so the next authenticated frame starts a new sequence (one defect is
         * counted once, not again as a counter jump that would trip the link) */
        uint32_t lost = 0u, n = ddyn_dbw_auth_expire(&dbw->auth, now_us, &lost);
        for (f = 0; f < DDYN_DBW_FRAME_COUNT; ++f) {
            if (lost & (1u << f)) {
                dbw->rx[f].counter_valid = false;
            }
        }
        for (; n > 0u; --n) {
            count_failure(dbw, DDYN_DBW_FAIL_AUTH_STALE, -1, now_us);
        }
    }
    for (f = 0; f < DDYN_DBW_FRAME_COUNT; ++f) {
        ddyn_dbw_rx_track *rx = &dbw->rx[f];
        uint32_t deadline = dbw->config.deadline_us[f];
        if (deadline == 0u) {
            continue;
        }
        if (!rx->seen) {
            all_good = false; /* never received since init: waiting, not (yet) a lapse */
            continue;
        }
        if (frame_is_late(rx, deadline, now_us)) {
            all_good = false;
            if (!rx->stale) {
                rx->stale = true;
                rx->counter_valid = false; /* after a gap any counter may follow */
                fail(dbw, DDYN_DBW_FAIL_STALE, (int)f, now_us);
            }
            continue;
        }
        if (rx->good_streak < dbw->config.recovery_good_frames) {
            all_good = false;
        }
    }
    if (dbw->state == DDYN_DBW_WAIT_GOOD && all_good) {
        dbw->state = DDYN_DBW_READY;
    }
    return dbw->state;
}

ddyn_status ddyn_dbw_enable(ddyn_dbw *dbw)
{
    if (dbw == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    if (dbw->state != DDYN_DBW_READY) {
        return DDYN_ERR_NOT_READY;
    }
    dbw->state = DDYN_DBW_ACTIVE;
    return DDYN_OK;
}

void ddyn_dbw_disable(ddyn_dbw *dbw)
{
    if (dbw != NULL) {
        dbw->state = DDYN_DBW_WAIT_GOOD;
        reset_streaks(dbw);
    }
}

void ddyn_dbw_safe_command(const ddyn_dbw *dbw, ddyn_dbw_command *out)
{
    if (out == NULL) {
        return;
    }
    out->throttle = 0.0;
    out->brake = dbw != NULL ? dbw->config.safe_brake : 0.3;
    out->steering = dbw != NULL ? dbw->held_steering : 0.0;
    /* the unit must keep actuating to brake and hold the wheel: enabled, in SAFE_STOP */
    out->enable = true;
    out->mode = DDYN_DBW_MODE_SAFE_STOP;
}

static bool command_in_range(const ddyn_dbw_command *c)
{
    return ddyn_can_dbw_command_throttle_is_in_phys_range(c->throttle) &&
           ddyn_can_dbw_command_brake_is_in_phys_range(c->brake) &&
           ddyn_can_dbw_command_steering_angle_is_in_phys_range(c->steering);
}

ddyn_dbw_state ddyn_dbw_command_frame(ddyn_dbw *dbw, uint64_t now_us, const ddyn_dbw_command *desired,
                                      ddyn_dbw_command *sent, uint8_t data[DDYN_DBW_FRAME_LEN])
{
    ddyn_dbw_signals s;
    if (dbw == NULL || sent == NULL || data == NULL) {
        return DDYN_DBW_WAIT_GOOD;
    }
    (void)ddyn_dbw_check(dbw, now_us);
    if (dbw->state == DDYN_DBW_ACTIVE && (desired == NULL || !command_in_range(desired))) {
        fail(dbw, DDYN_DBW_FAIL_COMMAND_RANGE, DDYN_DBW_FRAME_COMMAND, now_us);
    }
    if (dbw->state == DDYN_DBW_ACTIVE) {
        *sent = *desired;
        sent->enable = true;
        sent->mode = DDYN_DBW_MODE_AUTONOMOUS;
        dbw->held_steering = desired->steering;
    } else {
        ddyn_dbw_safe_command(dbw, sent);
    }
    memset(&s, 0, sizeof(s));
    s.command = *sent;
    /* the safe command is in range by construction (held steering was in range when sent) */
    (void)ddyn_dbw_next_frame(dbw, DDYN_DBW_FRAME_COMMAND, &s, data);
    return dbw->state;
}

ddyn_status ddyn_dbw_next_frame(ddyn_dbw *dbw, ddyn_dbw_frame frame, const ddyn_dbw_signals *s,
                                uint8_t data[DDYN_DBW_FRAME_LEN])
{
    ddyn_status rc;
    if (dbw == NULL || (unsigned)frame >= DDYN_DBW_FRAME_COUNT) {
        return DDYN_ERR_ARGUMENT;
    }
    rc = ddyn_dbw_encode(frame, s, dbw->tx_counter[frame], data);
    if (rc == DDYN_OK) {
        /* a frame that could not be encoded is not sent, so it does not consume a counter value */
        dbw->tx_counter[frame] = (uint8_t)((dbw->tx_counter[frame] + 1u) % DDYN_DBW_COUNTER_MODULO);
    }
    return rc;
}

uint32_t ddyn_dbw_take_fresh(ddyn_dbw *dbw)
{
    uint32_t m = 0u;
    if (dbw != NULL) {
        m = dbw->fresh_mask;
        dbw->fresh_mask = 0u;
    }
    return m;
}

uint32_t ddyn_dbw_take_failures(ddyn_dbw *dbw)
{
    uint32_t m = 0u;
    if (dbw != NULL) {
        m = dbw->failure_mask;
        dbw->failure_mask = 0u;
    }
    return m;
}

uint8_t ddyn_dbw_fault_bits(uint32_t failure_mask)
{
    uint8_t bits = 0u;
    if (failure_mask & (1u << DDYN_DBW_FAIL_STALE)) {
        bits |= DDYN_DBW_FAULT_CMD_TIMEOUT;
    }
    if (failure_mask & ((1u << DDYN_DBW_FAIL_COUNTER_JUMP) | (1u << DDYN_DBW_FAIL_COUNTER_REPEAT))) {
        bits |= DDYN_DBW_FAULT_CMD_COUNTER;
    }
    if (failure_mask & ((1u << DDYN_DBW_FAIL_CHECKSUM) | (1u << DDYN_DBW_FAIL_BAD_LENGTH) |
                        (1u << DDYN_DBW_FAIL_UNKNOWN_FRAME) | (1u << DDYN_DBW_FAIL_AUTH_FORGED) |
                        (1u << DDYN_DBW_FAIL_AUTH_REPLAY) | (1u << DDYN_DBW_FAIL_AUTH_STALE))) {
        bits |= DDYN_DBW_FAULT_CMD_CHECKSUM;
    }
    if (failure_mask & (1u << DDYN_DBW_FAIL_RANGE)) {
        bits |= DDYN_DBW_FAULT_CMD_RANGE;
    }
    return bits;
}

const char *ddyn_dbw_failure_name(ddyn_dbw_failure kind)
{
    static const char *const names[DDYN_DBW_FAIL_COUNT] = {
        "stale", "counter_jump", "counter_repeat", "checksum", "range", "unknown_frame",
        "bad_length", "bus_off", "bus_error", "iface_gone", "command_range",
        "auth_forged", "auth_replay", "auth_stale",
    };
    return ((unsigned)kind < DDYN_DBW_FAIL_COUNT) ? names[kind] : "none";
}

const char *ddyn_dbw_frame_name(ddyn_dbw_frame frame)
{
    static const char *const names[DDYN_DBW_FRAME_COUNT] = {
        DDYN_CAN_DBW_COMMAND_NAME, DDYN_CAN_DBW_STEERING_NAME,      DDYN_CAN_DBW_STATUS_NAME,
        DDYN_CAN_DBW_WHEEL_SPEEDS_NAME, DDYN_CAN_IMU_NAME,         DDYN_CAN_GNSS_POSITION_NAME,
        DDYN_CAN_GNSS_HEADING_NAME,
    };
    return ((unsigned)frame < DDYN_DBW_FRAME_COUNT) ? names[frame] : "unknown";
}

const char *ddyn_dbw_state_name(ddyn_dbw_state state)
{
    switch (state) {
    case DDYN_DBW_WAIT_GOOD: return "wait_good";
    case DDYN_DBW_READY: return "ready";
    case DDYN_DBW_ACTIVE: return "active";
    default: return "unknown";
    }
}

/* ---- frame ages on a degraded bus (ddyn/dbw.h) ---- */

/* a + b, stopping at UINT32_MAX instead of wrapping */
static uint32_t sat_add_u32(uint32_t a, uint32_t b)
{
    return a > UINT32_MAX - b ? UINT32_MAX : a + b;
}

void ddyn_dbw_link_init(ddyn_dbw_link *link)
{
    int f;
    if (link != NULL) {
        memset(link, 0, sizeof *link);
        for (f = 0; f < DDYN_DBW_FRAME_COUNT; ++f) {
            link->cycle_s[f] = (double)ddyn_dbw_cycle_us((ddyn_dbw_frame)f) * 1e-6;
        }
    }
}

/* the DBC's attribute range of GenMsgCycleTime: INT 0 10000 (ms) */
#define LINK_CYCLE_MAX_US 10000000u

ddyn_status ddyn_dbw_link_set_cycle(ddyn_dbw_link *link, ddyn_dbw_frame frame, uint32_t cycle_us)
{
    if (link == NULL || (unsigned)frame >= DDYN_DBW_FRAME_COUNT || cycle_us > LINK_CYCLE_MAX_US) {
        return DDYN_ERR_ARGUMENT;
    }
    link->cycle_s[frame] = (double)(cycle_us != 0u ? cycle_us : ddyn_dbw_cycle_us(frame)) * 1e-6;
    return DDYN_OK;
}

double ddyn_dbw_link_cycle(const ddyn_dbw_link *link, ddyn_dbw_frame frame)
{
    return (link == NULL || (unsigned)frame >= DDYN_DBW_FRAME_COUNT) ? -1.0 : link->cycle_s[frame];
}

ddyn_dbw_link_result ddyn_dbw_link_on_frame(ddyn_dbw_link *link, ddyn_dbw_frame frame, uint8_t counter,
                                            unsigned *lost, double *age_s)
{
    unsigned step = 1u;
    double tau, age, cycle;
    int f = (int)frame;
    if (lost != NULL) {
        *lost = 0u;
    }
    if (age_s != NULL) {
        *age_s = 0.0;
    }
    if (link == NULL || (unsigned)frame >= DDYN_DBW_FRAME_COUNT) {
        return DDYN_DBW_LINK_REPEATED;
    }
    cycle = link->cycle_s[f];
    counter = (uint8_t)(counter % DDYN_DBW_COUNTER_MODULO);
    if (link->seen[f]) {
        step = (counter + DDYN_DBW_COUNTER_MODULO - link->last_counter[f]) % DDYN_DBW_COUNTER_MODULO;
        if (step == 0u) {
            link->repeated = sat_add_u32(link->repeated, 1u);
            return DDYN_DBW_LINK_REPEATED;
        }
        if (step > DDYN_DBW_COUNTER_MODULO / 2u) {
            link->late = sat_add_u32(link->late, 1u);
            return DDYN_DBW_LINK_LATE;
        }
        link->lost = sat_add_u32(link->lost, step - 1u);
        if (lost != NULL) {
            *lost = step - 1u;
        }
        /* the sequence number saturates too (at 100 Hz, after 10^10 years) */
        link->seq[f] = link->seq[f] > INT64_MAX - (int64_t)step ? INT64_MAX : link->seq[f] + (int64_t)step;
    } else {
        /* the first frame of a stream: fresh by assumption (corrected by the window minimum) */
        link->seq[f] = 0;
        link->phase_s[f] = link->any_seen ? link->now_s : 0.0;
        link->window_min_s[f] = 0.0;
        link->window_n[f] = 0;
        link->ticked[f] = false;
        link->seen[f] = true;
    }
    link->any_seen = true;
    link->last_counter[f] = counter;
    tau = link->phase_s[f] + (double)link->seq[f] * cycle;
    if (tau > link->now_s) {
        link->now_s = tau;
    }
    age = link->now_s - tau;
    if (age_s != NULL) {
        *age_s = age;
    }
    return DDYN_DBW_LINK_NEW;
}

void ddyn_dbw_link_tick(ddyn_dbw_link *link)
{
    int f;
    if (link == NULL) {
        return;
    }
    for (f = 0; f < DDYN_DBW_FRAME_COUNT; ++f) {
        double age;
        if (!link->seen[f]) {
            continue;
        }
        age = ddyn_dbw_link_age(link, (ddyn_dbw_frame)f);
        if (link->window_n[f] == 0 || age < link->window_min_s[f]) {
            link->window_min_s[f] = age;
        }
        link->window_n[f] += 1;
        /* the first window is one tick long: a stream's first frame may have come just before fresher
         * frames of the same instant */
        if (link->window_n[f] >= (link->ticked[f] ? DDYN_DBW_LINK_WINDOW : 1)) {
            link->ticked[f] = true;
            /* the window's least delayed frame is fresh by definition: move the phase by that much */
            link->phase_s[f] += link->window_min_s[f];
            link->window_n[f] = 0;
        }
    }
}

void ddyn_dbw_link_on_bad_frame(ddyn_dbw_link *link)
{
    if (link != NULL) {
        link->bad = sat_add_u32(link->bad, 1u);
    }
}

double ddyn_dbw_link_age(const ddyn_dbw_link *link, ddyn_dbw_frame frame)
{
    int f = (int)frame;
    if (link == NULL || (unsigned)frame >= DDYN_DBW_FRAME_COUNT || !link->seen[f]) {
        return -1.0;
    }
    return link->now_s - (link->phase_s[f] + (double)link->seq[f] * link->cycle_s[f]);
}

uint32_t ddyn_dbw_link_take_faults(ddyn_dbw_link *link)
{
    uint32_t n;
    if (link == NULL) {
        return 0u;
    }
    n = sat_add_u32(sat_add_u32(link->lost, link->late), sat_add_u32(link->repeated, link->bad));
    link->lost = link->late = link->repeated = link->bad = 0u;
    return n;
}
