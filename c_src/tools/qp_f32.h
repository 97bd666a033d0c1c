/* qp_f32.h - the float32 build of the MPC's QP solver (qp_f32.c), for ddyn_qp_replay. Arrays laid out as in
 * ddyn_mpc_qp (DDYN_QP_NV strides); returns 1 when converged. */
#ifndef DDYN_QP_F32_H
#define DDYN_QP_F32_H

int qp_f32_solve(int horizon, double dt, double rho1, double rho2, const double *hess, const double *grad,
                 const double *lb, const double *ub, const double *hard_lo, const double *hard_hi,
                 const double *soft_row, const double *soft_lo, const double *soft_hi, int max_iterations,
                 double tol, double *z, double *slack, int *iterations);

#endif
