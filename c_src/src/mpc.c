/* ddyn MPC: configuration, parameters, raceline table and the real-time-iteration step (see ddyn/mpc.h). */
#include "ddyn/mpc.h"
#include "ddyn/mpc_qp.h"
#include "ddyn/mpc_qp_daqp.h"
#include "ddyn_mpc_limits.h"

#include <math.h>
#include <stddef.h>
#include <string.h>

/* the generated MPC step runs in the model's work memory */
typedef char mpc_step_work_fits[(DDYN_MPC_STEP_SZ_W <= DDYN_MODEL_MAX_SZ_W && DDYN_MPC_STEP_SZ_IW <= DDYN_MODEL_MAX_SZ_IW) ? 1 : -1];

ddyn_status ddyn_mpc_default_config(const ddyn_vehicle_model *model, ddyn_mpc_config *cfg)
{
    int i, j;
    if (model == NULL || cfg == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    for (i = 0; i < DDYN_MPC_LIMITS_COUNT; ++i) {
        if (strcmp(ddyn_mpc_limits[i].name, model->name) == 0) {
            break;
        }
    }
    if (i == DDYN_MPC_LIMITS_COUNT) {
        return DDYN_ERR_ARGUMENT;
    }
    memset(cfg, 0, sizeof *cfg);
    cfg->horizon = DDYN_MPC_DEFAULT_HORIZON;
    cfg->prediction = DDYN_MPC_PRED_RK4_SINGLE;
    for (j = 0; j < DDYN_NU; ++j) {
        cfg->rate_lo[j] = ddyn_mpc_limits[i].lo_hi[j][0];
        cfg->rate_hi[j] = ddyn_mpc_limits[i].lo_hi[j][1];
        cfg->state_lo[j] = ddyn_mpc_limits[i].lo_hi[2 + j][0];
        cfg->state_hi[j] = ddyn_mpc_limits[i].lo_hi[2 + j][1];
    }
    /* weights first tuned on the 1:43 car's ETHZMobil lap along its own time-optimal line (docs/mpc.md),
     * the steering-rate weight then chosen on random tracks (docs/tracks.md: 1.0; 0.1 spun on 4 of 20
     * held-out tracks): the terminal stage's position weight 10x the others pulls the plan onto the
     * line, throttle rate nearly free */
    cfg->q_pos[0] = 1000.0;
    cfg->q_pos[1] = 1000.0;
    cfg->q_terminal_scale = 10.0;
    cfg->r_rate[0] = 1e-3;
    cfg->r_rate[1] = 1.0; /* chosen on random tracks 0-19, held out on 200-219 (docs/tracks.md) */
    cfg->slack_l1 = 1e4;
    cfg->slack_l2 = 1e5;
    cfg->qp_solver = DDYN_MPC_QP_DAQP; /* docs/mpc.md: faster and far more accurate than the own IPM */
    cfg->qp_max_iterations = 30;
    cfg->qp_tolerance = 1e-6;
    cfg->qp_cold_max_iterations = DDYN_MPC_COLD_IPM_ITERATIONS;
    return DDYN_OK;
}

static int config_valid(const ddyn_mpc_config *cfg)
{
    int j;
    if (cfg->horizon < 1 || cfg->horizon > DDYN_MPC_MAX_HORIZON || (unsigned)cfg->prediction >= (unsigned)DDYN_MPC_PRED_COUNT ||
        (unsigned)cfg->qp_solver >= (unsigned)DDYN_MPC_QP_COUNT ||
        cfg->qp_max_iterations < 1 || cfg->qp_max_iterations > DDYN_MPC_MAX_QP_ITERATIONS ||
        cfg->qp_cold_max_iterations < 1 || cfg->qp_cold_max_iterations > DDYN_MPC_MAX_QP_ITERATIONS) {
        return 0;
    }
    if (!ddyn_all_finite(cfg->q_pos, 2) || !ddyn_all_finite(cfg->r_rate, DDYN_NU) || !isfinite(cfg->q_terminal_scale) ||
        !isfinite(cfg->slack_l1) || !isfinite(cfg->slack_l2) || !isfinite(cfg->qp_tolerance)) {
        return 0;
    }
    if (cfg->q_pos[0] < 0.0 || cfg->q_pos[1] < 0.0 || cfg->q_terminal_scale < 0.0 || cfg->slack_l1 < 0.0 ||
        cfg->slack_l2 <= 0.0 || cfg->qp_tolerance <= 0.0) {
        return 0;
    }
    for (j = 0; j < DDYN_NU; ++j) {
        /* R > 0 keeps the condensed Hessian positive definite whatever the linearisation */
        if (!(cfg->r_rate[j] > 0.0) || !(cfg->rate_lo[j] < cfg->rate_hi[j]) || !(cfg->state_lo[j] < cfg->state_hi[j]) ||
            !isfinite(cfg->rate_lo[j]) || !isfinite(cfg->rate_hi[j]) || !isfinite(cfg->state_lo[j]) ||
            !isfinite(cfg->state_hi[j]) || cfg->rate_lo[j] > 0.0 || cfg->rate_hi[j] < 0.0) {
            return 0;
        }
    }
    return 1;
}

ddyn_status ddyn_mpc_init(ddyn_mpc *mpc, const ddyn_vehicle_model *model, const ddyn_mpc_config *cfg)
{
    int i;
    if (mpc == NULL || model == NULL || cfg == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    if (!config_valid(cfg)) {
        return DDYN_ERR_ARGUMENT;
    }
    for (i = 0; i < DDYN_MPC_LIMITS_COUNT; ++i) {
        if (strcmp(ddyn_mpc_limits[i].name, model->name) == 0) {
            break;
        }
    }
    if (i == DDYN_MPC_LIMITS_COUNT) {
        return DDYN_ERR_ARGUMENT; /* a model without a generated MPC step */
    }
    memset(mpc, 0, sizeof *mpc);
    mpc->model = model;
    mpc->mpc_step = ddyn_mpc_limits[i].step;
    mpc->cfg = *cfg;
    return DDYN_OK;
}

ddyn_status ddyn_mpc_set_coefficients(ddyn_mpc *mpc, const double c[DDYN_NC])
{
    if (mpc == NULL || c == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    if (!ddyn_all_finite(c, DDYN_NC)) {
        return DDYN_ERR_NONFINITE_INPUT;
    }
    memcpy(mpc->c, c, sizeof mpc->c);
    mpc->have_coefficients = 1;
    return DDYN_OK;
}

ddyn_status ddyn_mpc_set_downforce(ddyn_mpc *mpc, double k)
{
    if (mpc == NULL || !(k >= 0.0) || !(k <= DDYN_MODEL_DOWNFORCE_MAX)) {
        return DDYN_ERR_ARGUMENT;
    }
    mpc->downforce = k;
    return DDYN_OK;
}

ddyn_status ddyn_mpc_set_track(ddyn_mpc *mpc, int n, const double *x, const double *y, const double *speed,
                               const double *width_left, const double *width_right)
{
    ddyn_mpc_track *t;
    int i;
    double s = 0.0;
    if (mpc == NULL || x == NULL || y == NULL || speed == NULL || width_left == NULL || width_right == NULL ||
        n < 4 || n > DDYN_MPC_MAX_TRACK_POINTS) {
        return DDYN_ERR_ARGUMENT;
    }
    if (!ddyn_all_finite(x, n) || !ddyn_all_finite(y, n) || !ddyn_all_finite(speed, n) || !ddyn_all_finite(width_left, n) ||
        !ddyn_all_finite(width_right, n)) {
        return DDYN_ERR_NONFINITE_INPUT;
    }
    for (i = 0; i < n; ++i) {
        int j = (i + 1) % n;
        if (!(speed[i] > 0.0) || !(hypot(x[j] - x[i], y[j] - y[i]) > 0.0)) {
            return DDYN_ERR_ARGUMENT; /* zero speed would stall the reference; zero-length segments have no normal */
        }
    }
    t = &mpc->track;
    for (i = 0; i < n; ++i) {
        int j = (i + 1) % n;
        t->s[i] = s;
        t->x[i] = x[i];
        t->y[i] = y[i];
        t->speed[i] = speed[i];
        t->width_left[i] = width_left[i];
        t->width_right[i] = width_right[i];
        s += hypot(x[j] - x[i], y[j] - y[i]);
    }
    t->length = s;
    t->n = n;
    t->speed_scale = 1.0;
    t->have_bank = 0;
    memset(t->bank, 0, sizeof t->bank);
    t->have_grade = 0;
    memset(t->grade, 0, sizeof t->grade);
    ddyn_mpc_reset(mpc);
    return DDYN_OK;
}

/* a road profile (the bank's, the grade's) along the track set last: |v| < max at every point, or NULL: none */
static ddyn_status set_profile(ddyn_mpc *mpc, const double *v, double max, double *table, int *have)
{
    int i;
    if (mpc == NULL || mpc->cfg.prediction != DDYN_MPC_PRED_RK4_SINGLE) {
        return DDYN_ERR_ARGUMENT;
    }
    if (mpc->track.n < 4) {
        return DDYN_ERR_NOT_READY;
    }
    if (v != NULL) {
        if (!ddyn_all_finite(v, mpc->track.n)) {
            return DDYN_ERR_NONFINITE_INPUT;
        }
        for (i = 0; i < mpc->track.n; ++i) {
            if (!(fabs(v[i]) < max)) {
                return DDYN_ERR_ARGUMENT;
            }
        }
        memcpy(table, v, (size_t)mpc->track.n * sizeof *v);
        *have = 1;
    } else {
        memset(table, 0, DDYN_MPC_MAX_TRACK_POINTS * sizeof *table);
        *have = 0;
    }
    ddyn_mpc_reset(mpc);
    return DDYN_OK;
}

ddyn_status ddyn_mpc_set_bank(ddyn_mpc *mpc, const double *bank)
{
    return mpc == NULL ? DDYN_ERR_ARGUMENT
                       : set_profile(mpc, bank, DDYN_MPC_MAX_BANK, mpc->track.bank, &mpc->track.have_bank);
}

ddyn_status ddyn_mpc_set_grade(ddyn_mpc *mpc, const double *grade)
{
    return mpc == NULL ? DDYN_ERR_ARGUMENT
                       : set_profile(mpc, grade, DDYN_MPC_MAX_GRADE, mpc->track.grade, &mpc->track.have_grade);
}

ddyn_status ddyn_mpc_fix_throttle(ddyn_mpc *mpc, int n, const double *dthrottle)
{
    int k;
    if (mpc == NULL || n < 0 || n >= mpc->cfg.horizon || (n > 0 && dthrottle == NULL)) {
        return DDYN_ERR_ARGUMENT;
    }
    if (n > 0 && !ddyn_all_finite(dthrottle, n)) {
        return DDYN_ERR_ARGUMENT;
    }
    for (k = 0; k < n; ++k) { /* n < horizon <= DDYN_MPC_MAX_HORIZON */
        mpc->fix_u[k] = dthrottle[k];
    }
    mpc->fix_n = n;
    return DDYN_OK;
}

void ddyn_mpc_reset(ddyn_mpc *mpc)
{
    if (mpc == NULL) {
        return;
    }
    mpc->have_warm_start = 0;
    mpc->prepared = 0;
    mpc->last_index = -1;
    memset(mpc->u_plan, 0, sizeof mpc->u_plan);
    ddyn_mpc_qp_daqp_reset(&mpc->daqp); /* the next QP starts cold */
}

/* ---- raceline geometry ------------------------------------------------------------------ */

#define LOCAL_WINDOW 40 /* raceline segments searched either side of the previous projection of x0 */
#define STAGE_WINDOW 10 /* ... and of the previous stage's predicted position (stages move < 0.1 m) */

/* nearest point of segment i to (px, py): squared distance, parameter in [0, 1] */
static double segment_distance(const ddyn_mpc_track *t, int i, double px, double py, double *param)
{
    int j = i + 1 < t->n ? i + 1 : 0;
    double dx = t->x[j] - t->x[i], dy = t->y[j] - t->y[i];
    double rx = px - t->x[i], ry = py - t->y[i];
    double u = (rx * dx + ry * dy) / (dx * dx + dy * dy);
    double ex, ey;
    u = u < 0.0 ? 0.0 : (u > 1.0 ? 1.0 : u);
    ex = rx - u * dx;
    ey = ry - u * dy;
    *param = u;
    return ex * ex + ey * ey;
}

/* Projection of (px, py) on the raceline: segment index and parameter. Searches +-window
 * segments around hint, or every segment when hint < 0. */
static int project(const ddyn_mpc_track *t, double px, double py, int hint, int window, double *param)
{
    int best = 0, k, count = hint < 0 ? t->n : (2 * window + 1 < t->n ? 2 * window + 1 : t->n);
    int start = hint < 0 ? 0 : hint - (count - 1) / 2;
    double best_d = INFINITY, best_u = 0.0;
    for (k = 0; k < count; ++k) {
        int i = ((start + k) % t->n + t->n) % t->n;
        double u, d = segment_distance(t, i, px, py, &u);
        if (d < best_d) {
            best_d = d;
            best = i;
            best_u = u;
        }
    }
    *param = best_u;
    return best;
}

/* point, unit tangent and interpolated table values at segment i, parameter u */
typedef struct {
    double x, y, tx, ty, speed, wl, wr, s;
} track_point;

static track_point track_at(const ddyn_mpc_track *t, int i, double u)
{
    int j = i + 1 < t->n ? i + 1 : 0;
    double dx = t->x[j] - t->x[i], dy = t->y[j] - t->y[i], len = hypot(dx, dy);
    track_point p;
    p.x = t->x[i] + u * dx;
    p.y = t->y[i] + u * dy;
    p.tx = dx / len;
    p.ty = dy / len;
    p.speed = t->speed_scale * (t->speed[i] + u * (t->speed[j] - t->speed[i]));
    p.wl = t->width_left[i] + u * (t->width_left[j] - t->width_left[i]);
    p.wr = t->width_right[i] + u * (t->width_right[j] - t->width_right[i]);
    p.s = t->s[i] + u * len;
    return p;
}

/* advance (i, u) by ds >= 0 metres along the closed raceline; a look-ahead of more than a lap wraps */
static void advance(const ddyn_mpc_track *t, int *i, double *u, double ds)
{
    int k;
    if (t->length > 0.0 && ds >= t->length) {
        ds = fmod(ds, t->length); /* whole laps end where they started */
    }
    for (k = 0; k <= t->n; ++k) { /* bounded: under a lap from mid-segment crosses at most n + 1 segments */
        int j = *i + 1 < t->n ? *i + 1 : 0;
        double len = hypot(t->x[j] - t->x[*i], t->y[j] - t->y[*i]);
        double left = (1.0 - *u) * len;
        if (ds <= left) {
            *u += ds / len;
            return;
        }
        ds -= left;
        *i = j;
        *u = 0.0;
    }
}

/* a profile's value at segment i, parameter u (linear between the points; 0 out of range) */
static double profile_at(const ddyn_mpc_track *t, const double *table, int i, double u)
{
    int j;
    if (i < 0 || i >= t->n || !(u >= 0.0 && u <= 1.0)) {
        return 0.0;
    }
    j = i + 1 < t->n ? i + 1 : 0;
    return table[i] + u * (table[j] - table[i]);
}

double ddyn_mpc_track_bank(const ddyn_mpc_track *t, int i, double u)
{
    return t == NULL || !t->have_bank ? 0.0 : profile_at(t, t->bank, i, u);
}

double ddyn_mpc_track_grade(const ddyn_mpc_track *t, int i, double u)
{
    return t == NULL || !t->have_grade ? 0.0 : profile_at(t, t->grade, i, u);
}

/* the road (bank, grade) at the projection of (px, py), searched +-window segments around *hint (all when < 0);
 * one projection for both, none without a profile */
static void road_lookup(const ddyn_mpc *mpc, double px, double py, int *hint, int window, double road[2])
{
    int i, h;
    double u;
    road[0] = road[1] = 0.0;
    if (mpc == NULL || !(mpc->track.have_bank || mpc->track.have_grade) || mpc->track.n < 4 || !isfinite(px) ||
        !isfinite(py)) {
        return;
    }
    h = hint != NULL && *hint >= 0 && *hint < mpc->track.n ? *hint : -1;
    i = project(&mpc->track, px, py, h, window, &u);
    if (hint != NULL) {
        *hint = i;
    }
    road[0] = ddyn_mpc_track_bank(&mpc->track, i, u);
    road[1] = ddyn_mpc_track_grade(&mpc->track, i, u);
}

void ddyn_mpc_road_at(const ddyn_mpc *mpc, double px, double py, int *hint, double road[2])
{
    road_lookup(mpc, px, py, hint, DDYN_MPC_BANK_WINDOW, road);
}

double ddyn_mpc_bank_at(const ddyn_mpc *mpc, double px, double py, int *hint)
{
    double road[2];
    road_lookup(mpc, px, py, hint, DDYN_MPC_BANK_WINDOW, road);
    return road[0];
}

/* ---- one real-time iteration --------------------------------------------------------------- */

static double clip(double v, double lo, double hi) { return v < lo ? lo : (v > hi ? hi : v); }

/* One prediction step x_next = f(x, u) and, when A is not NULL, its Jacobians A, B. */
static ddyn_status predict(ddyn_mpc *mpc, const double *x, const double *u, const double road[2], double *x_next,
                           double *A, double *B)
{
    ddyn_status st;
    double buf[DDYN_NC];
    const double *c_at = ddyn_model_coeffs_at(mpc->c, mpc->downforce, x[3], buf); /* at x's speed (downforce) */
    if (mpc->cfg.prediction == DDYN_MPC_PRED_RK4_SINGLE) {
        double out[DDYN_NX * (1 + DDYN_NX + DDYN_NU)];
        double *res[3];
        const double *arg[4];
        arg[0] = x;
        arg[1] = u;
        arg[2] = c_at;
        arg[3] = road; /* the road's bank and grade over this step (0, 0: flat and level) */
        res[0] = out;
        res[1] = out + DDYN_NX;
        res[2] = out + DDYN_NX * (1 + DDYN_NX);
        if (mpc->mpc_step(arg, res, mpc->model_work.iw, mpc->model_work.w, 0) != 0) {
            return DDYN_ERR_EVALUATION;
        }
        if (!ddyn_all_finite(out, DDYN_NX * (1 + DDYN_NX + DDYN_NU))) {
            return DDYN_ERR_NONFINITE_OUTPUT;
        }
        memcpy(x_next, out, DDYN_NX * sizeof(double));
        if (A != NULL) {
            memcpy(A, res[1], DDYN_NX * DDYN_NX * sizeof(double));
            memcpy(B, res[2], DDYN_NX * DDYN_NU * sizeof(double));
        }
        return DDYN_OK;
    }
    {
        ddyn_discretisation disc = mpc->cfg.prediction == DDYN_MPC_PRED_EULER ? DDYN_DISC_EULER : DDYN_DISC_RK4;
        st = ddyn_model_step(mpc->model, disc, x, u, c_at, x_next, &mpc->model_work);
        if (st != DDYN_OK || A == NULL) {
            return st;
        }
        return ddyn_model_step_jacobians(mpc->model, disc, x, u, c_at, A, B, NULL, &mpc->model_work);
    }
}

/* Linearisation trajectory: x0 and the shifted previous plan (zeros without warm start), clipped
 * to the rate bounds, simulated by the model; A, B along it. With the throttle held (hold != 0)
 * the throttle rates are the fixed ones instead: dthrottle0 at stage 0, then 0. */
static ddyn_status linearise(ddyn_mpc *mpc, const double x0[DDYN_NX], int hold, double dthrottle0)
{
    const int h = mpc->cfg.horizon;
    int k, j, hint;
    ddyn_status st;
    for (k = 0; k < h; ++k) {
        int src = mpc->have_warm_start ? (k + 1 < h ? k + 1 : h - 1) : -1;
        for (j = 0; j < DDYN_NU; ++j) {
            double v = src >= 0 ? mpc->u_plan[src * DDYN_NU + j] : 0.0;
            if (hold && j == 0) {
                v = k == 0 ? dthrottle0 : 0.0;
            } else if (j == 0 && k < mpc->fix_n) {
                v = mpc->fix_u[k]; /* known (ddyn_mpc_fix_throttle) */
            }
            mpc->u_lin[k * DDYN_NU + j] = clip(v, mpc->cfg.rate_lo[j], mpc->cfg.rate_hi[j]);
        }
    }
    memcpy(mpc->x_lin, x0, DDYN_NX * sizeof(double));
    hint = mpc->last_index;
    for (k = 0; k < h; ++k) {
        /* the road at this stage's own track position: its predicted position projected on the raceline */
        const double *xk = mpc->x_lin + k * DDYN_NX;
        double road[2];
        road_lookup(mpc, xk[0], xk[1], &hint, k == 0 ? LOCAL_WINDOW : STAGE_WINDOW, road);
        mpc->stage_bank[k] = road[0];
        mpc->stage_grade[k] = road[1];
        st = predict(mpc, xk, mpc->u_lin + k * DDYN_NU, road, mpc->x_lin + (k + 1) * DDYN_NX,
                     mpc->A + k * DDYN_NX * DDYN_NX, mpc->B + k * DDYN_NX * DDYN_NU);
        if (st != DDYN_OK) {
            return st;
        }
    }
    return DDYN_OK;
}

/* d(x, y)_k / du_j for j < k by forward propagation of the columns of B_j through A_{j+1..k-1}. Only
 * the entries j < k of each row are written: build_qp reads no others. */
static void sensitivities(ddyn_mpc *mpc)
{
    const int h = mpc->cfg.horizon, n = 2 * h;
    int j, k, ch, a, b;
    for (j = 0; j < h; ++j) {
        for (ch = 0; ch < DDYN_NU; ++ch) {
            double v[DDYN_NX], w[DDYN_NX];
            memcpy(v, mpc->B + j * DDYN_NX * DDYN_NU + ch * DDYN_NX, sizeof v);
            for (k = j + 1; k <= h; ++k) {
                double *row = mpc->sens + (k - 1) * 2 * n;
                row[2 * j + ch] = v[0];
                row[n + 2 * j + ch] = v[1];
                if (k == h) {
                    break;
                }
                for (a = 0; a < DDYN_NX; ++a) {
                    const double *Ak = mpc->A + k * DDYN_NX * DDYN_NX;
                    double acc = 0.0;
                    for (b = 0; b < DDYN_NX; ++b) {
                        acc += Ak[a + b * DDYN_NX] * v[b];
                    }
                    w[a] = acc;
                }
                memcpy(v, w, sizeof v);
            }
        }
    }
}

#define DDYN_MPC_MIN_LAUNCH_ACCEL 1e-6 /* m/s^2: a car that cannot gain speed here (a steep hill) */

/* How fast the car can gain speed from x0: the prediction model's dvx/dt at full throttle, driving straight
 * (vy = omega = steering = 0), with the coefficients the prediction uses; 0 when the model gives no finite
 * positive value (then the references follow the line's speed alone). The acceleration falls with speed (drag),
 * so the value at x0's speed bounds what the car gains over the horizon. */
static double launch_accel(ddyn_mpc *mpc, const double x0[DDYN_NX])
{
    double x[DDYN_NX] = {0.0}, u[DDYN_NU] = {0.0}, xdot[DDYN_NX], buf[DDYN_NC];
    x[3] = x0[3] > 0.0 ? x0[3] : 0.0;
    x[6] = mpc->cfg.state_hi[0];
    if (ddyn_model_derivatives(mpc->model, x, u, ddyn_model_coeffs_at(mpc->c, mpc->downforce, x[3], buf), xdot, &mpc->model_work) != DDYN_OK || !isfinite(xdot[3]) ||
        !(xdot[3] > 0.0)) {
        return 0.0;
    }
    /* on a grade, gravity at x0's position (linearise's first stage) speeds the car up or holds it back: a
     * downhill start bounded by the level road's rate held the cost points behind a car the told prediction
     * saw pass them (random:304, 0.05 rad hills: the QP at its cap, the car spun). A hill steeper than the
     * car can climb at this speed holds the cost points at its speed (a tiny rate), not unbounded at the line's */
    xdot[3] += ddyn_model_grade_accel(mpc->stage_grade[0]);
    return xdot[3] > DDYN_MPC_MIN_LAUNCH_ACCEL ? xdot[3] : DDYN_MPC_MIN_LAUNCH_ACCEL;
}

/* cost references along the raceline's speed profile, and track half-planes at the projections of
 * the linearisation trajectory's positions. The cost point moves on at the line's speed, but no faster than
 * the car could reach from vx0 at `accel` (launch_accel; 0: no such bound): a car far below its line's speed
 * (a flying line's first lap from standstill) is otherwise pulled towards points it cannot reach, around the
 * next bend, and steers across the track at walking pace to cut to them. A car on its line's speed profile
 * is never held back (the line accelerates no faster than the model); one a little below it is held to what it
 * can gain (laps without an effect moved by at most 16 ms; results/sil_loop.json has the case it cost). */
static void references(ddyn_mpc *mpc, int i0, double u0, double vx0, double accel)
{
    const ddyn_mpc_track *t = &mpc->track;
    const double dt = mpc->model->sample_time;
    const double v0 = vx0 > 0.0 ? vx0 : 0.0;
    int k, i = i0, ic = i0;
    double u = u0;
    for (k = 0; k <= mpc->cfg.horizon; ++k) {
        double *r = mpc->ref + k * 8, uc, v;
        track_point p = track_at(t, i, u), c;
        r[0] = p.x;
        r[1] = p.y;
        mpc->ref_tangent[2 * k] = p.tx;
        mpc->ref_tangent[2 * k + 1] = p.ty;
        v = p.speed; /* over interval k the car is at most at v0 + accel (k + 1) dt */
        if (accel > 0.0 && v > v0 + accel * (double)(k + 1) * dt) {
            v = v0 + accel * (double)(k + 1) * dt;
        }
        advance(t, &i, &u, v * dt);
        ic = project(t, mpc->x_lin[k * DDYN_NX], mpc->x_lin[k * DDYN_NX + 1], ic, k == 0 ? LOCAL_WINDOW : STAGE_WINDOW, &uc);
        c = track_at(t, ic, uc);
        r[2] = c.x;
        r[3] = c.y;
        r[4] = -c.ty; /* left normal */
        r[5] = c.tx;
        r[6] = c.wl;
        r[7] = c.wr;
    }
}

/* Row j (an even index: the throttle after stage j / 2 + 1) of the integrator rows relaxed to +-`span` times
 * the throttle range's width */
static void relax_throttle_row(ddyn_mpc *mpc, int j, double span)
{
    const double state_w = mpc->cfg.state_hi[0] - mpc->cfg.state_lo[0];
    mpc->qp.hard_lo[j] = -state_w * span;
    mpc->qp.hard_hi[j] = state_w * span;
}

/* Take throttle column j (an even z index) out of the QP built by build_qp (lower triangle only, before
 * mirroring): it keeps only its own diagonal weight 2 r_rate weight, no gradient (a fixed throttle's cost is a
 * constant), no entry in the track rows, its box relaxed to +-the rate bounds' width and its integrator row
 * to +-`span` times the throttle range's width. */
static void take_out_throttle_column(ddyn_mpc *mpc, int j, double weight, double span)
{
    const ddyn_mpc_config *cfg = &mpc->cfg;
    const int h = cfg->horizon, n = 2 * h;
    ddyn_mpc_qp *qp = &mpc->qp;
    const double rate_w = cfg->rate_hi[0] - cfg->rate_lo[0];
    int i, q;
    for (i = 0; i < n; ++i) {
        if (i > j) {
            qp->hess[i + j * DDYN_QP_NV] = 0.0; /* column j below the diagonal */
        } else if (i < j) {
            qp->hess[j + i * DDYN_QP_NV] = 0.0; /* row j left of the diagonal */
        }
    }
    qp->hess[j + j * DDYN_QP_NV] = 2.0 * cfg->r_rate[0] * weight;
    qp->grad[j] = 0.0;
    qp->lb[j] = -rate_w;
    qp->ub[j] = rate_w;
    relax_throttle_row(mpc, j, span);
    for (q = 0; q < h; ++q) {
        qp->soft_row[q * DDYN_QP_NV + j] = 0.0;
    }
}

/* Throttle held: every throttle column taken out (take_out_throttle_column, span 1).
 * The QP then separates into the steering problem (exactly the one of a steering-only MPC) and a throttle
 * block whose optimum is z = 0, strictly inside its relaxed rows; the caller uses the fixed throttle rates,
 * not z. */
static void hold_throttle_columns(ddyn_mpc *mpc)
{
    int j;
    for (j = 0; j < 2 * mpc->cfg.horizon; j += 2) {
        take_out_throttle_column(mpc, j, 1.0, 1.0);
    }
}

/* Known throttle rates of the first fix_n stages (ddyn_mpc_fix_throttle): their columns taken out
 * (take_out_throttle_column; the integrator rows of the stages they alone reach relaxed), with a weight
 * that keeps them at 0 where a later stage's integrator row pulls on them; the plan uses the known rates,
 * not z. */
static void fix_throttle_columns(ddyn_mpc *mpc)
{
    int k;
    for (k = 0; k < mpc->fix_n && k < mpc->cfg.horizon; ++k) {
        take_out_throttle_column(mpc, 2 * k, DDYN_MPC_FIX_WEIGHT, (double)(k + 1));
    }
}

/* condensed QP in the deviations z = u - u_lin */
static void build_qp(ddyn_mpc *mpc, const double x0[DDYN_NX], int hold)
{
    const ddyn_mpc_config *cfg = &mpc->cfg;
    const int h = cfg->horizon, n = 2 * h;
    const double dt = mpc->model->sample_time;
    ddyn_mpc_qp *qp = &mpc->qp;
    int i, j, k, ch;
    qp->horizon = h;
    qp->dt = dt;
    qp->rho1 = cfg->slack_l1;
    qp->rho2 = cfg->slack_l2;
    for (j = 0; j < n; ++j) {
        double rj = cfg->r_rate[j % DDYN_NU];
        for (i = 0; i < n; ++i) {
            qp->hess[i + j * DDYN_QP_NV] = 0.0;
        }
        qp->hess[j + j * DDYN_QP_NV] = 2.0 * rj;
        qp->grad[j] = 2.0 * rj * mpc->u_lin[j];
        qp->lb[j] = cfg->rate_lo[j % DDYN_NU] - mpc->u_lin[j];
        qp->ub[j] = cfg->rate_hi[j % DDYN_NU] - mpc->u_lin[j];
    }
    for (k = 1; k <= h; ++k) {
        const double *sx = mpc->sens + (k - 1) * 2 * n, *sy = sx + n, *r = mpc->ref + k * 8;
        const double *xk = mpc->x_lin + k * DDYN_NX;
        double w = k == h ? cfg->q_terminal_scale : 1.0;
        double qx = 2.0 * w * cfg->q_pos[0], qy = 2.0 * w * cfg->q_pos[1];
        double ex = xk[0] - r[0], ey = xk[1] - r[1], off;
        int len = 2 * k;
        double *g = qp->soft_row + (k - 1) * DDYN_QP_NV;
        for (j = 0; j < len; ++j) {
            double ax = qx * sx[j], ay = qy * sy[j];
            for (i = j; i < len; ++i) {
                qp->hess[i + j * DDYN_QP_NV] += ax * sx[i] + ay * sy[i];
            }
            qp->grad[j] += ax * ex + ay * ey;
            g[j] = r[4] * sx[j] + r[5] * sy[j];
        }
        for (j = len; j < n; ++j) {
            g[j] = 0.0;
        }
        /* track bound: -room_right <= n . (p - anchor) <= room_left, soft */
        off = r[4] * (xk[0] - r[2]) + r[5] * (xk[1] - r[3]);
        qp->soft_hi[k - 1] = r[6] - off;
        qp->soft_lo[k - 1] = -r[7] - off;
        /* throttle, steering (states 6, 7: exact integrators of the rates) within their bounds, the
         * bounds widened to what the rate limits can reach when x0 itself lies outside them */
        for (ch = 0; ch < 2; ++ch) {
            double lo = fmin(cfg->state_lo[ch], x0[6 + ch] + k * dt * cfg->rate_hi[ch]);
            double hi = fmax(cfg->state_hi[ch], x0[6 + ch] + k * dt * cfg->rate_lo[ch]);
            qp->hard_lo[2 * (k - 1) + ch] = lo - xk[6 + ch];
            qp->hard_hi[2 * (k - 1) + ch] = hi - xk[6 + ch];
        }
    }
    if (hold) {
        hold_throttle_columns(mpc);
    } else if (mpc->fix_n > 0) {
        fix_throttle_columns(mpc);
    }
    for (j = 0; j < n; ++j) { /* mirror the lower triangle */
        for (i = j + 1; i < n; ++i) {
            qp->hess[j + i * DDYN_QP_NV] = qp->hess[i + j * DDYN_QP_NV];
        }
    }
}

/* what the returned plan violates of the hard bounds, and its objective */
static void plan_info(const ddyn_mpc *mpc, ddyn_mpc_info *info)
{
    const ddyn_mpc_qp *qp = &mpc->qp;
    const int h = mpc->cfg.horizon, n = 2 * h;
    double viol = 0.0, cost = 0.0, acc[2] = {0.0, 0.0};
    int i, j, k;
    for (i = 0; i < n; ++i) {
        double hz = 0.0;
        viol = fmax(viol, fmax(qp->z[i] - qp->ub[i], qp->lb[i] - qp->z[i]));
        for (j = 0; j < n; ++j) {
            hz += qp->hess[i + j * DDYN_QP_NV] * qp->z[j];
        }
        cost += qp->z[i] * (0.5 * hz + qp->grad[i]);
    }
    for (k = 1; k <= h; ++k) {
        for (j = 0; j < 2; ++j) {
            int r = 2 * (k - 1) + j;
            acc[j] += qp->z[r];
            viol = fmax(viol, fmax(qp->dt * acc[j] - qp->hard_hi[r], qp->hard_lo[r] - qp->dt * acc[j]));
        }
        info->max_slack = fmax(info->max_slack, qp->slack[k - 1]);
        cost += qp->rho1 * qp->slack[k - 1] + qp->rho2 * qp->slack[k - 1] * qp->slack[k - 1];
    }
    info->max_bound_violation = viol;
    info->cost = cost;
    info->qp_iterations = qp->iterations;
    info->converged = qp->converged;
    info->kkt_residual = qp->residual;
}

/* d(x, y)_k / dx0 for k = 1..H: rows x, y of A_{k-1} ... A_0 (A column-major), by propagating the
 * product forward one stage at a time: H products of an 8x8 by an 8x8, done in the preparation */
static void state_sensitivities(ddyn_mpc *mpc)
{
    double P[DDYN_NX * DDYN_NX], Q[DDYN_NX * DDYN_NX];
    int k, a, b, c;
    memset(P, 0, sizeof P);
    for (a = 0; a < DDYN_NX; ++a) {
        P[a + a * DDYN_NX] = 1.0;
    }
    for (k = 1; k <= mpc->cfg.horizon; ++k) {
        const double *Ak = mpc->A + (k - 1) * DDYN_NX * DDYN_NX;
        double *row = mpc->phi + (k - 1) * 2 * DDYN_NX;
        for (b = 0; b < DDYN_NX; ++b) {
            for (a = 0; a < DDYN_NX; ++a) {
                double acc = 0.0;
                for (c = 0; c < DDYN_NX; ++c) {
                    acc += Ak[a + c * DDYN_NX] * P[c + b * DDYN_NX];
                }
                Q[a + b * DDYN_NX] = acc;
            }
        }
        memcpy(P, Q, sizeof P);
        for (b = 0; b < DDYN_NX; ++b) {
            row[b] = P[0 + b * DDYN_NX];
            row[DDYN_NX + b] = P[1 + b * DDYN_NX];
        }
    }
}

static ddyn_status prepare(ddyn_mpc *mpc, const double x0[DDYN_NX], int hold, double dthrottle0, int split)
{
    ddyn_status st;
    double u0;
    if (mpc == NULL || x0 == NULL || mpc->model == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    mpc->prepared = 0;
    if (!ddyn_all_finite(x0, DDYN_NX)) {
        return DDYN_ERR_NONFINITE_INPUT;
    }
    if (mpc->track.n < 4 || !mpc->have_coefficients) {
        return DDYN_ERR_NOT_READY;
    }
    mpc->prep_index = project(&mpc->track, x0[0], x0[1], mpc->last_index, LOCAL_WINDOW, &u0);
    mpc->prep_u0 = u0;
    st = linearise(mpc, x0, hold, dthrottle0);
    if (st != DDYN_OK) {
        ddyn_mpc_qp_daqp_reset(&mpc->daqp); /* a period without a QP: its working set no longer fits */
        return st;
    }
    sensitivities(mpc);
    /* with the throttle held, a speed controller outside the MPC (the PID) pursues the line's speed: the cost
     * points follow the line as that controller's reference does, unbounded (bounded, the steering was planned
     * for a car slower than the PID drives it: ETHZMobil's PID laps left the track, test_av21_putnam) */
    references(mpc, mpc->prep_index, u0, x0[3], hold ? 0.0 : launch_accel(mpc, x0));
    build_qp(mpc, x0, hold);
    /* DAQP starts cold without a plan to continue (its working set belongs to that plan) or without a
     * working set; the feedback then runs the interior point instead, which needs no factorisation */
    mpc->prep_cold = !mpc->have_warm_start || mpc->daqp.warm_h != mpc->cfg.horizon;
    if (mpc->cfg.qp_solver == DDYN_MPC_QP_DAQP && !mpc->prep_cold) {
        /* DAQP's factorisation reads only what the feedback leaves alone: done here, before the
         * measurement (its failure is reported by the feedback's solve) */
        (void)ddyn_mpc_qp_daqp_factor(&mpc->qp, &mpc->daqp);
    }
    if (split && !hold) {
        state_sensitivities(mpc); /* only a feedback at another state needs them: not in ddyn_mpc_solve */
    }
    memcpy(mpc->prep_x0, x0, sizeof mpc->prep_x0);
    mpc->prep_hold = hold;
    mpc->prep_movable = split && !hold; /* only with the sensitivities can the QP be moved to another x0 */
    mpc->prepared = 1;
    return DDYN_OK;
}

/* Move the prepared QP from x0_pred to x0: positions to first order through d(x, y)_k / dx0 (the
 * cost's gradient and the track rows), throttle and steering exactly (they are integrators of the
 * rates, so d x_k[6..7] / dx0 is the identity on them). */
static void shift_to(ddyn_mpc *mpc, const double x0[DDYN_NX])
{
    const ddyn_mpc_config *cfg = &mpc->cfg;
    const int h = cfg->horizon, n = 2 * h;
    const double dt = mpc->model->sample_time;
    ddyn_mpc_qp *qp = &mpc->qp;
    double dx[DDYN_NX], ds;
    int i, j, k, ch;
    for (i = 0; i < DDYN_NX; ++i) {
        dx[i] = x0[i] - mpc->prep_x0[i];
    }
    /* the cost's reference points start at x0's projection on the raceline: moving x0 along the
     * line by ds moves every reference point along it by ds too (to first order) */
    ds = dx[0] * mpc->ref_tangent[0] + dx[1] * mpc->ref_tangent[1];
    for (k = 1; k <= h; ++k) {
        const double *px = mpc->phi + (k - 1) * 2 * DDYN_NX, *py = px + DDYN_NX;
        const double *sx = mpc->sens + (k - 1) * 2 * n, *sy = sx + n, *r = mpc->ref + k * 8;
        const double *xk = mpc->x_lin + k * DDYN_NX;
        double w = k == h ? cfg->q_terminal_scale : 1.0;
        double qx = 2.0 * w * cfg->q_pos[0], qy = 2.0 * w * cfg->q_pos[1], ddx = 0.0, ddy = 0.0, doff;
        for (i = 0; i < DDYN_NX; ++i) {
            ddx += px[i] * dx[i];
            ddy += py[i] * dx[i];
        }
        for (j = 0; j < 2 * k; ++j) {
            qp->grad[j] += qx * sx[j] * (ddx - ds * mpc->ref_tangent[2 * k]) +
                           qy * sy[j] * (ddy - ds * mpc->ref_tangent[2 * k + 1]);
        }
        for (j = 0; j < 2 * mpc->fix_n && j < 2 * k; j += 2) {
            qp->grad[j] = 0.0; /* known throttle rates: no gradient (fix_throttle_columns) */
        }
        doff = r[4] * ddx + r[5] * ddy;
        qp->soft_hi[k - 1] -= doff;
        qp->soft_lo[k - 1] -= doff;
        for (ch = 0; ch < 2; ++ch) {
            double lo = fmin(cfg->state_lo[ch], x0[6 + ch] + k * dt * cfg->rate_hi[ch]);
            double hi = fmax(cfg->state_hi[ch], x0[6 + ch] + k * dt * cfg->rate_lo[ch]);
            qp->hard_lo[2 * (k - 1) + ch] = lo - (xk[6 + ch] + dx[6 + ch]);
            qp->hard_hi[2 * (k - 1) + ch] = hi - (xk[6 + ch] + dx[6 + ch]);
        }
    }
    /* the known throttle stages' rows stay relaxed, as fix_throttle_columns built them (issue 34: rewritten
     * here, the bound the known throttle is at or beyond made the QP move their columns, which the plan then
     * replaces by the known rates: the free throttle was planned for another throttle, capped QPs and
     * throttle limit cycles at 120 ms, docs/sil.md) */
    for (k = 0; k < mpc->fix_n && k < h; ++k) {
        relax_throttle_row(mpc, 2 * k, (double)(k + 1));
    }
}

/* Every refusal leaves a defined answer: u = {0, 0} (hold throttle and steering) and a zero info. */
static ddyn_status clear_outputs(const ddyn_mpc *mpc, const double *x0, double *u, ddyn_mpc_info *info)
{
    if (info != NULL) {
        memset(info, 0, sizeof *info);
    }
    if (u != NULL) {
        u[0] = 0.0;
        u[1] = 0.0;
    }
    return mpc == NULL || x0 == NULL || u == NULL || mpc->model == NULL ? DDYN_ERR_ARGUMENT : DDYN_OK;
}

static ddyn_status feedback(ddyn_mpc *mpc, const double x0[DDYN_NX], double u[DDYN_NU], ddyn_mpc_info *info)
{
    ddyn_mpc_info local;
    ddyn_status qst;
    int k, j, h, hold, moved = 0;
    double u0;
    if (info == NULL) {
        info = &local;
    }
    if (clear_outputs(mpc, x0, u, info) != DDYN_OK) {
        return DDYN_ERR_ARGUMENT;
    }
    if (!ddyn_all_finite(x0, DDYN_NX)) {
        return DDYN_ERR_NONFINITE_INPUT;
    }
    if (!mpc->prepared) {
        return DDYN_ERR_NOT_READY;
    }
    mpc->prepared = 0; /* one feedback per preparation: the QP is modified in place */
    hold = mpc->prep_hold;
    for (k = 0; k < DDYN_NX; ++k) {
        moved |= x0[k] != mpc->prep_x0[k];
    }
    if (moved) {
        if (!mpc->prep_movable) {
            return DDYN_ERR_NOT_READY; /* prepared by a whole iteration, or with the throttle held: solved where built */
        }
        shift_to(mpc, x0);
    }
    h = mpc->cfg.horizon;
    if (moved) {
        info->track_index = project(&mpc->track, x0[0], x0[1], mpc->prep_index, LOCAL_WINDOW, &u0);
    } else {
        info->track_index = mpc->prep_index;
        u0 = mpc->prep_u0;
    }
    info->progress = track_at(&mpc->track, info->track_index, u0).s;
    if (mpc->cfg.qp_solver == DDYN_MPC_QP_DAQP && !mpc->prep_cold) {
        /* warm start: the last solve's working set one stage on */
        /* (at the cap DAQP drops its working set: the next period starts cold, below) */
        qst = ddyn_mpc_qp_daqp_solve_factored(&mpc->qp, &mpc->daqp, mpc->cfg.qp_max_iterations, 1);
    } else if (mpc->cfg.qp_solver == DDYN_MPC_QP_DAQP) {
        /* A cold active-set start adds about one constraint per iteration and can need more than the cap
         * (the first QPs from a standstill, the QPs after a recovery: 40-60 active constraints, up to
         * ~120 iterations). The interior point's iteration count does not depend on a start: it solves
         * this QP with its own cap (a bounded cost, measured on the M7: docs/m7.md), and the constraints
         * active at its solution start DAQP's next solve, so that the warm chain starts right. (Before,
         * a capped cold DAQP solve was solved again by the interior point: both costs in one period.) */
        ddyn_mpc_qp_daqp_reset(&mpc->daqp);
        qst = ddyn_mpc_qp_solve(&mpc->qp, mpc->cfg.qp_cold_max_iterations, mpc->cfg.qp_tolerance);
        if (qst == DDYN_OK || qst == DDYN_ERR_QP_NOT_CONVERGED) {
            ddyn_mpc_qp_daqp_seed(&mpc->daqp, &mpc->qp);
        }
        info->qp_cold_start = 1;
    } else {
        qst = ddyn_mpc_qp_solve(&mpc->qp, mpc->cfg.qp_max_iterations, mpc->cfg.qp_tolerance);
    }
    if (qst != DDYN_OK && qst != DDYN_ERR_QP_NOT_CONVERGED) {
        return qst; /* malformed QP (non-finite sensitivities): keep the old plan */
    }
    plan_info(mpc, info);
    for (k = 0; k < h; ++k) {
        for (j = 0; j < DDYN_NU; ++j) {
            int idx = k * DDYN_NU + j;
            /* held throttle, known throttle rates: the fixed rates */
            double z = (hold || (j == 0 && k < mpc->fix_n)) && j == 0 ? 0.0 : mpc->qp.z[idx];
            mpc->u_plan[idx] = clip(mpc->u_lin[idx] + z, mpc->cfg.rate_lo[j], mpc->cfg.rate_hi[j]);
        }
    }
    memcpy(mpc->x_plan, x0, DDYN_NX * sizeof(double));
    mpc->have_warm_start = 1;
    mpc->last_index = info->track_index;
    u[0] = mpc->u_plan[0];
    u[1] = mpc->u_plan[1];
    return qst;
}

static ddyn_status solve(ddyn_mpc *mpc, const double x0[DDYN_NX], int hold, double dthrottle0, double u[DDYN_NU],
                         ddyn_mpc_info *info)
{
    ddyn_status st;
    if (clear_outputs(mpc, x0, u, info) != DDYN_OK) {
        return DDYN_ERR_ARGUMENT;
    }
    st = prepare(mpc, x0, hold, dthrottle0, 0);
    if (st != DDYN_OK) {
        return st;
    }
    return feedback(mpc, x0, u, info);
}

ddyn_status ddyn_mpc_prepare(ddyn_mpc *mpc, const double x0_pred[DDYN_NX])
{
    return prepare(mpc, x0_pred, 0, 0.0, 1);
}

ddyn_status ddyn_mpc_feedback(ddyn_mpc *mpc, const double x0[DDYN_NX], double u[DDYN_NU], ddyn_mpc_info *info)
{
    return feedback(mpc, x0, u, info);
}

ddyn_status ddyn_mpc_solve(ddyn_mpc *mpc, const double x0[DDYN_NX], double u[DDYN_NU], ddyn_mpc_info *info)
{
    return solve(mpc, x0, 0, 0.0, u, info);
}

ddyn_status ddyn_mpc_solve_held_throttle(ddyn_mpc *mpc, const double x0[DDYN_NX], double dthrottle0,
                                         double u[DDYN_NU], ddyn_mpc_info *info)
{
    if (!isfinite(dthrottle0)) {
        if (info != NULL) {
            memset(info, 0, sizeof *info);
        }
        if (u != NULL) {
            u[0] = 0.0;
            u[1] = 0.0;
        }
        return mpc == NULL || x0 == NULL || u == NULL ? DDYN_ERR_ARGUMENT : DDYN_ERR_NONFINITE_INPUT;
    }
    return solve(mpc, x0, 1, dthrottle0, u, info);
}

ddyn_status ddyn_mpc_reference_speed(const ddyn_mpc *mpc, const double x0[DDYN_NX], double ahead, double *speed)
{
    double u0;
    int i0;
    if (speed != NULL) {
        *speed = 0.0;
    }
    if (mpc == NULL || x0 == NULL || speed == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    if (mpc->track.n < 4) {
        return DDYN_ERR_NOT_READY;
    }
    if (!isfinite(x0[0]) || !isfinite(x0[1]) || !isfinite(ahead)) {
        return DDYN_ERR_NONFINITE_INPUT;
    }
    i0 = project(&mpc->track, x0[0], x0[1], mpc->last_index, LOCAL_WINDOW, &u0);
    if (ahead > 0.0) {
        advance(&mpc->track, &i0, &u0, ahead);
    }
    *speed = track_at(&mpc->track, i0, u0).speed;
    return DDYN_OK;
}

int ddyn_mpc_plan_inputs(const ddyn_mpc *mpc, double *u_plan)
{
    if (mpc == NULL || u_plan == NULL || !mpc->have_warm_start) {
        return 0;
    }
    memcpy(u_plan, mpc->u_plan, (size_t)(mpc->cfg.horizon * DDYN_NU) * sizeof(double));
    return mpc->cfg.horizon;
}

int ddyn_mpc_plan(ddyn_mpc *mpc, double *x_plan, double *u_plan)
{
    int h, k;
    if (mpc == NULL || !mpc->have_warm_start) {
        return 0;
    }
    h = mpc->cfg.horizon;
    for (k = 0; k < h; ++k) {
        const double road[2] = {mpc->stage_bank[k], mpc->stage_grade[k]};
        if (predict(mpc, mpc->x_plan + k * DDYN_NX, mpc->u_plan + k * DDYN_NU, road,
                    mpc->x_plan + (k + 1) * DDYN_NX, NULL, NULL) != DDYN_OK) {
            return 0;
        }
    }
    if (x_plan != NULL) {
        memcpy(x_plan, mpc->x_plan, (size_t)((h + 1) * DDYN_NX) * sizeof(double));
    }
    if (u_plan != NULL) {
        memcpy(u_plan, mpc->u_plan, (size_t)(h * DDYN_NU) * sizeof(double));
    }
    return h;
}
