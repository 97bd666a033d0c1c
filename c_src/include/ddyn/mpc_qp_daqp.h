/*
 * ddyn/mpc_qp_daqp.h - the MPC's condensed QP (ddyn/mpc_qp.h) solved by DAQP (dual active set,
 * D. Arnström, MIT licence), on a workspace laid out here for the MPC's fixed sizes: no allocation.
 *
 * Only DAQP's solver core is linked (daqp.c, auxiliary.c, factorization.c of the pinned sdist
 * daqp==0.11.0, fetched and hash-checked by cmake/daqp.cmake); its setup (api.c, utils.c) allocates
 * and is replaced by mpc_qp_daqp.c, which forms the dual (LDP) problem itself:
 *   variables z (n = 2H), simple bounds lb <= z <= ub (ms = n),
 *   general rows: the n integrator rows (hard_lo, hard_hi), then the H soft track rows g_q'z in
 *   [soft_lo, soft_hi] as DAQP soft constraints with the MPC's penalty rho1 s + rho2 s^2 per side.
 * The working set of a solve is kept and, shifted one stage, starts the next one (the warm start);
 * ddyn_mpc_qp_daqp_reset makes the next solve start cold.
 *
 * DDYN_QP_FLOAT32 (CMake option of the same name) builds DAQP and this workspace in float32.
 */
#ifndef DDYN_MPC_QP_DAQP_H
#define DDYN_MPC_QP_DAQP_H

#include "ddyn/mpc_qp.h"

#ifdef __cplusplus
extern "C" {
#endif

#ifdef DDYN_QP_FLOAT32
typedef float ddyn_qp_real; /* must be DAQP's c_float: DAQP_SINGLE_PRECISION is set with it */
#else
typedef double ddyn_qp_real;
#endif

#define DDYN_DAQP_N DDYN_QP_NV                        /* variables */
#define DDYN_DAQP_MG (DDYN_QP_NV + DDYN_QP_NS)         /* general rows: integrators, soft rows */
#define DDYN_DAQP_M (DDYN_DAQP_N + DDYN_DAQP_MG)       /* all constraints */
#define DDYN_DAQP_WS (DDYN_DAQP_N + DDYN_QP_NS + 1)    /* working set capacity (DAQP: n + soft + 1) */

typedef struct {
    /* the QP in DAQP's form (row-major), rebuilt every solve */
    ddyn_qp_real A[DDYN_DAQP_MG * DDYN_DAQP_N];
    ddyn_qp_real bupper[DDYN_DAQP_M], blower[DDYN_DAQP_M];
    /* the LDP: inverse Cholesky factor (packed upper, row-major), M = A Rinv, d, v = Rinv' f */
    ddyn_qp_real Rinv[DDYN_DAQP_N * (DDYN_DAQP_N + 1) / 2];
    ddyn_qp_real M[DDYN_DAQP_MG * DDYN_DAQP_N];
    ddyn_qp_real dupper[DDYN_DAQP_M], dlower[DDYN_DAQP_M], scaling[DDYN_DAQP_M];
    ddyn_qp_real v[DDYN_DAQP_N], Mu[DDYN_DAQP_MG];
    ddyn_qp_real soft_w[4 * DDYN_DAQP_M]; /* rho_l, rho_u, w_l, w_u per constraint (0 = hard) */
    /* iterates and the LDL' factor of the working set */
    ddyn_qp_real u[DDYN_DAQP_N], xold[DDYN_DAQP_N];
    ddyn_qp_real lam[DDYN_DAQP_WS], lam_star[DDYN_DAQP_WS];
    ddyn_qp_real L[DDYN_DAQP_WS * (DDYN_DAQP_WS + 1) / 2], D[DDYN_DAQP_WS];
    ddyn_qp_real xldl[DDYN_DAQP_WS], zldl[DDYN_DAQP_WS];
    int sense[DDYN_DAQP_M], WS[DDYN_DAQP_WS];
    /* warm start: the last solve's working set (constraint ids with their side) for horizon warm_h */
    int warm_id[DDYN_DAQP_WS], warm_lower[DDYN_DAQP_WS];
    int warm_n, warm_h;
    int exitflag;  /* DAQP's exit flag of the last solve (1 optimal, 2 soft optimal, < 0 failed) */
    int cold;      /* 1 if the last solve started cold */
    /* the factorisation (ddyn_mpc_qp_daqp_factor) the next solve_factored uses */
    int zero_row[DDYN_DAQP_MG];
    int ill;
    int factored_h; /* horizon factored, 0 = none */
    ddyn_status factor_status;
} ddyn_mpc_qp_daqp;

/* The next solve starts cold (after a fault, a reset of the MPC, or a failed solve). */
void ddyn_mpc_qp_daqp_reset(ddyn_mpc_qp_daqp *w);

/* Solve qp (the problem fields of ddyn_mpc_qp) with at most max_iterations DAQP iterations, warm
 * started from the previous solve's working set shifted by shift stages (1 for the next control
 * period, 0 for the same QP again). Returns and fills qp->z, slack, iterations, converged, residual
 * (the largest violation of a hard constraint) like ddyn_mpc_qp_solve:
 *   DDYN_OK (DAQP optimal), DDYN_ERR_QP_NOT_CONVERGED (iteration cap: z is the last finite primal
 *   iterate, or 0; the next solve starts cold), other DAQP failures (cycling, infeasible: the next
 *   solve starts cold), DDYN_ERR_ARGUMENT /
 *   DDYN_ERR_NONFINITE_INPUT for a malformed problem (z, slack zero; next solve cold). */
ddyn_status ddyn_mpc_qp_daqp_solve(ddyn_mpc_qp *qp, ddyn_mpc_qp_daqp *w, int max_iterations, int shift);

/* The solve in two parts, for the real-time iteration's split (docs/controller.md): the factor reads
 * only what the feedback phase leaves alone (H, the soft rows, dt, the penalty) and forms Rinv and M;
 * solve_factored then reads the gradient and the bounds (which the feedback moves to the measured
 * state) and runs DAQP. ddyn_mpc_qp_daqp_solve = factor + solve_factored. The factor returns DDYN_OK,
 * DDYN_ERR_NONFINITE_INPUT or DDYN_ERR_ARGUMENT (H not positive definite); solve_factored returns that
 * error again (z zero, next solve cold) if the factorisation failed or is missing, else as
 * ddyn_mpc_qp_daqp_solve. One solve_factored per factor. */
ddyn_status ddyn_mpc_qp_daqp_factor(const ddyn_mpc_qp *qp, ddyn_mpc_qp_daqp *w);
ddyn_status ddyn_mpc_qp_daqp_solve_factored(ddyn_mpc_qp *qp, ddyn_mpc_qp_daqp *w, int max_iterations, int shift);

/* The next solve starts from the constraints active at qp's interior-point solution
 * (ddyn_mpc_qp_active_side), in this solve's stage numbering (the next period shifts them as usual). */
void ddyn_mpc_qp_daqp_seed(ddyn_mpc_qp_daqp *w, const ddyn_mpc_qp *qp);

/* For the worst-case measurement (tests/m7): make the next solve start from a wrong working set,
 * the upper bounds of every stage but the last active, which DAQP must take apart one constraint per
 * iteration. */
void ddyn_mpc_qp_daqp_adversarial_start(ddyn_mpc_qp_daqp *w, int horizon);

#ifdef __cplusplus
}
#endif

#endif /* DDYN_MPC_QP_DAQP_H */
