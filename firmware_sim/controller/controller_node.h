/*
 * controller_node.h - the controller's CAN node, without the operating system: frames in, one
 * control period, the command frame out. The process (controller_main.c) adds the socket, the
 * clock and the files; the in-process SIL tests drive the same node through memory.
 *
 * Frame policy: checksum, length and range (ddyn_dbw_decode), a repeated counter and a counter up
 * to 8 behind (an older frame arriving late) reject a frame; a counter jump forward means frames
 * were lost and is counted, the frame itself is used. The counters also date every frame
 * (ddyn_dbw_link: its age against the freshest frame on the bus); the readings carry their ages,
 * the period its latency (the position frame's age) and the bus faults since the last period into
 * the controller's degraded-bus mode (ddyn/controller.h). A monitored frame missing for more than
 * `stale[f]` periods (plus the degraded mode's extra periods, ddyn_ctrl_stale_limit), or the
 * controller's own safe mode, gives the safe command (ddyn_ctrl_safe_command: brake, then hold; steering held). (The strict monitor of
 * ddyn/dbw.h, where every counter jump is a failure that needs an explicit re-enable, would stop
 * the car at the first lost frame; a lossy bus needs this tolerant policy.)
 *
 * Frame authentication (docs/can.md "Authenticated frames", AUTOSAR SecOC style), when enabled with a
 * key (ddyn_sil_node_auth_enable; the application reads it from can.key_file or DDYN_DBW_KEY_FILE):
 * a good protected frame (length 8, valid CRC) of the six the controller reads is held until its
 * sender's authenticator arrives and verifies; only then does it go through the policy above. A
 * forged, replayed or stale frame is counted (auth_forged, auth_replayed, auth_stale) and dropped,
 * never fatal: a genuine sender whose frames stop verifying is caught by the missing-frame limit.
 * Each command goes out with its authenticator (ddyn_sil_period.auth_data under auth_can_id, to be
 * sent right after the command frame). Off (the default), nothing of this runs.
 *
 * C99, no allocation: the caller owns the (large) node.
 */
#ifndef DDYN_SIL_CONTROLLER_NODE_H
#define DDYN_SIL_CONTROLLER_NODE_H

#include <stddef.h>
#include <stdint.h>

#include "ddyn/controller.h"
#include "ddyn/dbw.h"

#ifdef __cplusplus
extern "C" {
#endif

typedef struct {
    ddyn_ctrl ctl;
    ddyn_ctrl_input in;        /* readings of the current period */
    ddyn_dbw_signals sig;      /* last decoded values */
    double period;             /* s */
    double state_lo[2], state_hi[2]; /* throttle, steering set-point bounds */
    double setpoint[2];        /* the throttle and steering commanded last (integrated rates) */
    int stale[DDYN_DBW_FRAME_COUNT];  /* periods a monitored frame may be missing; 0 = unmonitored */
    long last_rx_step[DDYN_DBW_FRAME_COUNT];
    int last_counter[DDYN_DBW_FRAME_COUNT];
    ddyn_dbw_link link;        /* frame ages and bus faults (degraded-bus mode) */
    long steps;
    int catch_up;              /* periods still to run before the one of the last position frame */
    uint8_t tx_counter;
    /* frame authentication (off unless ddyn_sil_node_auth_enable) */
    int auth_on;
    ddyn_dbw_auth auth;        /* the held frames, the freshness values accepted, the key */
    uint64_t auth_freshness;   /* the next command's freshness value */
    uint8_t auth_counter;      /* SecOC_Controller's rolling counter */
    uint64_t rx_us;            /* receive time of the latest frame (the clock of the expiry) */
    /* counts */
    long frames_ok, frames_lost, repeated_counter, late, checksum, bad_length, range, unknown_id, safe_steps;
    long auth_accepted, auth_forged, auth_replayed, auth_stale;
} ddyn_sil_node;

typedef struct {
    ddyn_ctrl_output out;      /* what the controller step returned */
    int safe;                  /* the safe command went out */
    int stale;                 /* a monitored frame was missing */
    double throttle, steering; /* the set-points sent */
    uint8_t data[DDYN_DBW_FRAME_LEN];
    uint32_t can_id;
    int has_auth;              /* authentication on: send auth_data under auth_can_id right after data */
    uint8_t auth_data[DDYN_DBW_FRAME_LEN];
    uint32_t auth_can_id;
    /* the readings the period's step fused (a copy: the node clears its own after the step), so that the log
     * can record the raw sensors beside the filter's estimate, as a car's log does (ddyn_sil_log_readings) */
    ddyn_ctrl_input readings;
} ddyn_sil_period;

/* The raw readings a log records per period, after the state estimate: the yaw rate (IMU), the steering angle fed
 * back by the drive-by-wire unit, the accelerometer's (ax, ay), the GNSS position (x, y) and the GNSS heading,
 * each NaN when no reading came in the period. A diagnosis of the log reads the yaw rate from here rather than
 * from the estimate: the estimate comes from a filter whose model lacks whatever the diagnosis looks for (an
 * actuation delay, filtered by it, reads as a lag). The accelerometer reads the tyre and drag forces, not gravity:
 * on a banked road its ay differs from dvy + vx omega by the bank's g sin(bank), which the filter's states alone
 * hide. The position and heading as measured give the lateral velocity over the ground without the filter's model,
 * whose flat road turns its heading (and so the vy read from its track) away from a banked plant's. */
#define DDYN_SIL_LOG_READINGS_HEADER "yaw_rate_meas,steering_meas,ax_meas,ay_meas,gnss_x_meas,gnss_y_meas,heading_meas"
#define DDYN_SIL_LOG_READINGS 7
void ddyn_sil_log_readings(const ddyn_sil_period *p, double out[DDYN_SIL_LOG_READINGS]);

/* Set up the node around an initialised controller configuration. Returns DDYN_OK or the
 * controller's error. */
ddyn_status ddyn_sil_node_init(ddyn_sil_node *node, const ddyn_vehicle_model *model, const ddyn_net_tables *tables,
                               const ddyn_ctrl_config *cfg, const double x0[DDYN_NX], double period,
                               const int stale[DDYN_DBW_FRAME_COUNT]);

/* One received frame. Returns the number of control periods to run now: 0 for most frames, 1 for a
 * good GNSS_Position frame (the period's trigger). Position frames lost just before it (at most
 * DDYN_SIL_MAX_CATCH_UP) are caught up inside that period (ddyn_sil_node_period) so that the
 * filter's clock keeps pace with the plant's: their commands are not sent (the plant has moved on;
 * in lock-step a surplus command would answer a later position frame and delay every command after
 * it by a period), so the filter predicts them with the actuators held. */
#define DDYN_SIL_MAX_CATCH_UP 3
int ddyn_sil_node_on_frame(ddyn_sil_node *node, uint32_t can_id, const uint8_t *data, size_t len);
/* The same with the frame's receive time in microseconds (any monotonic clock): with authentication
 * on, a held frame whose authenticator has not come within DDYN_DBW_AUTH_TIMEOUT_US of it is dropped
 * (stale). ddyn_sil_node_on_frame uses the time of the previous frame. */
int ddyn_sil_node_on_frame_at(ddyn_sil_node *node, uint32_t can_id, const uint8_t *data, size_t len, uint64_t t_us);

/* Authenticate the frames the node reads and sign its commands with key[32] (copied; the caller
 * wipes its own copy). After ddyn_sil_node_init. Returns DDYN_OK or DDYN_ERR_ARGUMENT. */
ddyn_status ddyn_sil_node_auth_enable(ddyn_sil_node *node, const uint8_t key[DDYN_DBW_AUTH_KEY_LEN]);

/* One control period with the readings received since the last one (after the catch-up periods of
 * lost position frames, whose commands are not sent); the command frame is encoded into p->data
 * (identifier p->can_id), with authentication on its authenticator into p->auth_data
 * (p->auth_can_id). With authentication on, held frames older than the timeout at the latest
 * receive time are dropped first (stale). */
void ddyn_sil_node_period(ddyn_sil_node *node, ddyn_sil_period *p);

#ifdef __cplusplus
}
#endif

#endif
