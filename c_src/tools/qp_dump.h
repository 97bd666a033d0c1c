/*
 * qp_dump.h - one condensed MPC QP (ddyn_mpc_qp) as a record of little-endian doubles (host tools:
 * ddyn_mpc_lap writes them, ddyn_qp_replay and train/bench/qp.py read them). With n = 2H, m = H:
 *   H, dt, rho1, rho2, iterations, converged,
 *   hess (n x n, column-major), grad (n), lb (n), ub (n), hard_lo (n), hard_hi (n),
 *   soft_row (m rows of n), soft_lo (m), soft_hi (m), z (n), slack (m)
 */
#ifndef DDYN_QP_DUMP_H
#define DDYN_QP_DUMP_H

#include <stdio.h>
#include <string.h>

#include "ddyn/mpc_qp.h"

static inline int qp_dump_put(FILE *f, const double *v, int n)
{
    return fwrite(v, sizeof *v, (size_t)n, f) == (size_t)n;
}

static inline int qp_dump_write(FILE *f, const ddyn_mpc_qp *qp)
{
    const int m = qp->horizon, n = 2 * m;
    double head[6];
    int ok = 1, j;
    head[0] = m;
    head[1] = qp->dt;
    head[2] = qp->rho1;
    head[3] = qp->rho2;
    head[4] = qp->iterations;
    head[5] = qp->converged;
    ok &= qp_dump_put(f, head, 6);
    for (j = 0; j < n; ++j) {
        ok &= qp_dump_put(f, qp->hess + j * DDYN_QP_NV, n);
    }
    ok &= qp_dump_put(f, qp->grad, n) & qp_dump_put(f, qp->lb, n) & qp_dump_put(f, qp->ub, n);
    ok &= qp_dump_put(f, qp->hard_lo, n) & qp_dump_put(f, qp->hard_hi, n);
    for (j = 0; j < m; ++j) {
        ok &= qp_dump_put(f, qp->soft_row + j * DDYN_QP_NV, n);
    }
    ok &= qp_dump_put(f, qp->soft_lo, m) & qp_dump_put(f, qp->soft_hi, m);
    ok &= qp_dump_put(f, qp->z, n) & qp_dump_put(f, qp->slack, m);
    return ok;
}

/* the problem part of a record into qp (the rest zeroed); 0 at the end of the file or on a bad record */
static inline int qp_dump_read(FILE *f, ddyn_mpc_qp *qp)
{
    double head[6], row[DDYN_QP_NV];
    int m, n, j;
    if (fread(head, sizeof *head, 6, f) != 6) {
        return 0;
    }
    m = (int)head[0];
    n = 2 * m;
    if (m < 1 || m > DDYN_MPC_MAX_HORIZON) {
        return 0;
    }
    memset(qp, 0, sizeof *qp);
    qp->horizon = m;
    qp->dt = head[1];
    qp->rho1 = head[2];
    qp->rho2 = head[3];
    for (j = 0; j < n; ++j) {
        if (fread(qp->hess + j * DDYN_QP_NV, sizeof(double), (size_t)n, f) != (size_t)n) {
            return 0;
        }
    }
    if (fread(qp->grad, sizeof(double), (size_t)n, f) != (size_t)n ||
        fread(qp->lb, sizeof(double), (size_t)n, f) != (size_t)n ||
        fread(qp->ub, sizeof(double), (size_t)n, f) != (size_t)n ||
        fread(qp->hard_lo, sizeof(double), (size_t)n, f) != (size_t)n ||
        fread(qp->hard_hi, sizeof(double), (size_t)n, f) != (size_t)n) {
        return 0;
    }
    for (j = 0; j < m; ++j) {
        if (fread(qp->soft_row + j * DDYN_QP_NV, sizeof(double), (size_t)n, f) != (size_t)n) {
            return 0;
        }
    }
    if (fread(qp->soft_lo, sizeof(double), (size_t)m, f) != (size_t)m ||
        fread(qp->soft_hi, sizeof(double), (size_t)m, f) != (size_t)m ||
        fread(row, sizeof(double), (size_t)n, f) != (size_t)n ||
        fread(row, sizeof(double), (size_t)m, f) != (size_t)m) {
        return 0;
    }
    return 1;
}

#endif /* DDYN_QP_DUMP_H */
