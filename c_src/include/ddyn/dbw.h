/*
 * ddyn/dbw.h - the drive-by-wire protocol logic, portable (no OS, no CAN driver, no allocation).
 *
 * The frames are defined by can/ddyn_dbw.dbc and packed/unpacked by the cantools-generated
 * c_src/generated/can/ddyn_can.{h,c}. This layer adds what a DBC cannot say:
 *   - the rolling counter (+1 modulo 16 per identifier) and the CRC-8 checksum of every frame;
 *   - range checks of physical values on the sending side and of raw values on the receiving side;
 *   - a monitor per endpoint: per-frame receive deadlines, counter jump/repeat, bad checksum,
 *     out-of-range signal, unknown frame, bad length, bus-off and interface-gone reports; each
 *     failure is counted by kind and drops the endpoint to the safe command at once;
 *   - explicit recovery: after a failure, every monitored frame must arrive fresh and good
 *     `recovery_good_frames` times in a row (state READY), and then the caller must call
 *     ddyn_dbw_enable() again. Nothing resumes actuation on its own.
 *
 * The same monitor serves both ends: the controller monitors the feedback and sensor frames,
 * a drive-by-wire unit (or the SIL simulator's emulator) monitors DBW_Command.
 *
 * Time is a caller-supplied monotonic clock in microseconds (uint64_t).
 */
#ifndef DDYN_DBW_H
#define DDYN_DBW_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "ddyn/status.h"

#ifdef __cplusplus
extern "C" {
#endif

/* The frames of the protocol, in DBC order. */
typedef enum {
    DDYN_DBW_FRAME_COMMAND = 0,   /* 0x100 DBW_Command     controller -> DBW */
    DDYN_DBW_FRAME_STEERING,      /* 0x110 DBW_Steering    DBW -> controller */
    DDYN_DBW_FRAME_STATUS,        /* 0x111 DBW_Status      DBW -> controller */
    DDYN_DBW_FRAME_WHEEL_SPEEDS,  /* 0x112 DBW_WheelSpeeds DBW -> controller */
    DDYN_DBW_FRAME_IMU,           /* 0x120 IMU             sensors -> controller */
    DDYN_DBW_FRAME_GNSS_POSITION, /* 0x130 GNSS_Position   sensors -> controller */
    DDYN_DBW_FRAME_GNSS_HEADING,  /* 0x131 GNSS_Heading    sensors -> controller */
    DDYN_DBW_FRAME_COUNT
} ddyn_dbw_frame;

#define DDYN_DBW_FRAME_LEN 8u
#define DDYN_DBW_COUNTER_MODULO 16u
/* the identifier block the protocol lives in: 0x100-0x13F (acceptance filter id/mask) */
#define DDYN_DBW_ID_BLOCK_BASE 0x100u
#define DDYN_DBW_ID_BLOCK_MASK 0x7C0u

/* Mode signal values (DBC VAL_ tables of DBW_Command.Mode and DBW_Status.Mode). */
typedef enum { DDYN_DBW_MODE_STANDBY = 0, DDYN_DBW_MODE_AUTONOMOUS = 1, DDYN_DBW_MODE_SAFE_STOP = 2 } ddyn_dbw_mode;

/* DBW_Status.Faults bits, as the DBW unit reports them. */
enum {
    DDYN_DBW_FAULT_CMD_TIMEOUT = 1u << 0,
    DDYN_DBW_FAULT_CMD_COUNTER = 1u << 1,
    DDYN_DBW_FAULT_CMD_CHECKSUM = 1u << 2,
    DDYN_DBW_FAULT_CMD_RANGE = 1u << 3,
    DDYN_DBW_FAULT_ACTUATOR = 1u << 4,
    DDYN_DBW_FAULT_ESTOP = 1u << 5
};

/* What can go wrong; every kind is counted separately (ddyn_dbw.failures[kind]). */
typedef enum {
    DDYN_DBW_FAIL_STALE = 0,      /* a monitored frame older than its deadline */
    DDYN_DBW_FAIL_COUNTER_JUMP,   /* counter not previous + 1: frames lost */
    DDYN_DBW_FAIL_COUNTER_REPEAT, /* counter equal to the previous one: a stuck sender */
    DDYN_DBW_FAIL_CHECKSUM,       /* CRC-8 mismatch */
    DDYN_DBW_FAIL_RANGE,          /* a received signal outside its DBC range */
    DDYN_DBW_FAIL_UNKNOWN_FRAME,  /* an identifier inside the protocol's block that the DBC does not define:
                                   * counted, never fatal (no endpoint monitors an identifier it does not know) */
    DDYN_DBW_FAIL_BAD_LENGTH,     /* a known identifier with a data length other than 8 */
    DDYN_DBW_FAIL_BUS_OFF,        /* the controller went bus-off (reported by the transport) */
    DDYN_DBW_FAIL_BUS_ERROR,      /* other error frames: error passive, protocol, transceiver, lost arbitration excluded */
    DDYN_DBW_FAIL_IFACE_GONE,     /* the interface went down or disappeared (reported by the transport) */
    DDYN_DBW_FAIL_COMMAND_RANGE,  /* the caller asked to send a non-finite or out-of-range command */
    /* authentication (ddyn_dbw_auth_enable): counted and the frame dropped, never fatal (a node that
     * forges frames must not be able to stop the car; the deadlines still catch genuine frames that stop) */
    DDYN_DBW_FAIL_AUTH_FORGED,    /* an authenticator whose MAC does not match its frame, or a bad authenticator frame */
    DDYN_DBW_FAIL_AUTH_REPLAY,    /* a freshness value not newer than the last one accepted for that frame */
    DDYN_DBW_FAIL_AUTH_STALE,     /* a protected frame without its authenticator in time, or an authenticator without a frame */
    DDYN_DBW_FAIL_COUNT
} ddyn_dbw_failure;

typedef enum {
    DDYN_DBW_WAIT_GOOD = 0, /* safe command; waiting for every monitored frame to be good N times in a row */
    DDYN_DBW_READY,         /* safe command; the link is good, waiting for an explicit ddyn_dbw_enable() */
    DDYN_DBW_ACTIVE         /* the caller's commands go out */
} ddyn_dbw_state;

/* Result of decoding one frame. */
typedef enum {
    DDYN_DBW_DECODE_OK = 0,
    DDYN_DBW_DECODE_UNKNOWN_ID,  /* inside the protocol's block, not in the DBC */
    DDYN_DBW_DECODE_FOREIGN_ID,  /* outside the protocol's block (or extended): not ours, ignored */
    DDYN_DBW_DECODE_BAD_LENGTH,
    DDYN_DBW_DECODE_CHECKSUM,
    DDYN_DBW_DECODE_RANGE,
    DDYN_DBW_DECODE_ARGUMENT,    /* NULL pointer */
    /* authentication (ddyn_dbw_on_frame with ddyn_dbw_auth_enable; ddyn_dbw_decode gives the first only) */
    DDYN_DBW_DECODE_AUTHENTICATOR, /* a SecOC_* authenticator frame (length and checksum good) */
    DDYN_DBW_DECODE_AUTH_PENDING,  /* a good protected frame, held until its authenticator arrives */
    DDYN_DBW_DECODE_AUTH_REJECTED  /* an authenticator refused: forged, replayed or stale (counted) */
} ddyn_dbw_decode_result;

/* ---- authentication in the manner of AUTOSAR SecOC (c_src/src/dbw_auth.c, docs/can.md) ----
 * Every protected frame is followed by an authenticator frame of its sender (SecOC_Controller 0x101,
 * SecOC_DBW 0x113, SecOC_Sensors 0x121; can/ddyn_dbw.dbc) carrying the protected identifier, the low
 * 22 bits of a 64-bit freshness value (+1 per frame, per identifier) and a 24-bit MAC: the first 24
 * bits of keyed BLAKE2b (Monocypher, 32-byte key, 8-byte digest) over identifier (2 bytes LE), the
 * frame's 8 data bytes and the full freshness value (8 bytes LE). The receiver holds a good protected
 * frame until its authenticator arrives (at most timeout_us), reconstructs the full freshness value
 * from its low bits (newer than the last accepted; not newer = replay), checks the MAC, and only then
 * applies the frame. Forged, replayed and stale frames are counted and dropped; none trips the link. */
#define DDYN_DBW_AUTH_KEY_LEN 32u
#define DDYN_DBW_AUTH_MAC_BITS 24u
#define DDYN_DBW_AUTH_FRESHNESS_BITS 22u
#define DDYN_DBW_AUTH_TIMEOUT_US 5000u /* default: an authenticator follows its frame within 5 ms */
#define DDYN_DBW_AUTH_HOLD 2u /* held frames per identifier */
/* room for one BLAKE2b state (Monocypher's crypto_blake2b_ctx, 216-224 bytes; dbw_auth.c checks it fits) */
#define DDYN_DBW_AUTH_STATE_WORDS 28u

typedef struct {
    bool enabled;
    uint8_t key[DDYN_DBW_AUTH_KEY_LEN];
    /* per frame, the keyed BLAKE2b state after the key block and the frame's 2 identifier bytes, made once
     * by ddyn_dbw_auth_init: each MAC is then one compression instead of two (dbw_auth.c); wiped with the key */
    uint64_t mac_state[DDYN_DBW_FRAME_COUNT][DDYN_DBW_AUTH_STATE_WORDS];
    uint32_t timeout_us;
    uint64_t tx_freshness[DDYN_DBW_FRAME_COUNT]; /* per frame: the next value sent */
    uint8_t tx_counter[3];           /* rolling counters of the three authenticator identifiers */
    uint64_t rx_freshness[DDYN_DBW_FRAME_COUNT];        /* the last value accepted per frame */
    bool rx_freshness_valid[DDYN_DBW_FRAME_COUNT];
    /* good protected frames waiting for their authenticator, DDYN_DBW_AUTH_HOLD per frame: a frame
     * injected between a genuine frame and its authenticator does not push the genuine one out */
    uint8_t pending[DDYN_DBW_FRAME_COUNT][DDYN_DBW_AUTH_HOLD][DDYN_DBW_FRAME_LEN];
    uint64_t pending_us[DDYN_DBW_FRAME_COUNT][DDYN_DBW_AUTH_HOLD];
    bool pending_valid[DDYN_DBW_FRAME_COUNT][DDYN_DBW_AUTH_HOLD];
    uint32_t accepted;               /* frames authenticated since enable (saturating) */
} ddyn_dbw_auth;

/* The actuator command in physical units (DBW_Command). */
typedef struct {
    double throttle; /* [0, 1] pedal fraction */
    double brake;    /* [0, 1] brake fraction */
    double steering; /* [-0.6, 0.6] rad road-wheel angle, positive left */
    bool enable;
    ddyn_dbw_mode mode;
} ddyn_dbw_command;

/* Feedback of the DBW unit (DBW_Steering, DBW_Status, DBW_WheelSpeeds). */
typedef struct {
    double steering;       /* rad, measured */
    double steering_rate;  /* rad/s */
    double throttle_pedal; /* [0, 1] */
    double brake_pedal;    /* [0, 1] */
    ddyn_dbw_mode mode;
    bool enabled;
    bool driver_override;
    uint8_t faults;          /* DDYN_DBW_FAULT_* bits */
    double wheel_speed_front; /* m/s, longitudinal speed of the front wheel plane */
    double wheel_speed_rear;  /* m/s, rear axle */
} ddyn_dbw_feedback;

/* Sensor readings (IMU, GNSS_Position, GNSS_Heading), the units of train/model/sensors.py. */
typedef struct {
    double yaw_rate; /* rad/s */
    double accel_x;  /* m/s^2, body frame */
    double accel_y;
    double gnss_x;   /* m, local track frame */
    double gnss_y;
    double heading;  /* rad */
    uint8_t fix_type; /* 0 none, 1 single, 2 DGNSS, 3 RTK float, 4 RTK fixed */
} ddyn_dbw_sensors;

/* Every signal of the protocol: what a frame decodes into / encodes from. */
typedef struct {
    ddyn_dbw_command command;
    ddyn_dbw_feedback feedback;
    ddyn_dbw_sensors sensors;
} ddyn_dbw_signals;

typedef struct {
    /* receive deadline per frame in microseconds; 0 = this endpoint does not monitor the frame
     * (it is still decoded and checked if it arrives, but its absence is no failure) */
    uint32_t deadline_us[DDYN_DBW_FRAME_COUNT];
    /* consecutive good frames of every monitored frame needed before READY */
    uint32_t recovery_good_frames;
    /* the safe command's brake fraction */
    double safe_brake;
} ddyn_dbw_config;

typedef struct {
    uint64_t last_rx_us;
    uint32_t good_streak;
    uint32_t received;   /* good frames since init */
    uint8_t last_counter;
    bool seen;           /* a good frame has arrived since init */
    bool counter_valid;  /* last_counter is meaningful */
    bool stale;          /* the deadline has passed since the last good frame (reported once) */
} ddyn_dbw_rx_track;

typedef struct {
    ddyn_dbw_config config;
    ddyn_dbw_state state;
    ddyn_dbw_signals latest;          /* last good values of every received frame */
    uint32_t fresh_mask;              /* bit f: frame f decoded good since ddyn_dbw_take_fresh() */
    ddyn_dbw_rx_track rx[DDYN_DBW_FRAME_COUNT];
    uint32_t failures[DDYN_DBW_FAIL_COUNT]; /* counts by kind since init */
    uint32_t failure_mask;            /* bit k: failure k since ddyn_dbw_take_failures() */
    ddyn_dbw_failure last_failure;
    int last_failure_frame;           /* ddyn_dbw_frame, or -1 when no frame is concerned */
    uint64_t last_failure_us;
    uint8_t tx_counter[DDYN_DBW_FRAME_COUNT];
    double held_steering;             /* the last steering sent while ACTIVE: the safe command holds it */
    bool any_failure;
    ddyn_dbw_auth auth;               /* frame authentication, off until ddyn_dbw_auth_enable() */
} ddyn_dbw;

/* ---- frames: pure functions ---- */

/* CAN identifier of a frame, and the frame of an identifier (-1 when unknown). */
uint32_t ddyn_dbw_frame_id(ddyn_dbw_frame frame);
int ddyn_dbw_frame_of_id(uint32_t can_id);
/* Whether an identifier is one of the SecOC_* authenticator frames. */
bool ddyn_dbw_is_authenticator_id(uint32_t can_id);
/* The DBC's cycle time of a frame in microseconds. */
uint32_t ddyn_dbw_cycle_us(ddyn_dbw_frame frame);

/* CRC-8/SAE-J1850 over the identifier (two bytes, little-endian) and data bytes 0..6. */
uint8_t ddyn_dbw_checksum(uint32_t can_id, const uint8_t data[DDYN_DBW_FRAME_LEN]);

/* Encode frame `frame` from `s` (its physical values) with rolling counter `counter` into data[8].
 * Returns DDYN_OK, DDYN_ERR_ARGUMENT (NULL, unknown frame) or DDYN_ERR_RANGE when a value is
 * non-finite or outside its DBC range (data is then unspecified). */
ddyn_status ddyn_dbw_encode(ddyn_dbw_frame frame, const ddyn_dbw_signals *s, uint8_t counter,
                    uint8_t data[DDYN_DBW_FRAME_LEN]);

/* Decode one received frame: identifier, length, checksum and raw ranges are checked; on OK
 * the frame's signals are written into `s` (other members untouched), *frame and *counter set. */
ddyn_dbw_decode_result ddyn_dbw_decode(uint32_t can_id, const uint8_t *data, size_t len,
                                       ddyn_dbw_signals *s, ddyn_dbw_frame *frame, uint8_t *counter);

/* ---- the endpoint monitor ---- */

/* Defaults: deadline = 3 cycle times for every frame in `monitored_mask` (bit per ddyn_dbw_frame),
 * 0 for the others; 5 good frames to recover; safe brake 0.3. */
void ddyn_dbw_default_config(ddyn_dbw_config *config, uint32_t monitored_mask);
/* The controller's mask: all feedback and sensor frames. The DBW unit's: the command frame. */
#define DDYN_DBW_MONITOR_CONTROLLER \
    ((1u << DDYN_DBW_FRAME_STEERING) | (1u << DDYN_DBW_FRAME_STATUS) | (1u << DDYN_DBW_FRAME_WHEEL_SPEEDS) | \
     (1u << DDYN_DBW_FRAME_IMU) | (1u << DDYN_DBW_FRAME_GNSS_POSITION) | (1u << DDYN_DBW_FRAME_GNSS_HEADING))
#define DDYN_DBW_MONITOR_DBW_UNIT (1u << DDYN_DBW_FRAME_COMMAND)

/* Returns DDYN_OK, DDYN_ERR_ARGUMENT for a NULL argument or DDYN_ERR_CONFIG for a config with no monitored frame, recovery_good_frames 0
 * or a safe brake outside [0, 1]. Starts in WAIT_GOOD. */
ddyn_status ddyn_dbw_init(ddyn_dbw *dbw, const ddyn_dbw_config *config);

/* Feed one received frame (kernel receive time t_us). Foreign identifiers are ignored; everything
 * else either updates `latest` or is a failure. A failure drops the link only when this endpoint
 * monitors the frame (deadline > 0); a defect of an unmonitored frame and an unknown identifier of
 * the block are counted, not fatal. Returns the decode result. */
ddyn_dbw_decode_result ddyn_dbw_on_frame(ddyn_dbw *dbw, uint32_t can_id, const uint8_t *data, size_t len,
                                         uint64_t t_us);

/* Report a failure seen by the transport (DDYN_DBW_FAIL_BUS_OFF, _BUS_ERROR, _IFACE_GONE) or the caller.
 * After BUS_OFF and IFACE_GONE the next counter of every frame is accepted as a new sequence. */
void ddyn_dbw_report(ddyn_dbw *dbw, ddyn_dbw_failure kind, uint64_t t_us);

/* Deadlines and recovery at time now_us: a monitored frame older than its deadline is a STALE
 * failure (counted once per lapse); WAIT_GOOD becomes READY when every monitored frame is fresh
 * with a good streak of recovery_good_frames. Returns the state. */
ddyn_dbw_state ddyn_dbw_check(ddyn_dbw *dbw, uint64_t now_us);

/* READY -> ACTIVE. Returns DDYN_OK, or DDYN_ERR_NOT_READY in any other state (the caller must wait
 * for good frames; DDYN_ERR_ARGUMENT for NULL). */
ddyn_status ddyn_dbw_enable(ddyn_dbw *dbw);
/* Back to WAIT_GOOD without a failure (the operator disengages). */
void ddyn_dbw_disable(ddyn_dbw *dbw);

/* The safe command: zero throttle, the configured brake, steering held, mode SAFE_STOP. */
void ddyn_dbw_safe_command(const ddyn_dbw *dbw, ddyn_dbw_command *out);

/* Once per control period: ddyn_dbw_check(now_us), then `desired` (enable forced on, mode
 * AUTONOMOUS) when ACTIVE, otherwise the safe command; a desired command that is non-finite or
 * out of range is a COMMAND_RANGE failure and the safe command goes out instead. The result is
 * encoded into data[8] with the next rolling counter. Returns the state after the call. */
ddyn_dbw_state ddyn_dbw_command_frame(ddyn_dbw *dbw, uint64_t now_us, const ddyn_dbw_command *desired,
                                      ddyn_dbw_command *sent, uint8_t data[DDYN_DBW_FRAME_LEN]);

/* Encode frame `frame` from `s` with this endpoint's next rolling counter for it (for the DBW
 * unit / simulator side sending feedback and sensors). Returns as ddyn_dbw_encode. */
ddyn_status ddyn_dbw_next_frame(ddyn_dbw *dbw, ddyn_dbw_frame frame, const ddyn_dbw_signals *s,
                        uint8_t data[DDYN_DBW_FRAME_LEN]);

/* ---- authentication (c_src/src/dbw_auth.c) ---- */

/* Authenticate the frames this endpoint monitors and sign the frames it sends, with `key` (copied;
 * the caller should wipe its copy). timeout_us 0 = DDYN_DBW_AUTH_TIMEOUT_US. Freshness counters
 * start at 0. Returns DDYN_OK or DDYN_ERR_ARGUMENT. */
ddyn_status ddyn_dbw_auth_enable(ddyn_dbw *dbw, const uint8_t key[DDYN_DBW_AUTH_KEY_LEN], uint32_t timeout_us);
/* Off again; the key and its prepared MAC states are wiped. */
void ddyn_dbw_auth_disable(ddyn_dbw *dbw);

/* The authenticator of a frame this endpoint has just encoded (ddyn_dbw_command_frame,
 * ddyn_dbw_next_frame): send it right after `data`, under identifier *auth_id. Consumes one freshness
 * value of the frame. Returns DDYN_OK, DDYN_ERR_ARGUMENT (NULL, unknown frame) or DDYN_ERR_NOT_READY
 * when authentication is off. */
ddyn_status ddyn_dbw_authenticator(ddyn_dbw *dbw, ddyn_dbw_frame frame, const uint8_t data[DDYN_DBW_FRAME_LEN],
                                   uint32_t *auth_id, uint8_t auth_data[DDYN_DBW_FRAME_LEN]);

/* Pure pieces, for any caller (the simulator's plant, tools): */
/* the authenticator identifier of the node that sends `frame` (0 for an unknown frame) */
uint32_t ddyn_dbw_auth_id(ddyn_dbw_frame frame);
/* the 24-bit MAC of one frame with a full freshness value */
uint32_t ddyn_dbw_auth_mac(const uint8_t key[DDYN_DBW_AUTH_KEY_LEN], uint32_t can_id,
                           const uint8_t data[DDYN_DBW_FRAME_LEN], uint64_t freshness);
/* the same MAC with the key of an initialised `auth` (its prepared state: one BLAKE2b compression instead of
 * two); 0 when `auth` has no key */
uint32_t ddyn_dbw_auth_frame_mac(const ddyn_dbw_auth *auth, ddyn_dbw_frame frame, const uint8_t data[DDYN_DBW_FRAME_LEN],
                                 uint64_t freshness);
/* encode an authenticator frame (counter and checksum included) for `frame` with `freshness` */
ddyn_status ddyn_dbw_auth_encode(const uint8_t key[DDYN_DBW_AUTH_KEY_LEN], ddyn_dbw_frame frame,
                                 const uint8_t data[DDYN_DBW_FRAME_LEN], uint64_t freshness, uint8_t counter,
                                 uint8_t auth_data[DDYN_DBW_FRAME_LEN]);
/* ddyn_dbw_auth_encode with the key of an initialised `auth` (ddyn_dbw_auth_frame_mac); DDYN_ERR_NOT_READY
 * when it has no key */
ddyn_status ddyn_dbw_auth_sign(const ddyn_dbw_auth *auth, ddyn_dbw_frame frame, const uint8_t data[DDYN_DBW_FRAME_LEN],
                               uint64_t freshness, uint8_t counter, uint8_t auth_data[DDYN_DBW_FRAME_LEN]);
/* decode an authenticator frame: length, checksum, identifier; *frame, *freshness_low, *mac, *counter */
ddyn_dbw_decode_result ddyn_dbw_auth_decode(uint32_t can_id, const uint8_t *data, size_t len, ddyn_dbw_frame *frame,
                                            uint32_t *freshness_low, uint32_t *mac, uint8_t *counter);

/* Receiver state without the monitor (the simulator's plant uses it for DBW_Command); with a key, its MAC
 * states are prepared here (7 BLAKE2b compressions): */
void ddyn_dbw_auth_init(ddyn_dbw_auth *auth, const uint8_t key[DDYN_DBW_AUTH_KEY_LEN], uint32_t timeout_us);
/* hold a good protected frame (the oldest of DDYN_DBW_AUTH_HOLD makes room); returns true when it
 * displaced one that was never authenticated (stale) */
bool ddyn_dbw_auth_hold(ddyn_dbw_auth *auth, ddyn_dbw_frame frame, const uint8_t data[DDYN_DBW_FRAME_LEN],
                        uint64_t t_us);
/* verify an authenticator frame against the held frames of its identifier; on DDYN_DBW_FAIL_COUNT
 * (accepted) the matching frame is released into *frame, data and *data_t_us; otherwise the failure
 * kind (AUTH_FORGED, AUTH_REPLAY, AUTH_STALE). A rejected authenticator leaves the held frames held,
 * so that the genuine authenticator that follows still finds its frame. */
ddyn_dbw_failure ddyn_dbw_auth_verify(ddyn_dbw_auth *auth, uint32_t can_id, const uint8_t *auth_data, size_t len,
                                      uint64_t t_us, ddyn_dbw_frame *frame, uint8_t data[DDYN_DBW_FRAME_LEN],
                                      uint64_t *data_t_us);
/* drop held frames older than the timeout at now_us; returns how many (each a stale frame), and in
 * *frames (may be NULL) the bit of each frame that lost one */
uint32_t ddyn_dbw_auth_expire(ddyn_dbw_auth *auth, uint64_t now_us, uint32_t *frames);

/* Read-and-clear of the fresh-frame and failure bit sets. */
uint32_t ddyn_dbw_take_fresh(ddyn_dbw *dbw);
uint32_t ddyn_dbw_take_failures(ddyn_dbw *dbw);

/* The DBW_Status.Faults bits a DBW unit reports for the failures in `failure_mask` (command side). */
uint8_t ddyn_dbw_fault_bits(uint32_t failure_mask);

/* ---- frame ages on a degraded bus (the controller side) ----
 *
 * The frames carry no time stamp, only the 4-bit rolling counter. With the DBC's cycle time the
 * counter still dates a frame: unwrapped into a sequence number n (a step of 1..8 forward is new,
 * n advancing by the step; 0 a repeat; 9..15 an older frame overtaken by a newer one, "late"), the
 * frame was sampled at tau = phase + n * cycle. The link's bus clock `now_s` is the sample time of
 * the freshest frame of any stream, and a frame's AGE is now_s - tau: how much older it is than the
 * freshest data on the bus. That is the delay the controller can measure without a shared clock
 * (it is relative: a bus that delays every frame by the same amount shows age 0).
 *
 * Phases: a stream's first frame is taken as fresh (phase = now_s - n * cycle). A stream whose
 * first frame was itself delayed (or arrived just before fresher frames of the same instant) would
 * look old for ever, so the caller ticks the link once per control period (ddyn_dbw_link_tick), and
 * every DDYN_DBW_LINK_WINDOW ticks (the first window: one tick) the smallest age the stream's newest frame showed at them is added
 * to its phase: its least delayed frame is fresh by definition. Phases only move forward, by measured
 * amounts.
 *
 * Cycles: the DBC's GenMsgCycleTime by default (ddyn_dbw_cycle_us). A car whose nodes send a frame at
 * another rate (the AV-21 sends its GNSS frames once per 40 ms control period, the DBC says 20 ms) must
 * say so (ddyn_dbw_link_set_cycle): dated with the wrong cycle, a clean stream drifts against the others
 * by (DBC cycle - real cycle) per frame, and every period reads as late (issue 34: 2,616 of 2,619
 * periods of a clean AV-21 lap were in the degraded-bus mode).
 *
 * Lost frames (counter jumps), late frames, repeats and bad frames (checksum, length, range) are
 * counted since the last ddyn_dbw_link_take_faults(): the controller's degraded-bus detection.
 * Every count, their sum and the sequence numbers saturate instead of wrapping. */
#define DDYN_DBW_LINK_WINDOW 16

typedef enum {
    DDYN_DBW_LINK_NEW = 0,      /* a newer frame: use it (age and lost frames are set) */
    DDYN_DBW_LINK_REPEATED = 1, /* counter equal to the last one: a stuck sender, do not use */
    DDYN_DBW_LINK_LATE = 2      /* older than a frame already received: do not use */
} ddyn_dbw_link_result;

typedef struct {
    double now_s;                              /* bus clock: sample time of the freshest frame */
    double cycle_s[DDYN_DBW_FRAME_COUNT];      /* each stream's cycle (init: the DBC's) */
    double phase_s[DDYN_DBW_FRAME_COUNT];      /* sample time of sequence number 0 */
    double window_min_s[DDYN_DBW_FRAME_COUNT]; /* smallest age at the ticks of the current window */
    int64_t seq[DDYN_DBW_FRAME_COUNT];         /* unwrapped sequence number of the newest frame */
    int window_n[DDYN_DBW_FRAME_COUNT];
    uint8_t last_counter[DDYN_DBW_FRAME_COUNT];
    bool seen[DDYN_DBW_FRAME_COUNT];
    bool ticked[DDYN_DBW_FRAME_COUNT];         /* its first window (one tick) is over */
    bool any_seen;
    /* since the last ddyn_dbw_link_take_faults() */
    uint32_t lost, late, repeated, bad;
} ddyn_dbw_link;

/* Every stream at the DBC's cycle time. */
void ddyn_dbw_link_init(ddyn_dbw_link *link);

/* The cycle at which this car's sender really sends `frame`, in microseconds; 0 = the DBC's. Call it
 * after ddyn_dbw_link_init and before the stream's first frame. Returns DDYN_OK, or DDYN_ERR_ARGUMENT
 * (NULL link, unknown frame, or a cycle above 10 s, the DBC's largest GenMsgCycleTime). */
ddyn_status ddyn_dbw_link_set_cycle(ddyn_dbw_link *link, ddyn_dbw_frame frame, uint32_t cycle_us);

/* One good frame (decoded with a good checksum) of `frame` with `counter`. On NEW, *lost (may be
 * NULL) is the number of frames of this stream skipped before it and *age_s (may be NULL) its age
 * in seconds (>= 0). DDYN_DBW_FRAME_COUNT or a NULL link: REPEATED (ignored). */
ddyn_dbw_link_result ddyn_dbw_link_on_frame(ddyn_dbw_link *link, ddyn_dbw_frame frame, uint8_t counter,
                                            unsigned *lost, double *age_s);

/* Once per control period, after the period's frames: the phase correction above. */
void ddyn_dbw_link_tick(ddyn_dbw_link *link);

/* A frame refused by its checksum, length or range: counted as bad. */
void ddyn_dbw_link_on_bad_frame(ddyn_dbw_link *link);

/* The cycle (s) the link dates `frame` with (-1 for an unknown frame or a NULL link). */
double ddyn_dbw_link_cycle(const ddyn_dbw_link *link, ddyn_dbw_frame frame);

/* The age now (s) of the newest frame received of `frame` (-1 when none yet). */
double ddyn_dbw_link_age(const ddyn_dbw_link *link, ddyn_dbw_frame frame);

/* Lost + late + repeated + bad frames since the last call, and clear those counts. */
uint32_t ddyn_dbw_link_take_faults(ddyn_dbw_link *link);

const char *ddyn_dbw_failure_name(ddyn_dbw_failure kind);
const char *ddyn_dbw_frame_name(ddyn_dbw_frame frame);
const char *ddyn_dbw_state_name(ddyn_dbw_state state);

#ifdef __cplusplus
}
#endif

#endif /* DDYN_DBW_H */
