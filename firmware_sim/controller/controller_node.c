#include "controller_node.h"

#include <math.h>
#include <string.h>

static double clampd(double v, double lo, double hi)
{
    return v < lo ? lo : (v > hi ? hi : v);
}

ddyn_status ddyn_sil_node_init(ddyn_sil_node *node, const ddyn_vehicle_model *model, const ddyn_net_tables *tables,
                               const ddyn_ctrl_config *cfg, const double x0[DDYN_NX], double period,
                               const int stale[DDYN_DBW_FRAME_COUNT])
{
    ddyn_status st;
    int k;
    if (node == NULL || cfg == NULL || stale == NULL || !(period > 0.0)) {
        return DDYN_ERR_ARGUMENT;
    }
    memset(node, 0, sizeof *node);
    st = ddyn_ctrl_init(&node->ctl, model, tables, cfg, x0);
    if (st != DDYN_OK) {
        return st;
    }
    node->period = period;
    node->state_lo[0] = cfg->mpc.state_lo[0];
    node->state_lo[1] = cfg->mpc.state_lo[1];
    node->state_hi[0] = cfg->mpc.state_hi[0];
    node->state_hi[1] = cfg->mpc.state_hi[1];
    node->setpoint[0] = x0[6];
    node->setpoint[1] = x0[7];
    for (k = 0; k < DDYN_DBW_FRAME_COUNT; ++k) {
        node->stale[k] = stale[k];
        node->last_counter[k] = -1;
    }
    ddyn_dbw_link_init(&node->link);
    return DDYN_OK;
}

/* which sensor readings a frame carries */
static void take_reading(ddyn_dbw_frame f, const ddyn_dbw_signals *s, ddyn_ctrl_input *in)
{
    switch (f) {
    case DDYN_DBW_FRAME_STEERING:
        in->reading[DDYN_MEAS_STEERING].valid = 1;
        in->reading[DDYN_MEAS_STEERING].z[0] = s->feedback.steering;
        break;
    case DDYN_DBW_FRAME_WHEEL_SPEEDS:
        in->reading[DDYN_MEAS_WHEEL_SPEED].valid = 1;
        in->reading[DDYN_MEAS_WHEEL_SPEED].z[0] = s->feedback.wheel_speed_front;
        in->reading[DDYN_MEAS_WHEEL_SPEED].z[1] = s->feedback.wheel_speed_rear;
        break;
    case DDYN_DBW_FRAME_IMU:
        in->reading[DDYN_MEAS_YAW_RATE].valid = 1;
        in->reading[DDYN_MEAS_YAW_RATE].z[0] = s->sensors.yaw_rate;
        in->reading[DDYN_MEAS_ACCELERATION].valid = 1;
        in->reading[DDYN_MEAS_ACCELERATION].z[0] = s->sensors.accel_x;
        in->reading[DDYN_MEAS_ACCELERATION].z[1] = s->sensors.accel_y;
        break;
    case DDYN_DBW_FRAME_GNSS_POSITION:
        in->reading[DDYN_MEAS_GNSS_POSITION].valid = 1;
        in->reading[DDYN_MEAS_GNSS_POSITION].z[0] = s->sensors.gnss_x;
        in->reading[DDYN_MEAS_GNSS_POSITION].z[1] = s->sensors.gnss_y;
        break;
    case DDYN_DBW_FRAME_GNSS_HEADING:
        in->reading[DDYN_MEAS_HEADING].valid = 1;
        in->reading[DDYN_MEAS_HEADING].z[0] = s->sensors.heading;
        break;
    default:
        break;
    }
}

ddyn_status ddyn_sil_node_auth_enable(ddyn_sil_node *node, const uint8_t key[DDYN_DBW_AUTH_KEY_LEN])
{
    if (node == NULL || key == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    ddyn_dbw_auth_init(&node->auth, key, 0u);
    node->auth_on = 1;
    node->auth_freshness = 0u;
    node->auth_counter = 0u;
    return DDYN_OK;
}

/* a frame the policy below takes (with authentication on: one whose authenticator verified) */
static int on_good_frame(ddyn_sil_node *node, uint32_t can_id, const uint8_t *data, size_t len);

int ddyn_sil_node_on_frame(ddyn_sil_node *node, uint32_t can_id, const uint8_t *data, size_t len)
{
    return ddyn_sil_node_on_frame_at(node, can_id, data, len, node->rx_us);
}

int ddyn_sil_node_on_frame_at(ddyn_sil_node *node, uint32_t can_id, const uint8_t *data, size_t len, uint64_t t_us)
{
    int frame;
    node->rx_us = t_us;
    if (!node->auth_on) {
        return on_good_frame(node, can_id, data, len);
    }
    if (ddyn_dbw_is_authenticator_id(can_id)) {
        ddyn_dbw_frame f = DDYN_DBW_FRAME_COUNT;
        uint8_t released[DDYN_DBW_FRAME_LEN];
        uint64_t t_data = 0u;
        ddyn_dbw_failure kind = ddyn_dbw_auth_verify(&node->auth, can_id, data, len, t_us, &f, released, &t_data);
        if (kind == DDYN_DBW_FAIL_COUNT) {
            node->auth_accepted += 1;
            return on_good_frame(node, ddyn_dbw_frame_id(f), released, DDYN_DBW_FRAME_LEN);
        }
        /* another node's pair (a command and its authenticator of another controller) is not ours */
        if ((unsigned)f < DDYN_DBW_FRAME_COUNT && (DDYN_DBW_MONITOR_CONTROLLER & (1u << f)) == 0u) {
            return 0;
        }
        if (kind == DDYN_DBW_FAIL_AUTH_REPLAY) {
            node->auth_replayed += 1;
        } else if (kind == DDYN_DBW_FAIL_AUTH_STALE) {
            node->auth_stale += 1;
        } else {
            node->auth_forged += 1;
        }
        return 0;
    }
    frame = ddyn_dbw_frame_of_id(can_id);
    /* a good frame the controller reads waits for its authenticator; anything else (a damaged frame,
     * a command, a foreign identifier) goes to the checks below, which count and drop it */
    if (frame >= 0 && (DDYN_DBW_MONITOR_CONTROLLER & (1u << frame)) != 0u && len == DDYN_DBW_FRAME_LEN &&
        data != NULL && ddyn_dbw_checksum(can_id, data) == data[DDYN_DBW_FRAME_LEN - 1]) {
        if (ddyn_dbw_auth_hold(&node->auth, (ddyn_dbw_frame)frame, data, t_us)) {
            node->auth_stale += 1; /* it pushed out a held frame that never got its authenticator */
        }
        return 0;
    }
    return on_good_frame(node, can_id, data, len);
}

static int on_good_frame(ddyn_sil_node *node, uint32_t can_id, const uint8_t *data, size_t len)
{
    ddyn_dbw_frame f;
    uint8_t counter;
    unsigned lost = 0u;
    ddyn_dbw_signals decoded = node->sig; /* a frame refused later must not touch the last values */
    ddyn_dbw_decode_result r = ddyn_dbw_decode(can_id, data, len, &decoded, &f, &counter);
    switch (r) {
    case DDYN_DBW_DECODE_OK:
        break;
    case DDYN_DBW_DECODE_CHECKSUM:
        node->checksum += 1;
        ddyn_dbw_link_on_bad_frame(&node->link);
        return 0;
    case DDYN_DBW_DECODE_BAD_LENGTH:
        node->bad_length += 1;
        ddyn_dbw_link_on_bad_frame(&node->link);
        return 0;
    case DDYN_DBW_DECODE_RANGE:
        node->range += 1;
        ddyn_dbw_link_on_bad_frame(&node->link);
        return 0;
    case DDYN_DBW_DECODE_UNKNOWN_ID:
        node->unknown_id += 1;
        return 0;
    default:
        return 0; /* foreign identifiers: not ours */
    }
    if (f == DDYN_DBW_FRAME_COMMAND) {
        return 0; /* our own kind of frame (another controller's): not for us */
    }
    /* forward by 1..8 (mod 16): new, a skip means lost frames; 0: a stuck sender; 9..15: an older
     * frame arriving late. Neither of the last two may overwrite newer data. */
    switch (ddyn_dbw_link_on_frame(&node->link, f, counter, &lost, NULL)) {
    case DDYN_DBW_LINK_REPEATED:
        node->repeated_counter += 1;
        return 0;
    case DDYN_DBW_LINK_LATE:
        node->late += 1;
        return 0;
    default:
        break;
    }
    node->sig = decoded;
    node->frames_lost += (long)lost;
    node->last_counter[f] = counter;
    node->last_rx_step[f] = node->steps;
    node->frames_ok += 1;
    take_reading(f, &node->sig, &node->in);
    if (f != DDYN_DBW_FRAME_GNSS_POSITION) {
        return 0;
    }
    node->catch_up = (int)(lost < (unsigned)DDYN_SIL_MAX_CATCH_UP ? lost : (unsigned)DDYN_SIL_MAX_CATCH_UP);
    return 1;
}

/* the frame each sensor reading comes from */
static const ddyn_dbw_frame READING_FRAME[DDYN_MEAS_COUNT] = {
    [DDYN_MEAS_GNSS_POSITION] = DDYN_DBW_FRAME_GNSS_POSITION, [DDYN_MEAS_HEADING] = DDYN_DBW_FRAME_GNSS_HEADING,
    [DDYN_MEAS_YAW_RATE] = DDYN_DBW_FRAME_IMU,                [DDYN_MEAS_ACCELERATION] = DDYN_DBW_FRAME_IMU,
    [DDYN_MEAS_WHEEL_SPEED] = DDYN_DBW_FRAME_WHEEL_SPEEDS,    [DDYN_MEAS_STEERING] = DDYN_DBW_FRAME_STEERING};

/* the readings' ages and the period's latency on the bus clock now, and the bus faults since the last
 * period, into the controller's input */
static void date_input(ddyn_sil_node *node)
{
    int k;
    ddyn_dbw_link_tick(&node->link);
    for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
        double a = ddyn_dbw_link_age(&node->link, READING_FRAME[k]); /* the frame the reading came in */
        node->in.reading[k].age = a > 0.0 ? a : 0.0;
    }
    node->in.latency = node->in.reading[DDYN_MEAS_GNSS_POSITION].valid ? node->in.reading[DDYN_MEAS_GNSS_POSITION].age
                                                                        : 0.0;
    node->in.bus_faults = ddyn_dbw_link_take_faults(&node->link);
}

void ddyn_sil_node_period(ddyn_sil_node *node, ddyn_sil_period *p)
{
    double u[DDYN_NU];
    ddyn_dbw_signals cmd;
    int k;
    memset(p, 0, sizeof *p);
    if (node->auth_on) {
        /* frames whose authenticator never came (stale): dropped, once per period */
        node->auth_stale += (long)ddyn_dbw_auth_expire(&node->auth, node->rx_us, NULL);
    }
    /* (the degraded mode's extra periods as of the last period) */
    for (k = 0; k < DDYN_DBW_FRAME_COUNT; ++k) {
        if (node->stale[k] > 0 && node->steps - node->last_rx_step[k] > ddyn_ctrl_stale_limit(&node->ctl, node->stale[k])) {
            p->stale = 1;
        }
    }
    date_input(node);
    while (node->catch_up > 0) {
        /* a period whose position frame was lost: run it with the other readings, keep this
         * period's position and heading for the period they belong to; its command is not sent
         * (the actuators held theirs through it) */
        ddyn_ctrl_input held = node->in;
        node->in.reading[DDYN_MEAS_GNSS_POSITION].valid = 0;
        node->in.reading[DDYN_MEAS_HEADING].valid = 0;
        ddyn_ctrl_step(&node->ctl, &node->in, &p->out);
        ddyn_ctrl_command_not_sent(&node->ctl);
        memset(&node->in, 0, sizeof node->in);
        node->in.reading[DDYN_MEAS_GNSS_POSITION] = held.reading[DDYN_MEAS_GNSS_POSITION];
        node->in.reading[DDYN_MEAS_HEADING] = held.reading[DDYN_MEAS_HEADING];
        node->in.latency = held.latency;
        node->catch_up -= 1;
        node->steps += 1;
    }
    p->readings = node->in;
    ddyn_ctrl_step(&node->ctl, &node->in, &p->out);
    memset(&node->in, 0, sizeof node->in);
    p->safe = p->stale || (p->out.status & DDYN_CTRL_SAFE_COMMAND) != 0;
    if (p->stale) {
        ddyn_ctrl_safe_command(&node->ctl, p->out.x_est, u);
    } else {
        u[0] = p->out.u[0];
        u[1] = p->out.u[1];
    }
    /* The rates over the next period become the set-points at its end. They integrate the commanded
     * rates (not estimate + rate): the actuators reach each set-point within the period, so the
     * actual throttle and steering move by exactly u * period, as the filter's model predicts; a
     * set-point built on the estimate would also "correct" the estimate's error behind the filter's
     * back. */
    p->throttle = clampd(node->setpoint[0] + u[0] * node->period, node->state_lo[0], node->state_hi[0]);
    p->steering = clampd(node->setpoint[1] + u[1] * node->period, node->state_lo[1], node->state_hi[1]);
    if (p->stale) {
        /* the actuators get the safe command for a silent frame, not the step's command: the filter
         * must predict with it (otherwise its throttle state drifts from the actuator's and the safe
         * command, which reads that state, drives a stopped car back and forth). Set-points cut by their
         * bounds are left to the steering sensor: telling the filter the cut rates made the delayed-frame
         * laps worse (in-process seed 2: 3 violations, 67 steering readings gated, against 0 and 8). */
        double applied[DDYN_NU];
        applied[0] = (p->throttle - node->setpoint[0]) / node->period;
        applied[1] = (p->steering - node->setpoint[1]) / node->period;
        ddyn_ctrl_command_applied(&node->ctl, applied);
    }
    node->setpoint[0] = p->throttle;
    node->setpoint[1] = p->steering;
    memset(&cmd, 0, sizeof cmd);
    cmd.command.throttle = p->throttle > 0.0 ? p->throttle : 0.0;
    cmd.command.brake = p->throttle < 0.0 ? -p->throttle : 0.0;
    cmd.command.steering = p->steering;
    cmd.command.enable = true;
    cmd.command.mode = DDYN_DBW_MODE_AUTONOMOUS;
    p->can_id = ddyn_dbw_frame_id(DDYN_DBW_FRAME_COMMAND);
    (void)ddyn_dbw_encode(DDYN_DBW_FRAME_COMMAND, &cmd, node->tx_counter, p->data); /* in range by the clamps */
    node->tx_counter = (uint8_t)((node->tx_counter + 1u) % DDYN_DBW_COUNTER_MODULO);
    if (node->auth_on) {
        /* the authenticator over the command as encoded: one freshness value per command sent */
        p->has_auth = 1;
        p->auth_can_id = ddyn_dbw_auth_id(DDYN_DBW_FRAME_COMMAND);
        (void)ddyn_dbw_auth_sign(&node->auth, DDYN_DBW_FRAME_COMMAND, p->data, node->auth_freshness,
                                 node->auth_counter, p->auth_data); /* the prepared key state: one compression */
        node->auth_freshness += 1u;
        node->auth_counter = (uint8_t)((node->auth_counter + 1u) % DDYN_DBW_COUNTER_MODULO);
    }
    node->safe_steps += p->safe ? 1 : 0;
    node->steps += 1;
}

void ddyn_sil_log_readings(const ddyn_sil_period *p, double out[DDYN_SIL_LOG_READINGS])
{
    const ddyn_ctrl_reading *yaw = &p->readings.reading[DDYN_MEAS_YAW_RATE];
    const ddyn_ctrl_reading *steer = &p->readings.reading[DDYN_MEAS_STEERING];
    const ddyn_ctrl_reading *acc = &p->readings.reading[DDYN_MEAS_ACCELERATION];
    const ddyn_ctrl_reading *pos = &p->readings.reading[DDYN_MEAS_GNSS_POSITION];
    const ddyn_ctrl_reading *head = &p->readings.reading[DDYN_MEAS_HEADING];
    out[0] = yaw->valid ? yaw->z[0] : NAN;
    out[1] = steer->valid ? steer->z[0] : NAN;
    out[2] = acc->valid ? acc->z[0] : NAN;
    out[3] = acc->valid ? acc->z[1] : NAN;
    out[4] = pos->valid ? pos->z[0] : NAN;
    out[5] = pos->valid ? pos->z[1] : NAN;
    out[6] = head->valid ? head->z[0] : NAN;
}
