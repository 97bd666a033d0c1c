/* One control period: EKF -> history -> guard network -> MPC -> command, with defined fallbacks
 * (see ddyn/controller.h and docs/controller.md for the policy). */
#include "ddyn/controller.h"

#include <math.h>
#include <stddef.h>
#include <string.h>

#define NX DDYN_NX
#define NU DDYN_NU
#define NC DDYN_NC
#define TAU DDYN_NET_TAU
#define NFEAT DDYN_NET_NFEAT

/* state indices of the history features vx, vy, omega, throttle, steering (train/data/windows.py) */
#define FIRST_FEATURE_STATE 3
#define VX 3
#define THROTTLE 6
#define STEERING 7
#define CM1 12
#define CR0 14
/* the model's coefficient order (ddyn/model.h, train/model/single_track.py COEFF_NAMES) */
#define COEFF_ORDER "Bf,Cf,Df,Ef,Gf,Kf,Br,Cr,Dr,Er,Gr,Kr,Cm1,Cm2,Cr0,Cd,Iz"
/* default throttle PID gains: `ddyn sil pid-sweep` on the true-coefficient SIL lap (docs/sil.md) */
#define PID_DEFAULT_KP 2.0
#define PID_DEFAULT_KI 0.5
#define PID_DEFAULT_KD 0.0
#define PID_DEFAULT_PREVIEW 0.2

static double clamp(double v, double lo, double hi)
{
    return v < lo ? lo : (v > hi ? hi : v);
}

static uint32_t saturating_increment(uint32_t v)
{
    return v == UINT32_MAX ? v : v + 1u;
}

ddyn_status ddyn_ctrl_default_config(const ddyn_vehicle_model *model, ddyn_ctrl_config *cfg)
{
    static const double p0[NX] = {1e-2, 1e-2, 1e-2, 1e-2, 1e-2, 1e-2, 1e-6, 1e-6};
    static const double q[NX] = {1e-8, 1e-8, 1e-8, 1e-6, 1e-6, 1e-4, 1e-12, 1e-12};
    int i, k;
    ddyn_status s;
    if (model == NULL || cfg == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    memset(cfg, 0, sizeof *cfg);
    s = ddyn_mpc_default_config(model, &cfg->mpc);
    if (s != DDYN_OK) {
        return s;
    }
    cfg->ekf_disc = DDYN_DISC_RK4; /* Euler at the 1:43 car's 20 ms is unstable in vy below ~1 m/s */
    for (i = 0; i < NX; ++i) {
        cfg->p0_diag[i] = p0[i];
        cfg->q_diag[i] = q[i];
        cfg->p_max[i] = 1e4 * p0[i]; /* a hundred times the initial standard deviation */
    }
    for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
        for (i = 0; i < DDYN_MEAS_MAX_DIM; ++i) {
            cfg->r_diag[k][i] = 1e-2;
        }
    }
    /* no generic coefficients exist: c_nominal stays 0 so that init refuses a config without them */
    cfg->range_sigmas = 6.0;
    cfg->nis_gate = 100.0; /* a 10-sigma innovation of a scalar reading */
    cfg->safe_stop_speed = 10.0 * model->known[3]; /* ten times the model's low-speed floor v_min */
    cfg->max_coeff_age = 50;
    cfg->max_sensor_faults = 5;
    cfg->max_blind_steps = 25;
    cfg->max_plan_shift = 3;
    cfg->recovery_steps = 10;
    /* degraded-bus mode (docs/controller.md#degraded-bus-mode): the multipliers were chosen on the SIL's
     * delayed-frame scenario with in-process runs (its noise seed 1) and scored on the fault table in
     * the qemu guest; recovery after one clean second */
    cfg->degraded.age_tolerance = model->sample_time;
    cfg->degraded.max_age = 3.0 * model->sample_time;
    cfg->degraded.recovery_periods = 50;
    cfg->degraded.r_scale = 3.0;
    cfg->degraded.rate_weight_scale = 1.0;
    cfg->degraded.speed_scale = 1.0;
    cfg->degraded.stale_extra_periods = 2;
    cfg->coeff_source = DDYN_CTRL_SOURCE_NETWORK;
    cfg->throttle_mode = DDYN_CTRL_THROTTLE_MPC;
    /* throttle PID gains (PID_DEFAULT_*: see their definition) */
    cfg->pid.kp = PID_DEFAULT_KP;
    cfg->pid.ki = PID_DEFAULT_KI;
    cfg->pid.kd = PID_DEFAULT_KD;
    cfg->pid.preview = PID_DEFAULT_PREVIEW;
    return DDYN_OK;
}

/* coefficients the model can step with: finite, a positive drive (Cm1) and inertia (Iz = 0 would not) */
static int coefficients_usable(const double c[NC])
{
    return ddyn_all_finite(c, NC) && c[CM1] > 0.0 && c[NC - 1] > 0.0;
}

/* ---- actuation delays (ddyn_ctrl_delay_config) ---- */

#define DELAY_RING (DDYN_CTRL_MAX_DELAY_STEPS + 1)

void ddyn_ctrl_delay_line_reset(ddyn_ctrl_delay_line *d, double u0)
{
    int i;
    for (i = 0; i < DELAY_RING; ++i) {
        d->u[i] = u0;
    }
    d->newest = 0;
}

void ddyn_ctrl_delay_line_push(ddyn_ctrl_delay_line *d, double u)
{
    d->newest = d->newest + 1 < DELAY_RING ? d->newest + 1 : 0;
    d->u[d->newest] = u;
}

void ddyn_ctrl_delay_line_set_newest(ddyn_ctrl_delay_line *d, double u)
{
    d->u[d->newest] = u;
}

double ddyn_ctrl_delay_line_ago(const ddyn_ctrl_delay_line *d, int n)
{
    int i;
    if (n < 0 || n > DDYN_CTRL_MAX_DELAY_STEPS || d->newest < 0 || d->newest >= DELAY_RING) {
        return NAN;
    }
    i = d->newest - n;
    return d->u[i < 0 ? i + DELAY_RING : i];
}

/* one delay in whole periods of dt; -1 when refused */
static int delay_periods(double delay, double dt)
{
    double n;
    if (!(delay >= 0.0) || !isfinite(delay) || !(dt > 0.0)) {
        return -1;
    }
    n = delay / dt;
    if (!(n < (double)DDYN_CTRL_MAX_DELAY_STEPS + 0.5 - 1e-6)) {
        return -1; /* rounds to more than the compiled maximum */
    }
    n = floor(n + 0.5 + 1e-6); /* the nearest whole period; a half (to 1e-6 of a period) rounds up */
    return n > (double)DDYN_CTRL_MAX_DELAY_STEPS ? DDYN_CTRL_MAX_DELAY_STEPS : (int)n;
}

ddyn_status ddyn_ctrl_delay_steps(const ddyn_ctrl_delay_config *cfg, double dt, int steps[DDYN_NU])
{
    int t, s;
    if (cfg == NULL || steps == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    t = delay_periods(cfg->throttle, dt);
    s = delay_periods(cfg->steering, dt);
    if (t < 0 || s < 0) {
        return DDYN_ERR_ARGUMENT;
    }
    steps[DDYN_CTRL_CH_THROTTLE] = t;
    steps[DDYN_CTRL_CH_STEERING] = s;
    return DDYN_OK;
}

/* ---- steering lag (ddyn_ctrl_lag_config) ---- */

double ddyn_ctrl_lag_decay(double tau, double dt)
{
    if (!(tau >= 0.0) || !isfinite(tau) || !(dt > 0.0) || !isfinite(dt)) {
        return NAN;
    }
    return tau > 0.0 ? exp(-dt / tau) : 0.0;
}

double ddyn_ctrl_lag_step(double delta, double cmd, double decay)
{
    return cmd + (delta - cmd) * decay;
}

double ddyn_ctrl_lag_invert(double delta, double target, double decay)
{
    return delta + (target - delta) / (1.0 - decay);
}

/* One period of the lag from (cmd, act) at its start with the steering rate u acting on the set-point:
 * the set-point and acting angle at its end, and the acting rate over it (returned). */
static double lag_period(const ddyn_ctrl *ctl, double cmd, double act, double u, double *cmd_next, double *act_next)
{
    const double dt = ctl->model->sample_time;
    *cmd_next = clamp(cmd + dt * u, ctl->cfg.mpc.state_lo[1], ctl->cfg.mpc.state_hi[1]);
    *act_next = ddyn_ctrl_lag_step(act, *cmd_next, ctl->lag_decay);
    return (*act_next - act) / dt;
}

/* u_prev is the newest command sent (a caller may have replaced it: ddyn_ctrl_command_applied, _not_sent)
 * and the command acting on the car over the coming period is the one sent `delay` periods before it;
 * with a steering lag, its steering acts through the lag (from the start of the period, lag_cmd/lag_act) */
static void sync_delay_lines(ddyn_ctrl *ctl)
{
    int c;
    for (c = 0; c < NU; ++c) {
        ddyn_ctrl_delay_line_set_newest(&ctl->sent[c], ctl->u_prev[c]);
        ctl->u_acting[c] = ctl->delay_steps[c] == 0 ? ctl->u_prev[c]
                                                     : ddyn_ctrl_delay_line_ago(&ctl->sent[c], ctl->delay_steps[c]);
    }
    if (ctl->lag_decay > 0.0) {
        ctl->u_acting[1] = lag_period(ctl, ctl->lag_cmd, ctl->lag_act, ctl->u_acting[1], &ctl->lag_cmd_next,
                                      &ctl->lag_act_next);
    }
}

static int degraded_config_ok(const ddyn_ctrl_degraded_config *d, double dt)
{
    return d->age_tolerance >= 0.0 && isfinite(d->age_tolerance) && d->max_age >= 0.0 &&
           d->max_age <= DDYN_CTRL_AGE_PERIODS * dt && d->recovery_periods >= 1 && d->r_scale >= 1.0 &&
           isfinite(d->r_scale) && d->rate_weight_scale >= 1.0 && isfinite(d->rate_weight_scale) &&
           d->speed_scale > 0.0 && d->speed_scale <= 1.0 && d->stale_extra_periods >= 0;
}

void ddyn_ctrl_mass_scale(double c[DDYN_NC], double mass_offset)
{
    static const int idx[DDYN_CTRL_MASS_SCALED_COUNT] = DDYN_CTRL_MASS_SCALED;
    int i;
    if (mass_offset == 0.0) {
        return; /* bit-identical without it */
    }
    for (i = 0; i < DDYN_CTRL_MASS_SCALED_COUNT; ++i) {
        c[idx[i]] /= 1.0 + mass_offset;
    }
}

/* The MPC's horizon with a steering delay of n periods: cfg->mpc.horizon - n (ddyn/controller.h, "the
 * plan ends where it would without the delay"); < 1 when the delay leaves no stage (refused). */
static int plan_horizon(const ddyn_ctrl_config *cfg, int n_steer)
{
    return cfg->mpc.horizon - n_steer;
}

static int config_ok(const ddyn_ctrl_config *cfg, double dt)
{
    const ddyn_ctrl_pid_config *g = &cfg->pid;
    int i, k, steps[NU];
    if (!degraded_config_ok(&cfg->degraded, dt) || ddyn_ctrl_delay_steps(&cfg->delay, dt, steps) != DDYN_OK ||
        !(ddyn_ctrl_lag_decay(cfg->lag.steering, dt) < 1.0) || !(cfg->mass_offset >= DDYN_CTRL_MASS_OFFSET_MIN) ||
        !(cfg->mass_offset <= DDYN_CTRL_MASS_OFFSET_MAX) || !(cfg->downforce >= 0.0) ||
        !(cfg->downforce <= DDYN_MODEL_DOWNFORCE_MAX)) {
        return 0; /* a delay above the compiled maximum is refused, not cut; a negative, non-finite lag, or
                     one so long that it does not decay in a period (its inversion would divide by 0); a mass
                     offset or a downforce out of its range (also NaN) */
    }
    if ((unsigned)cfg->coeff_source >= (unsigned)DDYN_CTRL_SOURCE_COUNT ||
        (unsigned)cfg->throttle_mode >= (unsigned)DDYN_CTRL_THROTTLE_MODE_COUNT ||
        (cfg->coeff_source == DDYN_CTRL_SOURCE_FIXED && !coefficients_usable(cfg->c_fixed)) ||
        !(g->kp >= 0.0) || !(g->ki >= 0.0) || !(g->kd >= 0.0) || !isfinite(g->kp) || !isfinite(g->ki) ||
        !isfinite(g->kd) || !(g->preview >= 0.0) || !isfinite(g->preview)) {
        return 0;
    }
    if ((unsigned)cfg->ekf_disc >= (unsigned)DDYN_DISC_COUNT || !ddyn_all_finite(cfg->c_nominal, NC) ||
        !(cfg->range_sigmas > 0.0) || !(cfg->nis_gate > 0.0) || !(cfg->safe_stop_speed >= 0.0) ||
        !(cfg->c_nominal[CM1] > 0.0) ||
        cfg->max_coeff_age < 0 || cfg->max_sensor_faults < 1 ||
        cfg->max_blind_steps < 1 || cfg->recovery_steps < 1 || cfg->max_plan_shift < 0 ||
        cfg->max_plan_shift >= plan_horizon(cfg, steps[DDYN_CTRL_CH_STEERING])) {
        return 0; /* also a horizon that the steering delay leaves shorter than one stage */
    }
    for (i = 0; i < NX; ++i) {
        if (!(cfg->p_max[i] > cfg->p0_diag[i])) {
            return 0; /* also rejects NaN */
        }
    }
    for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
        for (i = 0; i < ddyn_meas_dim((ddyn_meas_kind)k); ++i) {
            if (!(cfg->r_diag[k][i] > 0.0) || !isfinite(cfg->r_diag[k][i])) {
                return 0;
            }
        }
    }
    /* the nominal coefficients must at least make a finite model step (Iz = 0 would not) */
    return coefficients_usable(cfg->c_nominal);
}

ddyn_status ddyn_ctrl_init(ddyn_ctrl *ctl, const ddyn_vehicle_model *model, const ddyn_net_tables *tables,
                           const ddyn_ctrl_config *cfg, const double x0[DDYN_NX])
{
    ddyn_mpc_config mpc_cfg;
    ddyn_status s;
    if (ctl == NULL || model == NULL || cfg == NULL || x0 == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    memset(ctl, 0, sizeof *ctl);
    if (!config_ok(cfg, model->sample_time) || (tables == NULL && cfg->coeff_source != DDYN_CTRL_SOURCE_FIXED)) {
        return DDYN_ERR_ARGUMENT;
    }
    /* the network's outputs feed the model directly: their order must be the model's */
    if (strcmp(DDYN_NET_OUTPUT_NAMES, COEFF_ORDER) != 0) {
        return DDYN_ERR_ARGUMENT;
    }
    if (tables != NULL) {
        /* magic, shape, checkpoint hash, normalisation: the caller is told which */
        s = ddyn_guard_net_init(&ctl->net, tables);
        if (s != DDYN_OK) {
            return s;
        }
    }
    s = ddyn_ekf_init(&ctl->ekf, model, cfg->ekf_disc, x0, cfg->p0_diag, cfg->q_diag);
    if (s != DDYN_OK) {
        return s;
    }
    (void)ddyn_ctrl_delay_steps(&cfg->delay, model->sample_time, ctl->delay_steps); /* checked by config_ok */
    mpc_cfg = cfg->mpc;
    mpc_cfg.horizon = plan_horizon(cfg, ctl->delay_steps[DDYN_CTRL_CH_STEERING]);
    s = ddyn_mpc_init(&ctl->mpc, model, &mpc_cfg);
    if (s == DDYN_OK) {
        s = ddyn_mpc_set_downforce(&ctl->mpc, cfg->downforce); /* in range: config_ok */
    }
    if (s != DDYN_OK) {
        return s;
    }
    ctl->cfg = *cfg;
    ctl->model = model;
    ddyn_ctrl_delay_line_reset(&ctl->sent[0], 0.0); /* the actuators held since forever */
    ddyn_ctrl_delay_line_reset(&ctl->sent[1], 0.0);
    /* a shorter throttle delay is held back to the steering's (ddyn/controller.h): the queue holds u = 0 */
    ctl->thr_hold = ctl->delay_steps[DDYN_CTRL_CH_STEERING] > ctl->delay_steps[DDYN_CTRL_CH_THROTTLE]
                        ? ctl->delay_steps[DDYN_CTRL_CH_STEERING] - ctl->delay_steps[DDYN_CTRL_CH_THROTTLE]
                        : 0;
    /* the steering lag: at rest at the start's steering (the drive-by-wire node's first set-point) */
    ctl->lag_decay = ddyn_ctrl_lag_decay(cfg->lag.steering, model->sample_time);
    ctl->lag_cmd = ctl->lag_act = ctl->lag_cmd_next = ctl->lag_act_next = x0[STEERING];
    memcpy(ctl->coeffs, cfg->coeff_source == DDYN_CTRL_SOURCE_FIXED ? cfg->c_fixed : cfg->c_nominal,
           sizeof ctl->coeffs);
    ddyn_ctrl_mass_scale(ctl->coeffs, cfg->mass_offset);
    /* a heavier car drives the line's path at 1 / sqrt(1 + offset) of its speeds (ddyn/controller.h) */
    ctl->mass_speed_scale = cfg->mass_offset > 0.0 ? 1.0 / sqrt(1.0 + cfg->mass_offset) : 1.0;
    ctl->last_good_age = -1;
    ctl->bank_hint = -1;
    memcpy(ctl->x_prev, x0, sizeof ctl->x_prev);
    ctl->initialised = 1;
    return DDYN_OK;
}

ddyn_status ddyn_ctrl_set_track(ddyn_ctrl *ctl, int n, const double *x, const double *y, const double *speed,
                                const double *width_left, const double *width_right)
{
    if (ctl == NULL || !ctl->initialised) {
        return DDYN_ERR_ARGUMENT;
    }
    ctl->bank_hint = -1;
    return ddyn_mpc_set_track(&ctl->mpc, n, x, y, speed, width_left, width_right);
}

ddyn_status ddyn_ctrl_set_bank(ddyn_ctrl *ctl, const double *bank)
{
    if (ctl == NULL || !ctl->initialised) {
        return DDYN_ERR_ARGUMENT;
    }
    ctl->bank_hint = -1;
    return ddyn_mpc_set_bank(&ctl->mpc, bank);
}

ddyn_status ddyn_ctrl_set_grade(ddyn_ctrl *ctl, const double *grade)
{
    if (ctl == NULL || !ctl->initialised) {
        return DDYN_ERR_ARGUMENT;
    }
    ctl->bank_hint = -1;
    return ddyn_mpc_set_grade(&ctl->mpc, grade);
}

/* The road at x's position, road[0] the bank and road[1] the grade (each 0 without its profile): the
 * raceline's tables at its projection. 0: neither profile (nothing to add). */
static int road_at(ddyn_ctrl *ctl, const double x[NX], double road[2])
{
    road[0] = road[1] = 0.0;
    if (!ctl->mpc.track.have_bank && !ctl->mpc.track.have_grade) {
        return 0;
    }
    ddyn_mpc_road_at(&ctl->mpc, x[0], x[1], &ctl->bank_hint, road);
    return 1;
}

/* The coefficients at x's speed: ctl->coeffs with the known downforce's tyre load (ddyn_model_downforce)
 * in buf, or ctl->coeffs itself without one. Every evaluation of the vehicle's model uses these. */
static const double *coeffs_at(const ddyn_ctrl *ctl, const double x[NX], double buf[NC])
{
    return ddyn_model_coeffs_at(ctl->coeffs, ctl->cfg.downforce, x[3], buf);
}

/* The filter's model step (cfg.ekf_disc) with the road's bank and grade at x's position (ddyn_model_add_bank,
 * ddyn_model_add_grade) */
static ddyn_status model_step(ddyn_ctrl *ctl, const double x[NX], const double u[NU], double x_next[NX])
{
    double c_at[NC], road[2];
    ddyn_status s = ddyn_model_step(ctl->model, ctl->cfg.ekf_disc, x, u, coeffs_at(ctl, x, c_at), x_next,
                                    &ctl->ekf.work);
    if (s == DDYN_OK && road_at(ctl, x, road)) {
        ddyn_model_add_bank(road[0], ctl->model->sample_time, x, x_next);
        ddyn_model_add_grade(road[1], ctl->model->sample_time, x, x_next);
    }
    return s;
}

void ddyn_ctrl_safe_command(const ddyn_ctrl *ctl, const double x[DDYN_NX], double u[DDYN_NU])
{
    const ddyn_mpc_config *m = &ctl->cfg.mpc;
    const double *c = ctl->cfg.c_nominal;
    double dt = ctl->model->sample_time, target, rate;
    if (!isfinite(x[VX]) || x[VX] > ctl->cfg.safe_stop_speed) {
        target = m->state_lo[0]; /* brake: the throttle state's lower bound */
    } else {
        /* stopped: the throttle whose drive force cancels the rolling resistance at vx = 0,
         * (Cm1 - Cm2 * 0) T = Cr0. In the single-track model a negative throttle accelerates
         * backwards once the car stands, so holding the brake would reverse the car. */
        target = clamp(c[CR0] / c[CM1], m->state_lo[0], m->state_hi[0]);
    }
    /* reach the target within one period if the rate bound allows, otherwise as fast as it
     * allows; a non-finite throttle estimate brakes at the full rate */
    rate = isfinite(x[THROTTLE]) ? (target - x[THROTTLE]) / dt : m->rate_lo[0];
    u[0] = clamp(rate, m->rate_lo[0], m->rate_hi[0]);
    u[1] = 0.0; /* hold the steering angle */
}

/* Step 1: append the previous period's row to the history (oldest row first). */
static void push_history_row(ddyn_ctrl *ctl)
{
    int t, f;
    for (t = 0; t + 1 < TAU; ++t) {
        for (f = 0; f < NFEAT; ++f) {
            ctl->history[t][f] = ctl->history[t + 1][f];
        }
    }
    for (f = 0; f < NFEAT - NU; ++f) {
        ctl->history[TAU - 1][f] = ctl->x_prev[FIRST_FEATURE_STATE + f];
    }
    for (f = 0; f < NU; ++f) {
        ctl->history[TAU - 1][NFEAT - NU + f] = ctl->u_acting[f]; /* the input that acted (u_prev without delay) */
    }
    if (ctl->history_rows < TAU) {
        ctl->history_rows += 1;
    }
}

/* Is every state feature (vx, vy, omega, throttle, steering) of the full history within
 * range_sigmas standard deviations of the network's training mean? The two input-rate features are
 * not judged: they are this controller's own commands, bounded by the MPC's rate bounds, and an
 * MPC sits on those bounds more often than the training data's driver did without the car being
 * anywhere unusual. */
static int history_in_range(const ddyn_ctrl *ctl)
{
    const ddyn_net_tables *t = ctl->net.tables;
    int row, f;
    for (row = 0; row < TAU; ++row) {
        for (f = 0; f < NFEAT - NU; ++f) {
            double dev = fabs(ctl->history[row][f] - (double)t->mean[f]);
            if (!(dev <= ctl->cfg.range_sigmas * (double)t->std[f])) {
                return 0;
            }
        }
    }
    return 1;
}

/* Step 2: the coefficients of this period, with their fallbacks (as the source gives them). */
static ddyn_ctrl_status choose_source_coefficients(ddyn_ctrl *ctl)
{
    ddyn_ctrl_status st = DDYN_CTRL_OK;
    double c[NC];
    if (ctl->cfg.coeff_source == DDYN_CTRL_SOURCE_FIXED) {
        memcpy(ctl->coeffs, ctl->cfg.c_fixed, sizeof ctl->coeffs); /* no network, no fallback needed */
        return DDYN_CTRL_COEFF_FIXED;
    }
    if (ctl->last_good_age >= 0 && ctl->last_good_age < ctl->cfg.max_coeff_age + 1) {
        ctl->last_good_age += 1; /* ages by one period whatever happens next */
    }
    if (ctl->history_rows < TAU) {
        st |= DDYN_CTRL_HISTORY_FILLING;
    } else if (!history_in_range(ctl)) {
        st |= DDYN_CTRL_OUT_OF_RANGE;
    } else if (ddyn_guard_net_infer(&ctl->net, (const double(*)[NFEAT])ctl->history, c) != DDYN_NET_OK ||
               !coefficients_usable(c)) {
        /* the same test as the fixed and nominal sets: an unguarded (DPM) or corrupt network may give
         * finite coefficients the model cannot step with (Cm1 <= 0, Iz <= 0) */
        st |= DDYN_CTRL_NET_FAULT;
    } else {
        memcpy(ctl->coeffs, c, sizeof c);
        memcpy(ctl->last_good, c, sizeof c);
        ctl->last_good_age = 0;
        return st;
    }
    if (ctl->last_good_age >= 0 && ctl->last_good_age <= ctl->cfg.max_coeff_age) {
        memcpy(ctl->coeffs, ctl->last_good, sizeof ctl->coeffs);
        st |= DDYN_CTRL_COEFF_LAST_GOOD;
    } else {
        memcpy(ctl->coeffs, ctl->cfg.c_nominal, sizeof ctl->coeffs);
        st |= DDYN_CTRL_COEFF_NOMINAL;
    }
    return st;
}

/* Step 2, then the known mass offset on whichever set was chosen (the last good set is kept as the
 * network gave it: scaled once, here) */
static ddyn_ctrl_status choose_coefficients(ddyn_ctrl *ctl)
{
    const ddyn_ctrl_status st = choose_source_coefficients(ctl);
    ddyn_ctrl_mass_scale(ctl->coeffs, ctl->cfg.mass_offset);
    return st;
}

/* The filter has diverged when a variance is not finite or above its bound, or P is not a
 * covariance any more: a non-finite or asymmetric entry, or not positive definite (a P with a sound
 * diagonal can still be indefinite; the next update would then be refused or go the wrong way).
 * Positive definiteness by an in-place Cholesky of a copy: NX^3/6 multiply-adds, bounded. */
static int covariance_ok(const ddyn_ctrl *ctl)
{
    double L[NX * NX];
    int i, j, k;
    if (!ddyn_all_finite(ctl->ekf.P, NX * NX)) {
        return 0;
    }
    for (i = 0; i < NX; ++i) {
        double v = ctl->ekf.P[i * NX + i];
        if (!(v <= ctl->cfg.p_max[i]) || !(v > 0.0)) {
            return 0;
        }
        for (j = 0; j < i; ++j) {
            double a = ctl->ekf.P[i * NX + j], b = ctl->ekf.P[j * NX + i];
            if (!(fabs(a - b) <= 1e-9 * (fabs(a) + fabs(b)) + 1e-300)) {
                return 0; /* the EKF symmetrises after every update: asymmetry is corruption */
            }
        }
    }
    memcpy(L, ctl->ekf.P, sizeof L);
    for (j = 0; j < NX; ++j) {
        double d = L[j * NX + j];
        for (k = 0; k < j; ++k) {
            d -= L[j * NX + k] * L[j * NX + k];
        }
        if (!(d > 0.0)) {
            return 0;
        }
        d = sqrt(d);
        L[j * NX + j] = d;
        for (i = j + 1; i < NX; ++i) {
            double v = L[i * NX + j];
            for (k = 0; k < j; ++k) {
                v -= L[i * NX + k] * L[j * NX + k];
            }
            L[i * NX + j] = v / d;
        }
    }
    return 1;
}

/* Fuse one finite reading unless the EKF refuses it or its normalised innovation squared exceeds
 * the gate (then the update is undone: x and P are restored). 0: fused, 1: refused, 2: gated. */
static int fuse(ddyn_ctrl *ctl, int k, const double *z, const double *r)
{
    double x[NX], P[NX * NX], nis = 0.0, c_at[NC];
    memcpy(x, ctl->ekf.x, sizeof x);
    memcpy(P, ctl->ekf.P, sizeof P);
    if (ddyn_ekf_update(&ctl->ekf, (ddyn_meas_kind)k, z, r, coeffs_at(ctl, x, c_at), &nis) != DDYN_OK) {
        return 1; /* the filter is left unchanged by a refused update */
    }
    if (!(nis <= ctl->cfg.nis_gate)) {
        memcpy(ctl->ekf.x, x, sizeof x);
        memcpy(ctl->ekf.P, P, sizeof P);
        return 2;
    }
    return 0;
}

/* A repeated restart of the filter in one fault episode starts the states that the still-faulty sensors
 * read (nonzero columns of their measurement Jacobians) from this multiple of p0_diag (within p_max): a
 * restart at P0 that the readings still fail shows an estimate further from them than P0 allows (e.g.
 * the car moved while the filter was blind), and restarting at P0 again would gate them again. 100 (ten
 * times the standard deviation) admits a 1:43 car's position off by metres; a reading absurd by
 * kilometres stays gated. Only those states: with every state widened, the first readings after such a
 * restart swung the speed estimate by +-2 m/s in a guest run of the plant restart (the tyre model). */
#define REACQUIRE_P0_SCALE 100.0

/* count one rejected reading of sensor k. Returns 1 when this rejection makes the sensor faulty (the
 * filter restarts), 2 after every max_sensor_faults further rejections while it stays faulty (the
 * filter restarts again, wider: REACQUIRE_P0_SCALE; not for the accelerometer, below), else 0. The
 * run stays >= max_sensor_faults (the sensor stays faulty) until a reading fuses; it cycles through
 * max + 1 .. 2 max, so it is bounded. (Before, the filter restarted once per episode: readings that the
 * restarted filter still gated stayed rejected to the end of the run, the controller safe.) */
static int count_fault(ddyn_ctrl *ctl, int k)
{
    const int max = ctl->cfg.max_sensor_faults;
    int *run = &ctl->sensor_fault_run[k];
    *run = *run < 2 * max ? *run + 1 : max + 1;
    /* the accelerometer is not re-anchored: its prediction runs through the tyre model and the
     * coefficients, so readings that stay outside its gate show a model that does not fit (e.g. a
     * network's poor coefficients), not a lost state; restarting for it every few periods threw the
     * position estimate off by 0.44 m in the SIL loop test (fsim SilLoop.FramesFlowBothWays...) */
    if (*run == 2 * max && k == DDYN_MEAS_ACCELERATION) {
        return 0;
    }
    return *run == max ? 1 : (*run == 2 * max ? 2 : 0);
}

/* ---- degraded-bus mode (ddyn_ctrl_degraded_config) ---- */

/* A reading's age relative to the period's time (>= 0: a fresher reading counts as current). NaN/inf
 * or negative ages (a caller's bug) count as too old. */
static double relative_age(const ddyn_ctrl_input *in, const ddyn_ctrl_reading *r)
{
    double latency = isfinite(in->latency) && in->latency > 0.0 ? in->latency : 0.0;
    double a = r->age - latency;
    if (!isfinite(r->age) || r->age < 0.0) {
        return INFINITY;
    }
    return a > 0.0 ? a : 0.0;
}

/* Enter degraded mode on a faulty period, leave it after recovery_periods clean ones. Returns the
 * status bits; sets the MPC's weights and reference speed of the mode. */
static ddyn_ctrl_status update_degraded(ddyn_ctrl *ctl, const ddyn_ctrl_input *in)
{
    const ddyn_ctrl_degraded_config *d = &ctl->cfg.degraded;
    ddyn_ctrl_status st = DDYN_CTRL_OK;
    int k, faulty = in->bus_faults > 0u || !(in->latency <= d->age_tolerance);
    for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
        if (in->reading[k].valid && !(relative_age(in, &in->reading[k]) <= d->age_tolerance)) {
            faulty = 1;
        }
    }
    if (faulty) {
        ctl->clean_periods = 0;
        ctl->degraded = 1;
    } else if (ctl->degraded) {
        ctl->clean_periods += 1;
        if (ctl->clean_periods >= d->recovery_periods) {
            ctl->degraded = 0;
            ctl->clean_periods = 0;
            st |= DDYN_CTRL_BUS_RECOVERED;
        }
    }
    for (k = 0; k < NU; ++k) {
        ctl->mpc.cfg.r_rate[k] = ctl->cfg.mpc.r_rate[k] * (ctl->degraded ? d->rate_weight_scale : 1.0);
    }
    ctl->mpc.track.speed_scale = (ctl->degraded ? d->speed_scale : 1.0) * ctl->mass_speed_scale;
    if (ctl->degraded) {
        st |= DDYN_CTRL_BUS_DEGRADED;
        ctl->degraded_periods = saturating_increment(ctl->degraded_periods);
    }
    return st;
}

/* The filter's own state `age` seconds before now (now = its estimate x_now), interpolated linearly
 * between the estimates at the ends of the last periods. 0 when the history is too short. */
static int state_at_age(const ddyn_ctrl *ctl, const double x_now[NX], double age, double x[NX])
{
    const double dt = ctl->model->sample_time;
    double s = age / dt, frac;
    int j0 = (int)s, i;
    const double *a, *b;
    if (!(s >= 0.0) || j0 + 1 > ctl->x_hist_n || j0 >= DDYN_CTRL_AGE_PERIODS) {
        return 0;
    }
    frac = s - (double)j0;
    a = j0 == 0 ? x_now : ctl->x_hist[j0 - 1];
    b = ctl->x_hist[j0];
    for (i = 0; i < NX; ++i) {
        x[i] = (1.0 - frac) * a[i] + frac * b[i];
    }
    return 1;
}

/* Move a reading of relative age `age` to the period's time with the filter's trajectory:
 * z + h(x_now) - h(x(now - age)) (a heading difference wrapped to (-pi, pi]). 0: not possible (older
 * than max_age, or the model failed): the reading is not fused. Before the filter has a trajectory
 * that long (the first periods) the reading is fused as it is. */
static int age_reading(ddyn_ctrl *ctl, int k, const double *z, double age, double *z_out)
{
    double x_then[NX], h_now[DDYN_MEAS_MAX_DIM], h_then[DDYN_MEAS_MAX_DIM], H[DDYN_MEAS_MAX_DIM * NX], c_at[NC];
    int i, m = ddyn_meas_dim((ddyn_meas_kind)k);
    if (!(age > 0.0)) {
        memcpy(z_out, z, (size_t)m * sizeof *z);
        return 1;
    }
    if (age > ctl->cfg.degraded.max_age) {
        return 0;
    }
    if (!state_at_age(ctl, ctl->ekf.x, age, x_then)) {
        /* the first periods: no trajectory to place it on yet, fused as it is */
        memcpy(z_out, z, (size_t)m * sizeof *z);
        return 1;
    }
    if (ddyn_model_measure(ctl->model, (ddyn_meas_kind)k, ctl->ekf.x, coeffs_at(ctl, ctl->ekf.x, c_at), h_now, H,
                           &ctl->ekf.work) != DDYN_OK ||
        ddyn_model_measure(ctl->model, (ddyn_meas_kind)k, x_then, coeffs_at(ctl, x_then, c_at), h_then, H,
                           &ctl->ekf.work) != DDYN_OK) {
        return 0;
    }
    for (i = 0; i < m; ++i) {
        double d = h_now[i] - h_then[i];
        if (k == DDYN_MEAS_HEADING) {
            d = atan2(sin(d), cos(d));
        }
        z_out[i] = z[i] + d;
    }
    return ddyn_all_finite(z_out, m);
}

/* The estimate predicted over the input's latency in Euler sub-steps of at most a quarter period: the
 * state when this period's command takes effect. The actuators are held over it (u = 0): they reached
 * the previous set-point within its period (the SIL's in-process delayed-bus runs: with the previous
 * rates continued, the steering overshoots its set-point in the prediction and the lap had violations). */
static void predict_latency(ddyn_ctrl *ctl, const double x_start[NX], double latency, double x[NX])
{
    const double dt = ctl->model->sample_time;
    double xdot[NX], h;
    int n, j, i;
    memcpy(x, x_start, NX * sizeof *x);
    if (!(latency > 0.0) || !ctl->started) {
        return;
    }
    if (latency > ctl->cfg.degraded.max_age) {
        latency = ctl->cfg.degraded.max_age;
    }
    n = (int)ceil(latency / (0.25 * dt));
    if (n < 1) {
        n = 1;
    }
    if (n > 4 * DDYN_CTRL_AGE_PERIODS) {
        n = 4 * DDYN_CTRL_AGE_PERIODS;
    }
    h = latency / (double)n;
    for (j = 0; j < n; ++j) {
        static const double u_hold[NU] = {0.0, 0.0};
        double c_at[NC];
        if (ddyn_model_derivatives(ctl->model, x, u_hold, coeffs_at(ctl, x, c_at), xdot, &ctl->ekf.work) != DDYN_OK ||
            !ddyn_all_finite(xdot, NX)) {
            memcpy(x, x_start, NX * sizeof *x); /* the model failed: the start as it is */
            return;
        }
        for (i = 0; i < NX; ++i) {
            x[i] += h * xdot[i];
        }
    }
}

/* Re-anchoring after a blind spell. When no reading has been fused for max_sensor_faults periods or
 * more (a silent bus, a plant that restarted), the prediction has run on with nothing to hold it: the
 * estimate of a car that braked, or of one that did not move, can be anywhere by the time readings come
 * back, and a filter restarted at that estimate (as a divergence restarts it) gates the returning
 * readings or, through the covariance the blind prediction built up, moves the position the wrong way
 * on a speed reading. In the SIL's plant restart the filter stayed wrong for the rest of the run in one
 * guest run (vx stuck at -0.5 m/s, every reading gated) and needed several restarts in the others.
 * Instead the filter restarts on this period's own readings: every state that one of them measures
 * directly (a row of the sensor's Jacobian with a single nonzero entry, 1, whose model value is that
 * state: position, heading, yaw rate, rear wheel speed, steering angle) is set to the reading (the
 * heading as the wrapped difference to the estimate, so the yaw stays unwrapped); the filter restarts
 * there with P0. A state that some sensor measures directly but whose reading is missing this period
 * (e.g. the position in a period caught up without its position frame) starts wider
 * (REACQUIRE_P0_SCALE), so its reading of a later period is fused instead of gated; the others (vy,
 * the throttle, which the filter was told while safe) keep their estimate with P0. Returns 1 when the
 * filter was restarted. */
static int reanchor(ddyn_ctrl *ctl, const ddyn_ctrl_input *in)
{
    const double *x_now = ddyn_all_finite(ctl->ekf.x, NX) ? ctl->ekf.x : ctl->x_prev;
    double x[NX], p[NX];
    int direct[NX] = {0}, set[NX] = {0}, k, i, j, any = 0;
    memcpy(x, x_now, sizeof x);
    for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
        const ddyn_ctrl_reading *r = &in->reading[k];
        const int m = ddyn_meas_dim((ddyn_meas_kind)k);
        const int have = r->valid && ddyn_all_finite(r->z, m);
        double h[DDYN_MEAS_MAX_DIM], H[DDYN_MEAS_MAX_DIM * NX], c_at[NC];
        if (ddyn_model_measure(ctl->model, (ddyn_meas_kind)k, x_now, coeffs_at(ctl, x_now, c_at), h, H,
                               &ctl->ekf.work) != DDYN_OK) {
            continue;
        }
        for (i = 0; i < m; ++i) {
            int n = 0, at = -1;
            for (j = 0; j < NX; ++j) {
                if (H[i + j * m] != 0.0) { /* H column-major, m x NX */
                    n += 1;
                    at = j;
                }
            }
            if (n != 1 || H[i + at * m] != 1.0 || h[i] != x_now[at]) {
                continue; /* not a direct reading of one state */
            }
            direct[at] = 1;
            if (have && !set[at]) {
                double d = r->z[i] - x_now[at];
                if (k == DDYN_MEAS_HEADING) {
                    d = atan2(sin(d), cos(d));
                }
                x[at] = x_now[at] + d;
                set[at] = 1;
                any = 1;
            }
        }
    }
    if (!any || !ddyn_all_finite(x, NX)) {
        return 0;
    }
    for (i = 0; i < NX; ++i) {
        const double p0 = ctl->cfg.p0_diag[i];
        p[i] = direct[i] && !set[i] ? fmax(p0, fmin(REACQUIRE_P0_SCALE * p0, 0.01 * ctl->cfg.p_max[i])) : p0;
    }
    (void)ddyn_ekf_init(&ctl->ekf, ctl->model, ctl->cfg.ekf_disc, x, p, ctl->cfg.q_diag);
    return 1;
}

/* Step 3: predict, fuse this period's readings, check the filter. */
static ddyn_ctrl_status estimate(ddyn_ctrl *ctl, const ddyn_ctrl_input *in)
{
    ddyn_ctrl_status st = DDYN_CTRL_OK;
    const double r_var_scale = ctl->degraded ? ctl->cfg.degraded.r_scale * ctl->cfg.degraded.r_scale : 1.0;
    int k, i, fused = 0, diverged = 0, restart;
    unsigned reacquire = 0u; /* sensors whose repeated restart this is (bit k) */
    double c_at[NC];         /* the coefficients at the predicted period's start speed (downforce) */
    double road[2];          /* the road's bank and grade where the predicted period starts */
    (void)road_at(ctl, ctl->ekf.x, road);
    ctl->ekf.bank = road[0];
    ctl->ekf.grade = road[1];
    if (ctl->started && ddyn_ekf_predict(&ctl->ekf, ctl->u_acting, coeffs_at(ctl, ctl->ekf.x, c_at)) != DDYN_OK) {
        diverged = 1; /* the model step failed (e.g. non-finite): the filter state is unchanged */
    }
    if (ctl->started && ctl->blind_steps >= ctl->cfg.max_sensor_faults && reanchor(ctl, in)) {
        st |= DDYN_CTRL_EKF_DIVERGED; /* the filter restarted (on its readings): safe until it recovers */
        diverged = 0;
    }
    for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
        const ddyn_ctrl_reading *r = &in->reading[k];
        int m = ddyn_meas_dim((ddyn_meas_kind)k), result;
        double z[DDYN_MEAS_MAX_DIM], rv[DDYN_MEAS_MAX_DIM];
        if (!r->valid) {
            continue; /* no new reading of this sensor: its fault count stands */
        }
        for (i = 0; i < DDYN_MEAS_MAX_DIM; ++i) {
            rv[i] = ctl->cfg.r_diag[k][i] * r_var_scale;
        }
        if (!ddyn_all_finite(r->z, m)) {
            st |= DDYN_CTRL_MEAS_NONFINITE;
            ctl->nonfinite_count[k] = saturating_increment(ctl->nonfinite_count[k]);
            (void)count_fault(ctl, k);
        } else if (!age_reading(ctl, k, r->z, relative_age(in, r), z)) {
            /* too old to place in time: the bus's fault, not the sensor's (no fault count) */
            st |= DDYN_CTRL_MEAS_REJECTED;
            ctl->rejected_count[k] = saturating_increment(ctl->rejected_count[k]);
        } else if ((result = fuse(ctl, k, z, rv)) != 0) {
            st |= DDYN_CTRL_MEAS_REJECTED;
            ctl->rejected_count[k] = saturating_increment(ctl->rejected_count[k]);
            restart = count_fault(ctl, k);
            if (restart) {
                /* readings that stay outside the gate (result 2), or that the filter keeps refusing
                 * (result 1: S not positive definite, a non-finite update): the filter no longer
                 * believes its sensors, or cannot use them; restart it with P0, and again, wider,
                 * after every max_sensor_faults further rejections (count_fault) */
                diverged = 1;
                reacquire |= restart == 2 ? 1u << k : 0u;
            }
        } else {
            ctl->sensor_fault_run[k] = 0;
            fused = 1;
        }
    }
    /* a sensor that stays silent keeps its fault run: a faulty sensor that stops sending stays faulty */
    for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
        if (ctl->sensor_fault_run[k] >= ctl->cfg.max_sensor_faults) {
            st |= DDYN_CTRL_SENSOR_FAULT;
        }
    }
    ctl->blind_steps = fused ? 0 : (ctl->blind_steps < ctl->cfg.max_blind_steps + 1 ? ctl->blind_steps + 1
                                                                                    : ctl->blind_steps);
    if (ctl->blind_steps > ctl->cfg.max_blind_steps) {
        st |= DDYN_CTRL_NO_MEASUREMENTS;
    }
    if (diverged || !covariance_ok(ctl) || !ddyn_all_finite(ctl->ekf.x, NX)) {
        /* restart the filter at its last finite estimate with the initial covariance: the
         * readings of the next periods pull it in again, while safe mode holds the car */
        const double *x = ddyn_all_finite(ctl->ekf.x, NX) ? ctl->ekf.x : ctl->x_prev;
        double x_restart[NX], p_restart[NX];
        int widen[NX] = {0};
        memcpy(x_restart, x, sizeof x_restart);
        for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
            double h[DDYN_MEAS_MAX_DIM], H[DDYN_MEAS_MAX_DIM * NX], c_at_restart[NC];
            const int m = ddyn_meas_dim((ddyn_meas_kind)k);
            int j;
            if (!(reacquire & (1u << k)) ||
                ddyn_model_measure(ctl->model, (ddyn_meas_kind)k, x_restart, coeffs_at(ctl, x_restart, c_at_restart),
                                   h, H, &ctl->ekf.work) != DDYN_OK) {
                continue;
            }
            for (j = 0; j < NX; ++j) {
                for (i = 0; i < m; ++i) {
                    widen[j] |= H[i + j * m] != 0.0; /* H column-major, m x NX */
                }
            }
        }
        for (i = 0; i < NX; ++i) {
            const double p0 = ctl->cfg.p0_diag[i];
            /* widened, but within p_max with room for the prediction's growth */
            p_restart[i] = widen[i] ? fmax(p0, fmin(REACQUIRE_P0_SCALE * p0, 0.01 * ctl->cfg.p_max[i])) : p0;
        }
        (void)ddyn_ekf_init(&ctl->ekf, ctl->model, ctl->cfg.ekf_disc, x_restart, p_restart, ctl->cfg.q_diag);
        st |= DDYN_CTRL_EKF_DIVERGED;
    }
    return st;
}

/* The throttle PID of one period (throttle_mode PID; the law is in ddyn/controller.h): the
 * throttle rate to command now, and the integral updated with conditional integration.
 * DDYN_CTRL_PID_SATURATED when the throttle's range or rate bound cut the PID's output. */
static ddyn_ctrl_status throttle_pid(ddyn_ctrl *ctl, double v_ref, ddyn_ctrl_output *out, double *dthrottle)
{
    const ddyn_ctrl_pid_config *g = &ctl->cfg.pid;
    const ddyn_mpc_config *m = &ctl->cfg.mpc;
    const double dt = ctl->model->sample_time, vx = ctl->ekf.x[VX], thr = ctl->ekf.x[THROTTLE];
    const double e = v_ref - vx;
    double dvx = ctl->pid_started ? (vx - ctl->pid_vx_prev) / dt : 0.0;
    double raw = g->kp * e + ctl->pid_integral - g->kd * dvx;
    double target = clamp(raw, m->state_lo[0], m->state_hi[0]);
    double rate = clamp((target - thr) / dt, m->rate_lo[0], m->rate_hi[0]);
    double applied = thr + dt * rate; /* the throttle this command reaches at the end of the period */
    /* tolerance for the rounding of thr + dt * (target - thr) / dt */
    double tol = 1e-9 * (1.0 + fabs(raw));
    int short_up = raw > applied + tol, short_down = raw < applied - tol;
    ddyn_ctrl_status st = (short_up || short_down) ? DDYN_CTRL_PID_SATURATED : DDYN_CTRL_OK;
    if (!isfinite(raw) || !isfinite(applied)) {
        /* cannot happen (estimate() keeps the filter finite, v_ref comes from a checked table); never
         * let a NaN into the integral: hold the throttle, leave the PID's state as it was */
        *dthrottle = 0.0;
        return DDYN_CTRL_PID_SATURATED;
    }
    if (!((short_up && e > 0.0) || (short_down && e < 0.0))) {
        ctl->pid_integral = clamp(ctl->pid_integral + g->ki * e * dt, m->state_lo[0], m->state_hi[0]);
    }
    ctl->pid_vx_prev = vx;
    ctl->pid_started = 1;
    out->pid_ref_speed = v_ref;
    out->pid_throttle = target;
    out->pid_integral = ctl->pid_integral;
    *dthrottle = rate;
    return st;
}

/* ddyn_ctrl_predict_pipe from the lag's state (set-point, acting angle) lag[0], lag[1] at x's time: lag
 * holds the state after the pipe on return (as given when the model fails). */
static ddyn_status predict_pipe_lag(ddyn_ctrl *ctl, const double x[NX], double x_out[NX], double lag[2])
{
    double xa[NX], xb[NX], u[NU], cmd = lag[0], act = lag[1];
    int n, i, c;
    ddyn_status s;
    memcpy(xa, x, sizeof xa);
    n = ctl->delay_steps[DDYN_CTRL_CH_STEERING]; /* the MPC plans from when its steering acts (ddyn/controller.h) */
    for (i = 0; i < n; ++i) { /* n <= DDYN_CTRL_MAX_DELAY_STEPS */
        for (c = 0; c < NU; ++c) {
            const int d = ctl->delay_steps[c];
            /* a channel with a shorter delay: its commands not sent yet; the throttle's are held back
             * to the steering's delay and known (thr_queue, i - d < thr_hold), the steering is never
             * shorter here (ddyn/controller.h) */
            if (i < d) {
                u[c] = ddyn_ctrl_delay_line_ago(&ctl->sent[c], d - 1 - i);
            } else {
                u[c] = c == DDYN_CTRL_CH_THROTTLE && i - d < ctl->thr_hold ? ctl->thr_queue[i - d] : 0.0;
            }
        }
        if (ctl->lag_decay > 0.0) {
            u[1] = lag_period(ctl, cmd, act, u[1], &cmd, &act); /* the steering acts through the lag */
        }
        s = model_step(ctl, xa, u, xb);
        if (s == DDYN_OK && !ddyn_all_finite(xb, NX)) {
            s = DDYN_ERR_NONFINITE_OUTPUT;
        }
        if (s != DDYN_OK) {
            memcpy(x_out, x, NX * sizeof *x_out);
            return s;
        }
        memcpy(xa, xb, sizeof xa);
    }
    memcpy(x_out, xa, sizeof xa);
    lag[0] = cmd;
    lag[1] = act;
    return DDYN_OK;
}

ddyn_status ddyn_ctrl_predict_pipe(ddyn_ctrl *ctl, const double x[DDYN_NX], double x_out[DDYN_NX])
{
    double lag[2];
    if (ctl == NULL || x == NULL || x_out == NULL || !ctl->initialised) {
        return DDYN_ERR_ARGUMENT;
    }
    lag[0] = ctl->lag_cmd;
    lag[1] = ctl->lag_act;
    return predict_pipe_lag(ctl, x, x_out, lag);
}

/* A throttle delay longer than the steering's: its commands still in the pipe act over the MPC's first
 * n_throttle - n_steer stages, given to the MPC as known inputs (ddyn_mpc_fix_throttle); returns that
 * count (0 otherwise, and with the PID throttle), the stage of the plan whose throttle goes out now */
static int fix_pipe_throttle(ddyn_ctrl *ctl)
{
    const int ns = ctl->delay_steps[DDYN_CTRL_CH_STEERING], nt = ctl->delay_steps[DDYN_CTRL_CH_THROTTLE];
    double u[DDYN_CTRL_MAX_DELAY_STEPS];
    int n = nt - ns, k;
    if (ctl->cfg.throttle_mode == DDYN_CTRL_THROTTLE_PID || n <= 0) {
        (void)ddyn_mpc_fix_throttle(&ctl->mpc, 0, NULL);
        return 0;
    }
    if (n > ctl->mpc.cfg.horizon - 1) { /* the MPC's horizon: shortened by the steering delay */
        n = ctl->mpc.cfg.horizon - 1;
    }
    for (k = 0; k < n; ++k) { /* n <= DDYN_CTRL_MAX_DELAY_STEPS */
        u[k] = ddyn_ctrl_delay_line_ago(&ctl->sent[DDYN_CTRL_CH_THROTTLE], nt - 1 - ns - k);
    }
    return ddyn_mpc_fix_throttle(&ctl->mpc, n, u) == DDYN_OK ? n : 0;
}

/* With a steering lag: the MPC's steering rate u_mpc (its acting angle's, from the acting angle act at the
 * time the command acts) into the rate to send, so that the acting angle reaches act + dt u_mpc at the end
 * of that period; cmd is the newest set-point then (ddyn/controller.h "steering lag"). Without: u_mpc. */
static double invert_lag(const ddyn_ctrl *ctl, double u_mpc, const double lag[2])
{
    const ddyn_mpc_config *m = &ctl->cfg.mpc;
    const double dt = ctl->model->sample_time;
    double want;
    if (!(ctl->lag_decay > 0.0)) {
        return u_mpc;
    }
    want = clamp(ddyn_ctrl_lag_invert(lag[1], lag[1] + dt * u_mpc, ctl->lag_decay), m->state_lo[1], m->state_hi[1]);
    return clamp((want - lag[0]) / dt, m->rate_lo[1], m->rate_hi[1]);
}

/* Coefficients the prepared QP may keep: each within PREPARED_COEFF_TOL of the new value, measured on
 * the guard's range of that coefficient (on the value itself without a guard). The network's estimates
 * drift by far less from one period to the next; a fallback to other coefficients moves them by more. */
#define PREPARED_COEFF_TOL 1e-2
static int coefficients_close(const ddyn_ctrl *ctl, const double a[NC], const double b[NC])
{
    const ddyn_net_tables *t = ctl->net.tables;
    int i;
    for (i = 0; i < NC; ++i) {
        double scale = t != NULL && t->guarded ? (double)t->hi[i] - (double)t->lo[i] : fabs(b[i]);
        if (!(fabs(a[i] - b[i]) <= PREPARED_COEFF_TOL * scale)) {
            return 0;
        }
    }
    return 1;
}

/* Steps 4-5: solve the MPC and pick the command; *safe_cause set when the plan is exhausted. */
static ddyn_ctrl_status plan(ddyn_ctrl *ctl, const ddyn_ctrl_input *in, ddyn_ctrl_output *out, int *safe_cause)
{
    ddyn_ctrl_status st = DDYN_CTRL_OK;
    double u[NU], dthrottle = 0.0, v_ref = 0.0, x0[NX], x_pipe[NX], lag[2];
    const int pid = ctl->cfg.throttle_mode == DDYN_CTRL_THROTTLE_PID;
    int fix;
    ddyn_status s;
    if (ctl->mpc.prepared && !coefficients_close(ctl, ctl->mpc.c, ctl->coeffs)) {
        /* prepared with coefficients this period replaced (a fallback, a jump of the network's estimate):
         * a QP built on them would steer by the wrong car, so the whole iteration runs instead */
        ctl->mpc.prepared = 0;
    }
    s = ddyn_mpc_set_coefficients(&ctl->mpc, ctl->coeffs);
    /* the plan starts where the car will be when this command takes effect: through the commands still
     * in the pipe (the actuation delays; on a model failure the estimate as it is), then over the input's
     * latency */
    lag[0] = ctl->lag_cmd;
    lag[1] = ctl->lag_act;
    (void)predict_pipe_lag(ctl, ctl->ekf.x, x_pipe, lag);
    predict_latency(ctl, x_pipe, in->latency, x0);
    memcpy(out->x_mpc0, x0, sizeof x0);
    fix = fix_pipe_throttle(ctl); /* the throttle still in the pipe over the first stages (a longer delay) */
    if (s == DDYN_OK && pid) {
        s = ddyn_mpc_reference_speed(&ctl->mpc, x0, ctl->cfg.pid.preview * fabs(x0[VX]), &v_ref);
        if (s == DDYN_OK) {
            st |= throttle_pid(ctl, v_ref, out, &dthrottle);
            s = ddyn_mpc_solve_held_throttle(&ctl->mpc, x0, dthrottle, u, &out->mpc_info);
        }
    } else if (s == DDYN_OK && ctl->mpc.prepared) {
        /* prepared after the last command (ddyn_ctrl_prepare): only the feedback phase remains */
        s = ddyn_mpc_feedback(&ctl->mpc, x0, u, &out->mpc_info);
    } else if (s == DDYN_OK) {
        s = ddyn_mpc_solve(&ctl->mpc, x0, u, &out->mpc_info);
    }
    out->mpc_status = s;
    if (ctl->plan_horizon > 0 && ctl->plan_age < ctl->plan_horizon) {
        ctl->plan_age += 1;
    }
    if (s == DDYN_OK && ddyn_all_finite(u, NU)) {
        int h = ddyn_mpc_plan_inputs(&ctl->mpc, ctl->plan_u); /* a copy: no re-simulation that could fail */
        ctl->plan_horizon = h > 0 && h <= DDYN_MPC_MAX_HORIZON ? h : 0;
        ctl->plan_age = 0;
        memcpy(out->u, u, sizeof u);
        if (fix > 0 && ctl->plan_horizon > fix) {
            out->u[0] = ctl->plan_u[fix * NU + 0]; /* the stage at which the throttle sent now acts */
        }
        out->u[1] = invert_lag(ctl, u[1], lag);
        return st;
    }
    st |= s == DDYN_ERR_QP_NOT_CONVERGED ? DDYN_CTRL_MPC_NOT_CONVERGED : DDYN_CTRL_MPC_FAILED;
    if (s != DDYN_ERR_NOT_READY && s != DDYN_ERR_ARGUMENT && ctl->plan_horizon > 0 &&
        ctl->plan_age <= ctl->cfg.max_plan_shift && ctl->plan_age < ctl->plan_horizon) {
        /* the plan computed plan_age periods ago, at the stage that is now */
        const int ts = ctl->plan_age + fix < ctl->plan_horizon ? ctl->plan_age + fix : ctl->plan_horizon - 1;
        out->u[0] = pid ? dthrottle : ctl->plan_u[ts * NU + 0]; /* PID: its throttle, always */
        out->u[1] = invert_lag(ctl, ctl->plan_u[ctl->plan_age * NU + 1], lag);
        st |= DDYN_CTRL_PLAN_SHIFTED;
    } else {
        *safe_cause = 1;
    }
    return st;
}

/* A throttle delay shorter than the steering's (thr_hold > 0): the throttle the MPC planned now joins
 * the queue and the one planned thr_hold periods ago goes out (u[0]); the safe command goes out at once
 * and the queue becomes holds (u = 0), what the pipe then assumes (ddyn/controller.h). */
static void hold_back_throttle(ddyn_ctrl *ctl, int safe, double u[NU])
{
    const int h = ctl->thr_hold;
    int i;
    if (safe) {
        for (i = 0; i < DDYN_CTRL_MAX_DELAY_STEPS; ++i) {
            ctl->thr_queue[i] = 0.0;
        }
        return;
    }
    {
        const double planned = u[0];
        u[0] = ctl->thr_queue[0];
        for (i = 0; i + 1 < h && i + 1 < DDYN_CTRL_MAX_DELAY_STEPS; ++i) {
            ctl->thr_queue[i] = ctl->thr_queue[i + 1];
        }
        ctl->thr_queue[h - 1] = planned;
    }
}

ddyn_ctrl_status ddyn_ctrl_step(ddyn_ctrl *ctl, const ddyn_ctrl_input *in, ddyn_ctrl_output *out)
{
    ddyn_ctrl_status st;
    int safe_cause = 0;
    if (out == NULL) {
        return DDYN_CTRL_ERR_ARGUMENT;
    }
    memset(out, 0, sizeof *out);
    if (ctl == NULL || in == NULL || !ctl->initialised) {
        out->status = DDYN_CTRL_ERR_ARGUMENT; /* no context to know the throttle: u = {0, 0} holds both */
        return out->status;
    }
    if (ctl->started) {
        sync_delay_lines(ctl); /* the command acting over the period just ended */
        ctl->lag_cmd = ctl->lag_cmd_next; /* the lag at this period's start (unused without a lag) */
        ctl->lag_act = ctl->lag_act_next;
        push_history_row(ctl);
    }
    st = choose_coefficients(ctl);
    st |= update_degraded(ctl, in);
    st |= estimate(ctl, in);
    st |= plan(ctl, in, out, &safe_cause);
    if (st & (DDYN_CTRL_SENSOR_FAULT | DDYN_CTRL_NO_MEASUREMENTS | DDYN_CTRL_EKF_DIVERGED)) {
        safe_cause = 1;
    }
    if (safe_cause) {
        ctl->safe_mode = 1;
        ctl->healthy_steps = 0;
    } else if (ctl->safe_mode) {
        ctl->healthy_steps += 1;
        if (ctl->healthy_steps >= ctl->cfg.recovery_steps) {
            /* explicit recovery: the warm start and the stored plan predate the fault */
            ctl->safe_mode = 0;
            ctl->healthy_steps = 0;
            ctl->plan_age = ctl->plan_horizon; /* no shifted plan from before the fault */
            ddyn_mpc_reset(&ctl->mpc);
            ctl->pid_integral = 0.0; /* nor an integral of the speed error while the car was braked */
            ctl->pid_started = 0;
            st |= DDYN_CTRL_RECOVERED;
        }
    }
    if (ctl->safe_mode) {
        ddyn_ctrl_safe_command(ctl, ctl->ekf.x, out->u);
        st |= DDYN_CTRL_SAFE_COMMAND;
    }
    if (!ddyn_all_finite(out->u, NU)) { /* cannot happen by the checks above; never hand out garbage */
        ddyn_ctrl_safe_command(ctl, ctl->ekf.x, out->u);
        st |= DDYN_CTRL_SAFE_COMMAND;
    }
    if (ctl->thr_hold > 0) {
        hold_back_throttle(ctl, (st & DDYN_CTRL_SAFE_COMMAND) != 0u, out->u);
    }
    memcpy(out->x_est, ctl->ekf.x, sizeof out->x_est);
    memcpy(out->coeffs, ctl->coeffs, sizeof out->coeffs);
    memcpy(ctl->x_prev, ctl->ekf.x, sizeof ctl->x_prev);
    memcpy(ctl->u_prev, out->u, sizeof ctl->u_prev);
    ddyn_ctrl_delay_line_push(&ctl->sent[0], out->u[0]); /* sent now (ddyn_ctrl_command_applied may */
    ddyn_ctrl_delay_line_push(&ctl->sent[1], out->u[1]); /* still replace it: sync_delay_lines) */
    /* the estimates that date aged readings: newest first, bounded */
    memmove(ctl->x_hist[1], ctl->x_hist[0], (DDYN_CTRL_AGE_PERIODS - 1) * sizeof ctl->x_hist[0]);
    memcpy(ctl->x_hist[0], ctl->ekf.x, sizeof ctl->x_hist[0]);
    ctl->x_hist_n = ctl->x_hist_n < DDYN_CTRL_AGE_PERIODS ? ctl->x_hist_n + 1 : DDYN_CTRL_AGE_PERIODS;
    ctl->started = 1;
    out->status = st;
    return st;
}

void ddyn_ctrl_command_not_sent(ddyn_ctrl *ctl)
{
    if (ctl != NULL && ctl->initialised) {
        ctl->u_prev[0] = 0.0;
        ctl->u_prev[1] = 0.0;
    }
}

void ddyn_ctrl_command_applied(ddyn_ctrl *ctl, const double u[DDYN_NU])
{
    if (ctl != NULL && ctl->initialised && u != NULL && ddyn_all_finite(u, NU)) {
        memcpy(ctl->u_prev, u, sizeof ctl->u_prev);
    }
}

int ddyn_ctrl_stale_limit(const ddyn_ctrl *ctl, int base)
{
    if (ctl == NULL || !ctl->initialised || !ctl->degraded) {
        return base;
    }
    return base + ctl->cfg.degraded.stale_extra_periods;
}

ddyn_status ddyn_ctrl_prepare(ddyn_ctrl *ctl)
{
    double x_next[NX], x_pred[NX], lag[2];
    ddyn_status s;
    if (ctl == NULL || !ctl->initialised || !ctl->started) {
        return DDYN_ERR_ARGUMENT;
    }
    ctl->mpc.prepared = 0;
    if (ctl->safe_mode || ctl->cfg.throttle_mode == DDYN_CTRL_THROTTLE_PID) {
        return DDYN_ERR_NOT_READY;
    }
    /* the filter's own prediction model, with this period's coefficients and the command that acts over
     * the coming period (the one just sent without a delay; the EKF's work memory is scratch between its
     * calls), then on through the commands still in the pipe: the next step's MPC start */
    sync_delay_lines(ctl);
    s = model_step(ctl, ctl->ekf.x, ctl->u_acting, x_next);
    if (s != DDYN_OK) {
        return s;
    }
    lag[0] = ctl->lag_cmd_next; /* the lag at the next period's start */
    lag[1] = ctl->lag_act_next;
    (void)predict_pipe_lag(ctl, x_next, x_pred, lag);
    (void)fix_pipe_throttle(ctl); /* as the next step will: its pipe is this line (newest: just sent) */
    return ddyn_mpc_prepare(&ctl->mpc, x_pred);
}

const char *ddyn_ctrl_status_name(ddyn_ctrl_status bit)
{
    static const char *const names[DDYN_CTRL_STATUS_BITS] = {
        "DDYN_CTRL_ERR_ARGUMENT",    "DDYN_CTRL_MEAS_NONFINITE",    "DDYN_CTRL_MEAS_REJECTED",
        "DDYN_CTRL_SENSOR_FAULT",    "DDYN_CTRL_NO_MEASUREMENTS",   "DDYN_CTRL_HISTORY_FILLING",
        "DDYN_CTRL_OUT_OF_RANGE",    "DDYN_CTRL_NET_FAULT",         "DDYN_CTRL_COEFF_LAST_GOOD",
        "DDYN_CTRL_COEFF_NOMINAL",   "DDYN_CTRL_EKF_DIVERGED",      "DDYN_CTRL_MPC_NOT_CONVERGED",
        "DDYN_CTRL_MPC_FAILED",      "DDYN_CTRL_PLAN_SHIFTED",      "DDYN_CTRL_SAFE_COMMAND",
        "DDYN_CTRL_RECOVERED",       "DDYN_CTRL_COEFF_FIXED",       "DDYN_CTRL_PID_SATURATED",
        "DDYN_CTRL_BUS_DEGRADED",    "DDYN_CTRL_BUS_RECOVERED"};
    int i;
    if (bit == DDYN_CTRL_OK) {
        return "DDYN_CTRL_OK";
    }
    for (i = 0; i < DDYN_CTRL_STATUS_BITS; ++i) {
        if (bit == ((ddyn_ctrl_status)1u << i)) {
            return names[i];
        }
    }
    return "DDYN_CTRL_UNKNOWN";
}
