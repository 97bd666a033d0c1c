/*
 * ddyn/controller.h - one control period of the car: EKF -> history -> guard network -> MPC -> command.
 *
 * The chain (docs/controller.md), once per sample time, in ddyn_ctrl_step:
 *   1. history: the row [vx, vy, omega, throttle, steering, dthrottle, dsteering] of the previous
 *      period (the filter's estimate then and the command applied from it) enters the guard
 *      network's history of DDYN_NET_TAU rows, exactly the rows the network was trained on
 *      (train/data/windows.py: row k = state at k and the input applied from k to k+1);
 *   2. coefficients: the guard network reads the history (the 17 coefficients of the step that
 *      led to now); while the history fills, or when the history's states lie outside the
 *      network's training range or the network's output is not finite, the last good coefficients (for a
 *      bounded number of periods) or the vehicle's nominal ones are used instead. With
 *      cfg.coeff_source = DDYN_CTRL_SOURCE_FIXED the network is never run: cfg.c_fixed every period;
 *   3. EKF predict over the period with the previous command and those coefficients, then an
 *      update for every reading marked valid this period (sensors arrive at their own rates);
 *      NaN/inf readings are rejected and counted, the filter goes on predicting;
 *   4. MPC: one real-time iteration from the estimate with the coefficients. With
 *      cfg.throttle_mode = DDYN_CTRL_THROTTLE_PID a PID on the speed error (the raceline table's
 *      speed at the car's projection minus the estimated vx) sets the throttle, with anti-windup
 *      and the throttle's range and rate bounds, and the MPC plans the steering alone with the
 *      throttle held at the PID's value over its horizon (ddyn_mpc_solve_held_throttle);
 *   5. command: the MPC's input, or the shifted previous plan while the QP does not converge
 *      (a bounded number of periods), or the SAFE COMMAND.
 *
 * Every check that fails sets a bit of the returned status (several at once), nothing returns
 * garbage: the command is always finite. The SAFE COMMAND holds the steering (dsteering = 0)
 * and drives the throttle state to a target as fast as the rate bound allows,
 * dthrottle = clamp((target - throttle) / dt, rate_lo, rate_hi): while the estimated vx is above
 * safe_stop_speed the target is the braking value (the throttle state's lower bound); below it,
 * the throttle that holds the car at standstill in the model, Cr0 / Cm1 of the nominal
 * coefficients (the model has no brake: a negative throttle at standstill drives backwards).
 * Safe mode latches: it is left only after `recovery_steps` consecutive periods without a
 * safe-mode cause (DDYN_CTRL_RECOVERED marks the period), and the MPC then restarts cold.
 *
 * Embedded rules: C99, everything in the caller-owned ddyn_ctrl (no allocation, no recursion,
 * no VLAs, loops bounded by compile-time sizes). One context per controller; not thread-safe.
 * The guard-network shape comes from the export the library is built for (ddyn_net_config.h).
 */
#ifndef DDYN_CONTROLLER_H
#define DDYN_CONTROLLER_H

#include <stdint.h>

#include "ddyn/ekf.h"
#include "ddyn/guard_net.h"
#include "ddyn/model.h"
#include "ddyn/mpc.h"

#ifdef __cplusplus
extern "C" {
#endif

#if DDYN_NET_NOUT != DDYN_NC
#error "the controller needs a guard network with all 17 coefficients (a DDM export)"
#endif

/* Status bits of one period (ddyn_ctrl_step's return value and ddyn_ctrl_output.status). */
#define DDYN_CTRL_OK 0u
#define DDYN_CTRL_ERR_ARGUMENT (1ul << 0)      /* null pointer, or context not initialised: u = {0, 0} */
#define DDYN_CTRL_MEAS_NONFINITE (1ul << 1)    /* a reading held NaN/inf: rejected and counted */
#define DDYN_CTRL_MEAS_REJECTED (1ul << 2)     /* a finite reading outside the innovation gate, or refused
                                                  by the EKF (innovation not PD): not fused, counted */
#define DDYN_CTRL_SENSOR_FAULT (1ul << 3)      /* a sensor failed max_sensor_faults readings in a row: safe */
#define DDYN_CTRL_NO_MEASUREMENTS (1ul << 4)   /* no reading fused for more than max_blind_steps: safe */
#define DDYN_CTRL_HISTORY_FILLING (1ul << 5)   /* fewer than DDYN_NET_TAU rows yet: nominal coefficients */
#define DDYN_CTRL_OUT_OF_RANGE (1ul << 6)      /* history outside the network's training range: fallback */
#define DDYN_CTRL_NET_FAULT (1ul << 7)         /* the guard network's output was not finite: fallback */
#define DDYN_CTRL_COEFF_LAST_GOOD (1ul << 8)   /* the MPC and EKF use the last good coefficients */
#define DDYN_CTRL_COEFF_NOMINAL (1ul << 9)     /* the MPC and EKF use the vehicle's nominal coefficients */
#define DDYN_CTRL_EKF_DIVERGED (1ul << 10)     /* covariance blow-up, failed prediction, or a sensor gated
                                                  max_sensor_faults times in a row: filter reset, safe */
#define DDYN_CTRL_MPC_NOT_CONVERGED (1ul << 11) /* the QP hit its iteration cap */
#define DDYN_CTRL_MPC_FAILED (1ul << 12)       /* the MPC returned another error (not ready, model failure) */
#define DDYN_CTRL_PLAN_SHIFTED (1ul << 13)     /* command taken from the last converged plan, shifted */
#define DDYN_CTRL_SAFE_COMMAND (1ul << 14)     /* the command is the safe command */
#define DDYN_CTRL_RECOVERED (1ul << 15)        /* safe mode left this period */
#define DDYN_CTRL_COEFF_FIXED (1ul << 16)      /* coeff_source FIXED: the MPC and EKF use cfg.c_fixed; the
                                                  network is not run (every period of such a controller) */
#define DDYN_CTRL_PID_SATURATED (1ul << 17)    /* throttle PID: the throttle's range or rate bound cut the
                                                  PID's output; the integral is held (anti-windup) */
#define DDYN_CTRL_BUS_DEGRADED (1ul << 18)   /* degraded-bus mode (ddyn_ctrl_degraded_config): the bus lost,
                                                  refused or delayed frames recently; heavier input-rate
                                                  weights, slower reference, inflated R, aged readings
                                                  moved to the period's time */
#define DDYN_CTRL_BUS_RECOVERED (1ul << 19)  /* degraded-bus mode left this period (recovery_periods clean) */
#define DDYN_CTRL_STATUS_BITS 20

typedef uint32_t ddyn_ctrl_status;

/* Where the coefficients of each period come from. */
typedef enum {
    DDYN_CTRL_SOURCE_NETWORK = 0, /* default: the guard network, with the fallbacks last good / nominal */
    DDYN_CTRL_SOURCE_FIXED = 1,   /* cfg.c_fixed every period, the network never run (its tables are
                                     optional at init); status DDYN_CTRL_COEFF_FIXED */
    DDYN_CTRL_SOURCE_COUNT = 2
} ddyn_ctrl_coeff_source;

/* Who commands the throttle. */
typedef enum {
    DDYN_CTRL_THROTTLE_MPC = 0, /* default: the MPC plans throttle and steering rates */
    DDYN_CTRL_THROTTLE_PID = 1, /* a PID on the speed error sets the throttle; the MPC plans the steering
                                   with that throttle held over its horizon (the Deep Dynamics paper's
                                   set-up for the DPM, whose model has no drivetrain law) */
    DDYN_CTRL_THROTTLE_MODE_COUNT = 2
} ddyn_ctrl_throttle_mode;

/* The throttle PID (throttle_mode PID). Each period, e = v_ref - vx with v_ref the raceline table's
 * speed `preview * vx` metres ahead of the projection of the estimate (a PID that reads the speed at
 * the car brakes only once it is in the corner) and vx the estimate:
 *   T* = clamp(kp e + I - kd dvx/dt, throttle bounds)         (derivative on the estimate, not e)
 *   dthrottle = clamp((T* - throttle) / dt, rate bounds)       (the command: the input is a rate)
 *   I += ki e dt  unless the applied throttle (throttle + dt dthrottle) falls short of the
 *                 unclamped output in the direction e pushes (conditional integration), I kept
 *                 within the throttle bounds.
 * I starts at 0, and restarts at 0 when safe mode ends. */
typedef struct {
    double kp;  /* throttle per m/s of speed error (>= 0) */
    double ki;  /* throttle per m/s of speed error and second (>= 0) */
    double kd;  /* throttle per m/s^2 of the estimated acceleration (>= 0) */
    double preview; /* s (>= 0): the reference speed is read this many seconds ahead at the car's speed */
} ddyn_ctrl_pid_config;

/* Degraded-bus mode (docs/controller.md#degraded-bus-mode). A period is FAULTY when the caller reports
 * bus faults (ddyn_ctrl_input.bus_faults: frames lost, late, repeated or refused since the last period)
 * or a reading older than age_tolerance relative to the period's time. A faulty period enters the mode
 * at once; recovery_periods consecutive clean periods leave it (hysteresis: DDYN_CTRL_BUS_RECOVERED).
 * While degraded: every reading's measurement noise std is scaled by r_scale, the MPC's input-rate
 * weights by rate_weight_scale and its reference speed by speed_scale, and the caller's frame-silence
 * limit may grow by stale_extra_periods (ddyn_ctrl_stale_limit). In every mode, a reading of age a
 * (relative to the period's time, at most max_age) is moved to the period's time with the filter's own
 * trajectory, z += h(x_now) - h(x(now - a)), and the MPC starts from the estimate predicted over the
 * input's latency with the model (bounded by max_age). Defaults: ddyn_ctrl_default_config. */
typedef struct {
    double age_tolerance;    /* s (>= 0): an older reading makes the period faulty */
    double max_age;          /* s (>= 0): older readings are not fused (counted as rejected), and the
                                latency prediction is cut here; at most DDYN_CTRL_AGE_PERIODS periods */
    int recovery_periods;    /* >= 1 */
    double r_scale;          /* >= 1 */
    double rate_weight_scale; /* >= 1 */
    double speed_scale;      /* (0, 1] */
    int stale_extra_periods; /* >= 0 */
} ddyn_ctrl_degraded_config;

/* estimates kept to date aged readings (periods) */
#define DDYN_CTRL_AGE_PERIODS 4

/* Known actuation delays (docs/sil.md "Actuation delays"). A set-point sent now acts on the car `delay`
 * seconds later (the steering and the throttle each with its own delay, as the SIL plant's steer_delay,
 * throttle_delay). The controller keeps the commands it has sent (one delay line per input channel,
 * ddyn_ctrl_delay_line) and
 *   - predicts the filter over each period with the command that acts on the car in it, the one sent
 *     delay ago (also the history row of the guard network: the input that acted);
 *   - before the MPC, predicts the estimate through the commands still in the pipe (sent, not yet acting)
 *     with the filter's model step (ddyn_ctrl_predict_pipe), so that the MPC plans from the state at
 *     which its new command takes effect.
 * A delay counts in whole control periods, to the NEAREST: n = floor(delay / sample_time + 1/2) (a half
 * period and 1e-6 of one rounds up: 30 ms at 20 ms periods is 2): with a fast actuator, at the end of a
 * period the car holds the set-point sent n periods before, and a delay between n - 1/2 and n + 1/2
 * periods is closest to that (until issue 34 the count was floor(delay / sample_time): 39 ms acted as 1
 * period, and a diagnosis's estimate a few per cent short of a whole period lost one). Both delays
 * 0 (the default) is the controller without this: bit-identical.
 * The MPC plans from the state at which its STEERING command takes effect (n = the steering delay: the
 * steering keeps the car within the track bounds). Over that prediction the throttle runs its commands
 * still in the pipe (a shorter throttle delay: held back to the steering's, below); with a longer one,
 * its commands still in the pipe beyond that point are not
 * in the MPC's plan (the QP cannot fix stages of an input), and its planned ones act later than it
 * thinks. (Measured in the SIL on ETHZMobil, docs/sil.md "Actuation delays": continuing a shorter
 * channel with the last plan's commands instead of holding it failed 3 of 4 noise seeds of the 40 ms
 * steering delay; planning from the later channel's time (n = max) put the throttle-delay-only laps off
 * the track in 4 of 4. A throttle delay is compensated in the filter and the pipe only: with a
 * throttle delay alone the compensated laps are no better than the uncompensated ones.)
 * A THROTTLE DELAY SHORTER THAN THE STEERING'S (e.g. none, with a steering delay) is held back to the
 * steering's (issue 34, docs/sil.md "Why 80 ms left the track"): the throttle command the MPC plans now
 * goes out h = n_steer - n_throttle periods later (the ring ctl->thr_queue), so that it acts at the MPC's
 * stage 0, as its steering does; the pipe runs the held-back commands (known: planned, not yet sent)
 * instead of holding the throttle. The closed loop is then exactly that of a throttle delayed as much
 * as the steering (the pipe's prediction has no unknown input). Without it the pipe's throttle was
 * 0.29 (rms) off the plant's at 80 ms and the MPC's throttle acted 80 ms before it planned it to: with
 * the 80 ms steering delay told, 3 of 4 seeds on ETHZMobil had violations (2 left the track). The safe command goes out at once
 * (the queue is then emptied to holds, u = 0).
 * THE PLAN ENDS WHERE IT WOULD WITHOUT THE DELAY: with a steering delay of n periods the MPC's horizon is
 * cfg.mpc.horizon - n stages (its first stage is n periods ahead), so that the plan looks as far ahead in
 * time as the horizon it was tuned with (a config whose max_plan_shift is not below that is refused).
 * Chosen in the SIL with the true delay told (docs/sil.md "Actuation delays"), on ETHZMobil and
 * random:303-305 at noise seeds 1 and 2: 24 of 24 laps with 40-80 ms clean and within 2 % of no delay
 * (results/sil_oracle.json), against 22 of 24 clean with the full horizon (runs before this rule, a
 * hand-edited horizon; no command of today's build gives that arm); scored on the held-out random:301
 * and :302 (results/sil_loop.json).
 * The compiled maximum (override with -DDDYN_CTRL_MAX_DELAY_STEPS=...): 6 periods = 120 ms at the 1:43
 * car's 50 Hz, 240 ms at the AV-21's 25 Hz (5 until issue 34's 120 ms throttle delay). A delay that rounds to more than DDYN_CTRL_MAX_DELAY_STEPS
 * periods is refused at init (DDYN_ERR_ARGUMENT), never cut. */
#ifndef DDYN_CTRL_MAX_DELAY_STEPS
#define DDYN_CTRL_MAX_DELAY_STEPS 6
#endif
#if DDYN_CTRL_MAX_DELAY_STEPS < 1
#error "DDYN_CTRL_MAX_DELAY_STEPS must be at least 1"
#endif
/* input channels of the delay lines: the order of u (ddyn/model.h) */
#define DDYN_CTRL_CH_THROTTLE 0
#define DDYN_CTRL_CH_STEERING 1

typedef struct {
    double steering; /* s (>= 0): the steering set-point acts this long after it was sent (default 0) */
    double throttle; /* s (>= 0): the same for the throttle (default 0) */
} ddyn_ctrl_delay_config;

/* The commands of one channel sent in the last DDYN_CTRL_MAX_DELAY_STEPS + 1 periods: a ring, newest
 * at `newest`. Fixed size, no allocation. */
typedef struct {
    double u[DDYN_CTRL_MAX_DELAY_STEPS + 1];
    int newest; /* 0 .. DDYN_CTRL_MAX_DELAY_STEPS */
} ddyn_ctrl_delay_line;

/* Every entry u0 (commands "since forever"), newest at 0. */
void ddyn_ctrl_delay_line_reset(ddyn_ctrl_delay_line *d, double u0);
/* A command sent now: it becomes the newest, the oldest drops out. */
void ddyn_ctrl_delay_line_push(ddyn_ctrl_delay_line *d, double u);
/* Replace the newest command (the caller sent another one than the controller's). */
void ddyn_ctrl_delay_line_set_newest(ddyn_ctrl_delay_line *d, double u);
/* The command sent n periods before the newest (n = 0: the newest), 0 <= n <= DDYN_CTRL_MAX_DELAY_STEPS;
 * NaN for any other n (never another entry). */
double ddyn_ctrl_delay_line_ago(const ddyn_ctrl_delay_line *d, int n);
/* The delays of cfg in whole periods of dt, rounded to the nearest (steps[DDYN_CTRL_CH_THROTTLE],
 * steps[DDYN_CTRL_CH_STEERING]): DDYN_OK, or DDYN_ERR_ARGUMENT (steps untouched) for a negative, non-finite
 * one or one that rounds to more than DDYN_CTRL_MAX_DELAY_STEPS periods. */
ddyn_status ddyn_ctrl_delay_steps(const ddyn_ctrl_delay_config *cfg, double dt, int steps[DDYN_NU]);

/* A known MASS OFFSET (the SIL plant's mass_offset, a diagnosis's mass_offset): the car's mass is
 * (1 + mass_offset) times the model's, its yaw inertia and axle distances unchanged. The model's forces
 * are linear in the coefficients DDYN_CTRL_MASS_SCALED (each axle's Pacejka D and K; Cm1, Cm2, Cr0, Cd)
 * for the drivetrain of the papers (and the power-limited one), and the rigid body divides them by the
 * mass and the yaw moment by Iz; so the coefficients with those and Iz divided by (1 + mass_offset) are
 * exactly the car with that mass: dvx and dvy's force parts scaled, domega unchanged (the SIL plant's
 * mass_offset, train/model/effects.py). The controller applies it to every coefficient set it uses
 * (fixed, the network's, the last good, the nominal) before the filter, the pipe and the MPC; the
 * accelerometer's model, force / mass, then reads the heavier car too. Not exact for a drivetrain with
 * a known brake gain (the "powertrain" forms: its braking force is a constant of the generated model,
 * not scaled). Range [-0.5, 1]; 0 (the default) leaves the coefficients bit-identical.
 * The LINE: every acceleration the heavier car can make (its tyres', its drivetrain's, its drag's) is
 * 1 / (1 + offset) of the model's, so on the line's path its fastest speeds are the line's times
 * 1 / sqrt(1 + offset) (v^2 = a / curvature in the turns, v^2 changing by 2 a ds on the straights): with
 * a positive offset the MPC's reference speed is scaled by that (times the degraded mode's scale). A
 * lighter car keeps the line's speeds (the line was made for the model's car; not driven faster). */
#define DDYN_CTRL_MASS_SCALED {2, 5, 8, 11, 12, 13, 14, 15, 16}
#define DDYN_CTRL_MASS_SCALED_COUNT 9
#define DDYN_CTRL_MASS_OFFSET_MIN (-0.5)
#define DDYN_CTRL_MASS_OFFSET_MAX 1.0
/* c scaled in place for a mass (1 + mass_offset) times the model's (above). */
void ddyn_ctrl_mass_scale(double c[DDYN_NC], double mass_offset);

/* A known first-order STEERING LAG (docs/sil.md "Steering lag"; the SIL plant's steer_lag): the steering
 * angle acting on the car follows the set-point acting (the one sent, after the steering delay) as
 *   d(delta)/dt = (delta_cmd - delta) / tau,
 * the set-point held over each period (the drive-by-wire node integrates the rates: the set-point of a
 * period is the one before plus period * the steering rate, within the steering state's bounds
 * cfg.mpc.state_lo/hi). The controller keeps its own estimate of the acting angle, the lag integrated
 * exactly over each period (a zero-order hold, ddyn_ctrl_lag_step):
 *   delta_{k+1} = cmd_{k+1} + (delta_k - cmd_{k+1}) e^{-dt / tau}
 * from the set-points of the commands it sent (after any delay; a caller's ddyn_ctrl_command_applied and
 * _not_sent reach it), and
 *   - the filter predicts each period, and the guard network's history row holds, the ACTING steering
 *     rate (delta_{k+1} - delta_k) / dt instead of the rate sent;
 *   - the prediction through the pipe (ddyn_ctrl_predict_pipe) runs the same lag, so that the MPC plans
 *     from the state its new command acts in;
 *   - the MPC's first steering rate u (its planned acting angle delta + dt u at the end of the period in
 *     which the new command acts, delta the estimate then) is inverted through the discretised lag: the
 *     set-point that reaches it is cmd = delta + dt u / (1 - e^{-dt / tau}) (ddyn_ctrl_lag_invert),
 *     clipped to the steering state's bounds, and the rate sent is (cmd - the newest set-point) / dt,
 *     clipped to the steering rate bounds. The MPC's later stages are planned without the lag (its
 *     model has no actuator state; it replans every period from the lagged state).
 * tau = 0 (the default): no lag, the controller as before, bit-identical. The safe command holds the
 * set-point (u = 0), not inverted. */
typedef struct {
    double steering; /* s (>= 0, finite, e^{-dt/tau} < 1 in doubles): the lag's time constant tau (default 0:
                        none); refused at init otherwise (DDYN_ERR_ARGUMENT) */
} ddyn_ctrl_lag_config;

/* e^{-dt / tau} for tau > 0, 0 for tau = 0 (no lag); NaN for a negative or non-finite tau or dt <= 0. */
double ddyn_ctrl_lag_decay(double tau, double dt);
/* The acting angle one period on: cmd + (delta - cmd) * decay (decay = ddyn_ctrl_lag_decay). */
double ddyn_ctrl_lag_step(double delta, double cmd, double decay);
/* The set-point that takes the acting angle from delta to target in one period: the inverse of
 * ddyn_ctrl_lag_step in cmd, delta + (target - delta) / (1 - decay) (unclipped; decay in [0, 1)). */
double ddyn_ctrl_lag_invert(double delta, double target, double decay);

typedef struct {
    ddyn_discretisation ekf_disc; /* the filter's prediction model (default Euler, as the network trains) */
    /* EKF: initial covariance (also used when the filter is reset), process noise per period,
     * measurement noise variance per sensor kind and component */
    double p0_diag[DDYN_NX];
    double q_diag[DDYN_NX];
    double r_diag[DDYN_MEAS_COUNT][DDYN_MEAS_MAX_DIM];
    /* covariance blow-up: the filter has diverged when a variance P_ii exceeds p_max[i] */
    double p_max[DDYN_NX];
    /* innovation gate: a reading whose normalised innovation squared exceeds it is not fused
     * (INFINITY: no gate) */
    double nis_gate;
    /* the vehicle's nominal coefficients (COEFF_NAMES order): the fallback of last resort, and the
     * safe command's standstill throttle */
    double c_nominal[DDYN_NC];
    ddyn_ctrl_coeff_source coeff_source; /* default DDYN_CTRL_SOURCE_NETWORK */
    double c_fixed[DDYN_NC];             /* the coefficients of DDYN_CTRL_SOURCE_FIXED (ignored otherwise) */
    ddyn_ctrl_throttle_mode throttle_mode; /* default DDYN_CTRL_THROTTLE_MPC */
    ddyn_ctrl_pid_config pid;              /* gains of DDYN_CTRL_THROTTLE_PID (defaults: docs/controller.md) */
    /* a history state feature (vx, vy, omega, throttle, steering) is out of range when
     * |f - mean| > range_sigmas * std of the network's input normalisation (the training data's
     * statistics, exported with the weights) */
    double range_sigmas;
    double safe_stop_speed; /* m/s: below it the safe command holds the car instead of braking */
    int max_coeff_age;      /* periods the last good coefficients stay usable, then nominal */
    int max_sensor_faults;  /* consecutive rejected readings of one sensor before safe mode (>= 1) */
    int max_blind_steps;    /* consecutive periods without a fused reading before safe mode (>= 1) */
    int max_plan_shift;     /* periods the shifted plan replaces a non-converged QP, then safe
                               (0 .. horizon - 1, the horizon less the steering delay's periods) */
    int recovery_steps;     /* consecutive healthy periods that end safe mode (>= 1) */
    ddyn_ctrl_degraded_config degraded; /* degraded-bus mode (above) */
    ddyn_ctrl_delay_config delay; /* known actuation delays (above; default 0: none) */
    ddyn_ctrl_lag_config lag;     /* known steering lag (above; default 0: none) */
    double mass_offset;           /* known mass offset (DDYN_CTRL_MASS_SCALED; default 0: none) */
    double downforce;             /* known downforce k (s^2/m^2, 0..DDYN_MODEL_DOWNFORCE_MAX; default 0: none):
                                     the filter, the pipe and each MPC stage use the coefficients of their
                                     own state's speed, D_f and D_r times 1 + k vx^2 (ddyn_model_downforce),
                                     after the mass offset; the line's speeds are not raised */
    ddyn_mpc_config mpc;    /* the MPC's configuration (its bounds also define the safe command) */
} ddyn_ctrl_config;

/* One reading per sensor kind; valid = 1 when a new reading arrived this period. */
typedef struct {
    int valid;
    double z[DDYN_MEAS_MAX_DIM]; /* ddyn_meas_dim(kind) components */
    double age; /* s (>= 0): how much older the reading is than the freshest data on the bus (its frame's
                   age, ddyn_dbw_link); 0 = fresh. A zeroed input means fresh readings. */
} ddyn_ctrl_reading;

typedef struct {
    ddyn_ctrl_reading reading[DDYN_MEAS_COUNT]; /* indexed by ddyn_meas_kind */
    /* the period's time relative to the bus (s, >= 0): how much older the period's own time is than the
     * freshest data, i.e. how late this period's command goes out (the age of the frame that triggered
     * it). A reading's age relative to the period is age - latency (a fresher one counts as current). */
    double latency;
    uint32_t bus_faults; /* frames lost, late, repeated or refused since the last period (ddyn_dbw_link) */
} ddyn_ctrl_input;

typedef struct {
    double u[DDYN_NU];          /* the command to apply now: dthrottle, dsteering (always finite) */
    ddyn_ctrl_status status;    /* bits DDYN_CTRL_* of this period */
    double x_est[DDYN_NX];      /* the filter's estimate after this period's readings */
    double coeffs[DDYN_NC];     /* the coefficients used this period */
    ddyn_status mpc_status;     /* what ddyn_mpc_solve returned */
    ddyn_mpc_info mpc_info;
    /* throttle PID (0 in MPC mode): reference speed v_ref, the PID's throttle target T* (clamped), its
     * integral term I after this period */
    double pid_ref_speed, pid_throttle, pid_integral;
    /* the state the MPC planned from: the estimate predicted through the commands in the pipe (the
     * actuation delays) and over the input's latency; x_est without either */
    double x_mpc0[DDYN_NX];
} ddyn_ctrl_output;

/* The caller-owned controller context (large: it holds the MPC; ~155 kB with the defaults). */
typedef struct {
    ddyn_ctrl_config cfg;
    const ddyn_vehicle_model *model;
    ddyn_ekf ekf;
    ddyn_guard_net net;
    ddyn_mpc mpc;
    double history[DDYN_NET_TAU][DDYN_NET_NFEAT]; /* oldest row first */
    int history_rows;                             /* 0 .. DDYN_NET_TAU */
    double coeffs[DDYN_NC];                       /* used this period */
    double last_good[DDYN_NC];                    /* the network's last accepted output */
    int last_good_age;                            /* periods since it was computed; -1: none yet */
    double plan_u[DDYN_MPC_NV];                   /* last converged plan, stage-major */
    int plan_horizon;                             /* its horizon; 0: none */
    int plan_age;                                 /* periods since it was computed */
    double x_prev[DDYN_NX];                       /* estimate at the end of the previous period */
    double u_prev[DDYN_NU];                       /* command applied from it */
    int started;                                  /* 0 before the first period */
    int sensor_fault_run[DDYN_MEAS_COUNT];        /* consecutive rejected readings per sensor */
    uint32_t nonfinite_count[DDYN_MEAS_COUNT];    /* NaN/inf readings rejected since init (saturating) */
    uint32_t rejected_count[DDYN_MEAS_COUNT];     /* finite readings the EKF refused (saturating) */
    int blind_steps;                              /* consecutive periods without a fused reading */
    int safe_mode;
    int healthy_steps;                            /* consecutive periods without a safe-mode cause */
    double pid_integral;                          /* throttle PID: integral term I (throttle units) */
    double pid_vx_prev;                           /* estimated vx of the PID's previous period */
    int pid_started;                              /* 0: no previous period (derivative 0) */
    int degraded;                                 /* degraded-bus mode */
    int clean_periods;                            /* consecutive periods without a bus fault */
    uint32_t degraded_periods;                    /* periods in degraded mode since init (saturating) */
    double x_hist[DDYN_CTRL_AGE_PERIODS][DDYN_NX]; /* estimates at the end of the last periods, newest first */
    int x_hist_n;                                 /* valid rows of x_hist */
    /* actuation delays: the commands sent, per channel (newest = u_prev, synchronised from it at each
     * step and preparation, so that a caller's ddyn_ctrl_command_applied reaches them), the delays in
     * periods, and the command acting on the car over the period just predicted */
    ddyn_ctrl_delay_line sent[DDYN_NU];
    int delay_steps[DDYN_NU];
    double u_acting[DDYN_NU];
    /* a throttle delay shorter than the steering's: the throttle commands held back (thr_hold = the
     * difference in periods, 0 otherwise), oldest first: thr_queue[0] goes out next period */
    double thr_queue[DDYN_CTRL_MAX_DELAY_STEPS];
    int thr_hold;
    /* steering lag: e^{-dt/tau} (0: none); the set-point acting and the acting angle at the start of the
     * period being run (lag_cmd, lag_act: committed at each step) and at its end (lag_cmd_next,
     * lag_act_next: from the command acting over it, recomputed at each synchronisation) */
    double lag_decay;
    double lag_cmd, lag_act, lag_cmd_next, lag_act_next;
    int bank_hint; /* the road's bank: the raceline segment of its last lookup (-1: search every one) */
    double mass_speed_scale; /* the line's speeds for the known mass offset (1: none or a lighter car) */
    int initialised;
} ddyn_ctrl;

/* Defaults for a vehicle model: the MPC's defaults (ddyn_mpc_default_config), the fault limits
 * documented in docs/controller.md; p0/q/r/p_max/c_nominal are set to generic values the caller
 * should overwrite with the car's (nominal coefficients: the vehicle file's). */
ddyn_status ddyn_ctrl_default_config(const ddyn_vehicle_model *model, ddyn_ctrl_config *cfg);

/* Check cfg, validate the network tables (ddyn_guard_net_init) and set up the filter at x0.
 * Returns DDYN_ERR_ARGUMENT for a bad configuration, and the network's own error for tables the
 * library was not built for (DDYN_ERR_NET_MAGIC, _SHAPE, _HASH, _NORMALISATION).
 * With cfg->coeff_source = DDYN_CTRL_SOURCE_FIXED, tables may be NULL (given, they are still checked). */
ddyn_status ddyn_ctrl_init(ddyn_ctrl *ctl, const ddyn_vehicle_model *model, const ddyn_net_tables *tables,
                           const ddyn_ctrl_config *cfg, const double x0[DDYN_NX]);

/* The raceline the MPC tracks (ddyn_mpc_set_track). */
ddyn_status ddyn_ctrl_set_track(ddyn_ctrl *ctl, int n, const double *x, const double *y, const double *speed,
                                const double *width_left, const double *width_right);

/* The road's bank along the raceline (issue 34; controller.json control.bank): bank[i] (rad, + tilting the
 * road so that gravity pulls to the left) at each point of the track set last, in the MPC's fixed-size
 * table (ddyn_mpc_set_bank: |bank| < DDYN_MPC_MAX_BANK, single-step RK4 prediction). With it the MPC
 * predicts each stage with the bank at that stage's track position (the generated step's road input (bank, grade)),
 * and the filter's prediction, the preparation's and the pipe's steps add the bank's lateral gravity
 * at the state's position (ddyn_model_add_bank; the position projected on the raceline). NULL: a flat
 * road (the default: the controller as before, bit-identical). Call after ddyn_ctrl_set_track. */
ddyn_status ddyn_ctrl_set_bank(ddyn_ctrl *ctl, const double *bank);

/* The road's grade along the raceline (issue 34; controller.json control.grade): grade[i] (rad, + uphill in the
 * direction of travel, |grade| < DDYN_MPC_MAX_GRADE) at each point of the track set last, as the bank's: the MPC
 * predicts each stage with the grade at its track position (ddyn_mpc_set_grade), the filter's prediction, the
 * preparation's and the pipe's steps add its longitudinal gravity at the state's position
 * (ddyn_model_add_grade). NULL: a level road. Refusals as ddyn_ctrl_set_bank's. */
ddyn_status ddyn_ctrl_set_grade(ddyn_ctrl *ctl, const double *grade);

/* One control period: readings in, command out. Returns out->status (also when out is NULL:
 * DDYN_CTRL_ERR_ARGUMENT). in may hold no valid reading at all. */
ddyn_ctrl_status ddyn_ctrl_step(ddyn_ctrl *ctl, const ddyn_ctrl_input *in, ddyn_ctrl_output *out);

/* The MPC's preparation phase for the next period (ddyn_mpc_prepare), to call after the command of
 * ddyn_ctrl_step has been sent and before the next readings arrive: the next state is predicted
 * from the estimate with the command just sent, and the MPC linearises, builds its QP and the
 * state sensitivities there. The next ddyn_ctrl_step then only moves the QP to the measured state
 * and solves it (ddyn_mpc_feedback): the measurement-to-command latency no longer includes the
 * model evaluations along the horizon. Without it, ddyn_ctrl_step does the whole iteration.
 * DDYN_ERR_NOT_READY in safe mode or with the PID throttle (its held-throttle QP needs the PID's
 * output of the next period), DDYN_ERR_ARGUMENT before the first step; the next step then does
 * the whole iteration. */
ddyn_status ddyn_ctrl_prepare(ddyn_ctrl *ctl);

/* The state x of the car when the next command goes out (one period after the newest command sent:
 * ddyn_ctrl_step's estimate before its MPC, ddyn_ctrl_prepare's predicted state) predicted on through
 * the commands still in the pipe (sent, not yet acting: the actuation delays), n model
 * steps (n = the steering delay, above) of the filter's discretisation (cfg.ekf_disc) with the current
 * coefficients; step i runs each channel's command sent delay - 1 - i periods before the newest
 * (ddyn_ctrl_delay_line_ago), a channel whose delay is shorter than i + 1 held (0); with a steering
 * lag the steering runs the acting rate of the lag from the acting angle of the last step (lag_act).
 * No steering delay: x_out = x. On a model failure returns its error with x_out = x. */
ddyn_status ddyn_ctrl_predict_pipe(ddyn_ctrl *ctl, const double x[DDYN_NX], double x_out[DDYN_NX]);

/* The last command of ddyn_ctrl_step never reached the actuators (e.g. a period run late to catch up
 * with lost trigger frames, whose command is not sent): the filter's next prediction holds throttle and
 * steering (u = 0), as the actuators did. */
void ddyn_ctrl_command_not_sent(ddyn_ctrl *ctl);

/* The caller sent another command than ddyn_ctrl_step's (e.g. its own safe command for a silent
 * frame): the filter's next prediction uses u, what the actuators got. Non-finite u is ignored. */
void ddyn_ctrl_command_applied(ddyn_ctrl *ctl, const double u[DDYN_NU]);

/* The frame-silence limit (periods) a caller's monitor should use for a frame normally allowed
 * `base` periods: base, plus cfg.degraded.stale_extra_periods while in degraded-bus mode. */
int ddyn_ctrl_stale_limit(const ddyn_ctrl *ctl, int base);

/* The safe command in state x under cfg's bounds and the model's sample time (see the top). */
void ddyn_ctrl_safe_command(const ddyn_ctrl *ctl, const double x[DDYN_NX], double u[DDYN_NU]);

/* Name of one status bit (e.g. "DDYN_CTRL_SAFE_COMMAND"), or "DDYN_CTRL_UNKNOWN". */
const char *ddyn_ctrl_status_name(ddyn_ctrl_status bit);

#ifdef __cplusplus
}
#endif

#endif /* DDYN_CONTROLLER_H */
