/*
 * qp_f32.c - the MPC's QP solver (c_src/src/mpc_qp.c) compiled with float instead of double, for the
 * float32 accuracy comparison of ddyn_qp_replay only (docs/m7.md): every double of the solver,
 * its struct and its constants becomes float (a mechanical port; the 1e-300 floors underflow to 0).
 */
#include <math.h>
#include <string.h>

typedef double qp_f64;

#define double float
#define ddyn_mpc_qp ddyn_mpc_qp_f32
#define ddyn_mpc_qp_solve ddyn_mpc_qp_solve_f32
#define ddyn_mpc_qp_newton_factor ddyn_mpc_qp_newton_factor_f32
#define ddyn_mpc_qp_newton_solve ddyn_mpc_qp_newton_solve_f32
#define ddyn_mpc_qp_active_side ddyn_mpc_qp_active_side_f32
#include "../src/mpc_qp.c"
#undef double

#include "qp_f32.h"

static ddyn_mpc_qp_f32 qp32;

int qp_f32_solve(int horizon, qp_f64 dt, qp_f64 rho1, qp_f64 rho2, const qp_f64 *hess, const qp_f64 *grad,
                 const qp_f64 *lb, const qp_f64 *ub, const qp_f64 *hard_lo, const qp_f64 *hard_hi,
                 const qp_f64 *soft_row, const qp_f64 *soft_lo, const qp_f64 *soft_hi, int max_iterations,
                 qp_f64 tol, qp_f64 *z, qp_f64 *slack, int *iterations)
{
    int i;
    memset(&qp32, 0, sizeof qp32);
    qp32.horizon = horizon;
    qp32.dt = (float)dt;
    qp32.rho1 = (float)rho1;
    qp32.rho2 = (float)rho2;
    for (i = 0; i < DDYN_QP_NV * DDYN_QP_NV; ++i) {
        qp32.hess[i] = (float)hess[i];
    }
    for (i = 0; i < DDYN_QP_NS * DDYN_QP_NV; ++i) {
        qp32.soft_row[i] = (float)soft_row[i];
    }
    for (i = 0; i < DDYN_QP_NV; ++i) {
        qp32.grad[i] = (float)grad[i];
        qp32.lb[i] = (float)lb[i];
        qp32.ub[i] = (float)ub[i];
        qp32.hard_lo[i] = (float)hard_lo[i];
        qp32.hard_hi[i] = (float)hard_hi[i];
    }
    for (i = 0; i < DDYN_QP_NS; ++i) {
        qp32.soft_lo[i] = (float)soft_lo[i];
        qp32.soft_hi[i] = (float)soft_hi[i];
    }
    i = ddyn_mpc_qp_solve_f32(&qp32, max_iterations, (float)tol) == DDYN_OK;
    for (int k = 0; k < DDYN_QP_NV; ++k) {
        z[k] = qp32.z[k];
    }
    for (int k = 0; k < DDYN_QP_NS; ++k) {
        slack[k] = qp32.slack[k];
    }
    *iterations = qp32.iterations;
    return i;
}
