/*
 * ddyn/mpc_qp.h - the condensed QP of the MPC and its dense interior-point solver (used by mpc.c;
 * public only so that ddyn_mpc can hold it by value and the tests can drive it directly).
 *
 *   min  1/2 z'Hz + f'z + sum_q (rho1 s_q + rho2 s_q^2)      z: 2H input-rate deviations,
 *   s.t. lb <= z <= ub                                         s: H track slacks
 *        hard_lo[r] <= dt * sum_{j<k} z[2j+ch] <= hard_hi[r]   r = 2(k-1)+ch, k = 1..H
 *                                                              (throttle, steering: integrators)
 *        soft_lo[q] - s_q <= g_q' z <= soft_hi[q] + s_q,  s_q >= 0,   q = 0..H-1, g_q has its
 *                                                              nonzeros in the first 2(q+1) entries
 *                                                              (the solver sets the rest of its row to 0)
 *
 * Primal-dual interior point (Mehrotra predictor-corrector) with an infeasible start: each
 * iteration forms the n x n reduced Newton matrix from the structure above (the integrator rows
 * by suffix sums, the slacks eliminated in closed form), factors it by Cholesky and solves twice.
 * The objective is scaled internally to unit mean Hessian diagonal; results are unscaled.
 */
#ifndef DDYN_MPC_QP_H
#define DDYN_MPC_QP_H

#include "ddyn/model.h"

#ifdef __cplusplus
extern "C" {
#endif

#ifndef DDYN_MPC_MAX_HORIZON
#define DDYN_MPC_MAX_HORIZON 20
#endif
#define DDYN_QP_NV (2 * DDYN_MPC_MAX_HORIZON)                   /* input-rate variables */
#define DDYN_QP_NS DDYN_MPC_MAX_HORIZON                         /* soft rows and slacks */
#define DDYN_QP_NCON (4 * DDYN_QP_NV + 3 * DDYN_QP_NS)          /* one-sided inequalities */

typedef struct {
    /* problem (filled by the caller) */
    int horizon;
    double dt;
    double hess[DDYN_QP_NV * DDYN_QP_NV]; /* column-major, symmetric, positive definite */
    double grad[DDYN_QP_NV];
    double lb[DDYN_QP_NV], ub[DDYN_QP_NV];
    double hard_lo[DDYN_QP_NV], hard_hi[DDYN_QP_NV];
    double soft_row[DDYN_QP_NS * DDYN_QP_NV]; /* row q at [q * DDYN_QP_NV] */
    double soft_lo[DDYN_QP_NS], soft_hi[DDYN_QP_NS];
    double rho1, rho2;
    /* solution */
    double z[DDYN_QP_NV];
    double slack[DDYN_QP_NS];
    int iterations;
    int converged;
    double residual;      /* max of scaled primal and dual residuals and mean complementarity */
    /* work */
    double t[DDYN_QP_NCON], lam[DDYN_QP_NCON], d[DDYN_QP_NCON], w[DDYN_QP_NCON];
    double dt_aff[DDYN_QP_NCON], dl_aff[DDYN_QP_NCON], cz[DDYN_QP_NCON], rp[DDYN_QP_NCON];
    double rd[DDYN_QP_NV + DDYN_QP_NS], dz[DDYN_QP_NV + DDYN_QP_NS];
    double kkt[DDYN_QP_NV * DDYN_QP_NV]; /* Cholesky factor U (K = U'U), upper triangle row-major, 2H x 2H */
} ddyn_mpc_qp;

/* Solve with at most max_iterations iterations, stopping at tolerance tol. Returns DDYN_OK,
 * DDYN_ERR_QP_NOT_CONVERGED (z, slack hold the last iterate, finite) or DDYN_ERR_ARGUMENT /
 * DDYN_ERR_NONFINITE_INPUT for a malformed problem (z, slack are then zero). */
ddyn_status ddyn_mpc_qp_solve(ddyn_mpc_qp *qp, int max_iterations, double tol);

/* After a solve: which side of two-sided constraint c is active at the last iterate (its multiplier
 * exceeds its slack): +1 upper, -1 lower, 0 neither. c numbers the constraints as DAQP's path does
 * (mpc_qp_daqp.c): [0, n) the bounds of z, [n, 2n) the integrator rows, [2n, 2n + H) the soft rows. */
int ddyn_mpc_qp_active_side(const ddyn_mpc_qp *qp, int c);

/* The solver's linear algebra, exposed for the tests: with D (length DDYN_QP_NCON, the barrier
 * weights lambda / t of the inequalities in the order of mpc_qp.c) and the objective scale, forms the
 * reduced Newton matrix K = scale H + C_z'D C_z - (slack elimination) in qp->kkt and factors it,
 * K = U'U (returns the number of regularised pivots); the solve overwrites b (length 2H) by K^-1 b. */
int ddyn_mpc_qp_newton_factor(ddyn_mpc_qp *qp, const double *D, double scale);
void ddyn_mpc_qp_newton_solve(const ddyn_mpc_qp *qp, double *b);

#ifdef __cplusplus
}
#endif

#endif /* DDYN_MPC_QP_H */
