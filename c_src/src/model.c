/* ddyn model wrapper: input checks and fixed-size work memory around the generated model. */
#include "ddyn/model.h"
#include "ddyn_models.h"

#include <math.h>
#include <stddef.h>
#include <string.h>

/* 1 when every one of v[0..n) is finite (the runtime modules' shared NaN/inf guard). */
int ddyn_all_finite(const double *v, int n)
{
    int i;
    for (i = 0; i < n; ++i) {
        if (!isfinite(v[i])) {
            return 0;
        }
    }
    return 1;
}

static ddyn_status check_args(const ddyn_vehicle_model *model, const double *x, const double *u, const double *c,
                              const ddyn_model_work *work)
{
    if (model == NULL || x == NULL || u == NULL || c == NULL || work == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    if (!ddyn_all_finite(x, DDYN_NX) || !ddyn_all_finite(u, DDYN_NU) || !ddyn_all_finite(c, DDYN_NC)) {
        return DDYN_ERR_NONFINITE_INPUT;
    }
    return DDYN_OK;
}

/* Evaluate a generated function with up to three outputs into scratch space, then
 * copy the outputs only if all are finite, so a failed call leaves results untouched. */
static ddyn_status evaluate(ddyn_casadi_fn fn, const double *x, const double *u, const double *c, double *const out[3],
                            const int out_len[3], ddyn_model_work *work)
{
    double scratch[DDYN_NX * (DDYN_NX + DDYN_NU + DDYN_NC)];
    double *res[3];
    const double *arg[3];
    int offset = 0;
    int k;
    arg[0] = x;
    arg[1] = u;
    arg[2] = c;
    for (k = 0; k < 3; ++k) {
        res[k] = out_len[k] > 0 ? scratch + offset : NULL;
        offset += out_len[k];
    }
    if (fn(arg, res, work->iw, work->w, 0) != 0) {
        return DDYN_ERR_EVALUATION;
    }
    if (!ddyn_all_finite(scratch, offset)) {
        return DDYN_ERR_NONFINITE_OUTPUT;
    }
    offset = 0;
    for (k = 0; k < 3; ++k) {
        if (out[k] != NULL && out_len[k] > 0) {
            memcpy(out[k], scratch + offset, (size_t)out_len[k] * sizeof(double));
        }
        offset += out_len[k];
    }
    return DDYN_OK;
}

const ddyn_vehicle_model *ddyn_model_find(const char *name)
{
    int i;
    if (name == NULL) {
        return NULL;
    }
    for (i = 0; i < DDYN_MODEL_COUNT; ++i) {
        if (strcmp(ddyn_models[i]->name, name) == 0) {
            return ddyn_models[i];
        }
    }
    return NULL;
}

ddyn_status ddyn_model_step(const ddyn_vehicle_model *model, ddyn_discretisation disc, const double x[DDYN_NX],
                            const double u[DDYN_NU], const double c[DDYN_NC], double x_next[DDYN_NX],
                            ddyn_model_work *work)
{
    double *out[3];
    const int len[3] = {DDYN_NX, 0, 0};
    ddyn_status s = check_args(model, x, u, c, work);
    if (s != DDYN_OK) {
        return s;
    }
    if (x_next == NULL || (unsigned)disc >= (unsigned)DDYN_DISC_COUNT) {
        return DDYN_ERR_ARGUMENT;
    }
    out[0] = x_next;
    out[1] = NULL;
    out[2] = NULL;
    return evaluate(model->step[disc], x, u, c, out, len, work);
}

ddyn_status ddyn_model_step_jacobians(const ddyn_vehicle_model *model, ddyn_discretisation disc,
                                      const double x[DDYN_NX], const double u[DDYN_NU], const double c[DDYN_NC],
                                      double A[DDYN_NX * DDYN_NX], double B[DDYN_NX * DDYN_NU],
                                      double P[DDYN_NX * DDYN_NC], ddyn_model_work *work)
{
    double *out[3];
    const int len[3] = {DDYN_NX * DDYN_NX, DDYN_NX * DDYN_NU, DDYN_NX * DDYN_NC};
    ddyn_status s = check_args(model, x, u, c, work);
    if (s != DDYN_OK) {
        return s;
    }
    if ((unsigned)disc >= (unsigned)DDYN_DISC_COUNT) {
        return DDYN_ERR_ARGUMENT;
    }
    out[0] = A;
    out[1] = B;
    out[2] = P;
    return evaluate(model->step_jac[disc], x, u, c, out, len, work);
}

ddyn_status ddyn_model_derivatives(const ddyn_vehicle_model *model, const double x[DDYN_NX], const double u[DDYN_NU],
                                   const double c[DDYN_NC], double xdot[DDYN_NX], ddyn_model_work *work)
{
    double *out[3];
    const int len[3] = {DDYN_NX, 0, 0};
    ddyn_status s = check_args(model, x, u, c, work);
    if (s != DDYN_OK) {
        return s;
    }
    if (xdot == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    out[0] = xdot;
    out[1] = NULL;
    out[2] = NULL;
    return evaluate(model->deriv, x, u, c, out, len, work);
}

int ddyn_meas_dim(ddyn_meas_kind kind)
{
    static const int dims[DDYN_MEAS_COUNT] = DDYN_MEAS_DIMS;
    return (unsigned)kind < (unsigned)DDYN_MEAS_COUNT ? dims[kind] : 0;
}

ddyn_status ddyn_model_measure(const ddyn_vehicle_model *model, ddyn_meas_kind kind, const double x[DDYN_NX],
                               const double c[DDYN_NC], double h[DDYN_MEAS_MAX_DIM],
                               double H[DDYN_MEAS_MAX_DIM * DDYN_NX], ddyn_model_work *work)
{
    static const double no_input[DDYN_NU] = {0.0, 0.0};
    double *out[3];
    int len[3];
    int dim = ddyn_meas_dim(kind);
    ddyn_status s = check_args(model, x, no_input, c, work);
    if (s != DDYN_OK) {
        return s;
    }
    if (dim == 0 || h == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    /* the generated measurement functions take (x, c): pass c in the second argument slot */
    out[0] = h;
    out[1] = H;
    out[2] = NULL;
    len[0] = dim;
    len[1] = dim * DDYN_NX;
    len[2] = 0;
    return evaluate(model->meas[kind], x, c, NULL, out, len, work);
}

void ddyn_model_downforce(const double c[DDYN_NC], double k, double vx, double out[DDYN_NC])
{
    double scale;
    if (out != c) {
        memcpy(out, c, DDYN_NC * sizeof *c);
    }
    if (k == 0.0) {
        return; /* bit-identical without it */
    }
    scale = 1.0 + k * vx * vx;
    out[DDYN_MODEL_DF_INDEX] *= scale;
    out[DDYN_MODEL_DR_INDEX] *= scale;
}

const double *ddyn_model_coeffs_at(const double c[DDYN_NC], double k, double vx, double buf[DDYN_NC])
{
    if (k == 0.0) {
        return c; /* no copy on the hot path without a downforce */
    }
    ddyn_model_downforce(c, k, vx, buf);
    return buf;
}

double ddyn_model_bank_accel(double bank) { return DDYN_GRAVITY * sin(bank); }

double ddyn_model_grade_accel(double grade) { return -DDYN_GRAVITY * sin(grade); }

/* a body-frame acceleration (along, left of the heading), held over dt, added to a step's x_next exactly */
static void add_body_accel(double a_along, double a_left, double dt, const double x[DDYN_NX],
                           double x_next[DDYN_NX])
{
    const double c = cos(x[2]), s = sin(x[2]), h_along = 0.5 * a_along * dt * dt, h_left = 0.5 * a_left * dt * dt;
    x_next[0] += h_along * c - h_left * s; /* the heading (c, s), its left normal (-s, c) */
    x_next[1] += h_along * s + h_left * c;
    x_next[3] += a_along * dt;
    x_next[4] += a_left * dt;
}

void ddyn_model_add_grade(double grade, double dt, const double x[DDYN_NX], double x_next[DDYN_NX])
{
    if (x != NULL && x_next != NULL && grade != 0.0) {
        add_body_accel(ddyn_model_grade_accel(grade), 0.0, dt, x, x_next);
    }
}

void ddyn_model_add_bank(double bank, double dt, const double x[DDYN_NX], double x_next[DDYN_NX])
{
    if (x != NULL && x_next != NULL && bank != 0.0) {
        add_body_accel(0.0, ddyn_model_bank_accel(bank), dt, x, x_next);
    }
}
