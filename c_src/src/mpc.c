/* ddyn MPC: configuration, parameters, raceline table and the real-time-iteration step (see ddyn/mpc.h). */
#include "ddyn/mpc.h"
#include "ddyn_mpc_limits.h"

#include <math.h>
#include <stddef.h>
#include <string.h>

static int all_finite(const double *v, int n)
{
    int i;
    for (i = 0; i < n; ++i) {
        if (!isfinite(v[i])) {
            return 0;
        }
    }
    return 1;
}

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
    cfg->disc = DDYN_DISC_RK4;
    for (j = 0; j < DDYN_NU; ++j) {
        cfg->rate_lo[j] = ddyn_mpc_limits[i].lo_hi[j][0];
        cfg->rate_hi[j] = ddyn_mpc_limits[i].lo_hi[j][1];
        cfg->state_lo[j] = ddyn_mpc_limits[i].lo_hi[2 + j][0];
        cfg->state_hi[j] = ddyn_mpc_limits[i].lo_hi[2 + j][1];
    }
    cfg->q_pos[0] = 1.0;
    cfg->q_pos[1] = 1.0;
    cfg->q_terminal_scale = 1.0;
    cfg->r_rate[0] = 1e-4;
    cfg->r_rate[1] = 1e-4;
    cfg->slack_l1 = 100.0;
    cfg->slack_l2 = 1000.0;
    cfg->qp_max_iterations = 30;
    cfg->qp_tolerance = 1e-8;
    return DDYN_OK;
}

static int config_valid(const ddyn_mpc_config *cfg)
{
    int j;
    if (cfg->horizon < 1 || cfg->horizon > DDYN_MPC_MAX_HORIZON || (unsigned)cfg->disc >= (unsigned)DDYN_DISC_COUNT ||
        cfg->qp_max_iterations < 1 || cfg->qp_max_iterations > DDYN_MPC_MAX_QP_ITERATIONS) {
        return 0;
    }
    if (!all_finite(cfg->q_pos, 2) || !all_finite(cfg->r_rate, DDYN_NU) || !isfinite(cfg->q_terminal_scale) ||
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
    if (mpc == NULL || model == NULL || cfg == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    if (!config_valid(cfg)) {
        return DDYN_ERR_ARGUMENT;
    }
    memset(mpc, 0, sizeof *mpc);
    mpc->model = model;
    mpc->cfg = *cfg;
    return DDYN_OK;
}

ddyn_status ddyn_mpc_set_coefficients(ddyn_mpc *mpc, const double c[DDYN_NC])
{
    if (mpc == NULL || c == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    if (!all_finite(c, DDYN_NC)) {
        return DDYN_ERR_NONFINITE_INPUT;
    }
    memcpy(mpc->c, c, sizeof mpc->c);
    mpc->have_coefficients = 1;
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
    if (!all_finite(x, n) || !all_finite(y, n) || !all_finite(speed, n) || !all_finite(width_left, n) ||
        !all_finite(width_right, n)) {
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
    ddyn_mpc_reset(mpc);
    return DDYN_OK;
}

void ddyn_mpc_reset(ddyn_mpc *mpc)
{
    if (mpc == NULL) {
        return;
    }
    mpc->have_warm_start = 0;
    mpc->last_index = -1;
    memset(mpc->u_plan, 0, sizeof mpc->u_plan);
}

int ddyn_mpc_plan(const ddyn_mpc *mpc, double *x_plan, double *u_plan)
{
    int h;
    if (mpc == NULL || !mpc->have_warm_start) {
        return 0;
    }
    h = mpc->cfg.horizon;
    if (x_plan != NULL) {
        memcpy(x_plan, mpc->x_plan, (size_t)((h + 1) * DDYN_NX) * sizeof(double));
    }
    if (u_plan != NULL) {
        memcpy(u_plan, mpc->u_plan, (size_t)(h * DDYN_NU) * sizeof(double));
    }
    return h;
}

ddyn_status ddyn_mpc_solve(ddyn_mpc *mpc, const double x0[DDYN_NX], double u[DDYN_NU], ddyn_mpc_info *info)
{
    if (u != NULL) {
        u[0] = 0.0;
        u[1] = 0.0;
    }
    if (info != NULL) {
        memset(info, 0, sizeof *info);
    }
    if (mpc == NULL || x0 == NULL || u == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    if (!all_finite(x0, DDYN_NX)) {
        return DDYN_ERR_NONFINITE_INPUT;
    }
    /* skeleton (API commit): the real-time iteration follows in the next commit */
    return DDYN_ERR_NOT_READY;
}
