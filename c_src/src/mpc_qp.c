/* Dense primal-dual interior-point solver of the MPC's condensed QP (see ddyn/mpc_qp.h).
 *
 * Inequalities C [z; s] <= d, one-sided, in this order (n = 2H, ns = H):
 *   [0, n)          z_i <= ub_i                  [n, 2n)        -z_i <= -lb_i
 *   [2n, 3n)        a_r <= hard_hi_r             [3n, 4n)       -a_r <= -hard_lo_r
 *   [4n, 4n+ns)     g_q'z - s_q <= soft_hi_q     [4n+ns, 4n+2ns) -g_q'z - s_q <= -soft_lo_q
 *   [4n+2ns, 4n+3ns) -s_q <= 0
 * with a_r = dt * sum_{j<k} z[2j+ch] for r = 2(k-1)+ch. Each iteration solves the Newton system
 * reduced to z: (H + C'DC) restricted to z after eliminating s, D = lambda / t. */
#include "ddyn/mpc_qp.h"

#include <math.h>
#include <string.h>

#define REG_PIVOT 1e-12 /* Cholesky pivots below this (relative) are replaced: keeps the factor finite */
#define STEP_FRACTION 0.99

typedef struct {
    int n, ns, h;
    int o_lb, o_hup, o_hlo, o_sup, o_slo, o_sg, m;
} layout;

static layout make_layout(int h)
{
    layout l;
    l.h = h;
    l.n = 2 * h;
    l.ns = h;
    l.o_lb = l.n;
    l.o_hup = 2 * l.n;
    l.o_hlo = 3 * l.n;
    l.o_sup = 4 * l.n;
    l.o_slo = 4 * l.n + l.ns;
    l.o_sg = 4 * l.n + 2 * l.ns;
    l.m = 4 * l.n + 3 * l.ns;
    return l;
}

static int soft_len(int q) { return 2 * (q + 1); }

/* out = C [z; s] */
static void mul_c(const ddyn_mpc_qp *qp, const layout *l, const double *z, const double *s, double *out)
{
    int i, k, q;
    for (i = 0; i < l->n; ++i) {
        out[i] = z[i];
        out[l->o_lb + i] = -z[i];
    }
    for (i = 0; i < 2; ++i) {
        double acc = 0.0;
        for (k = 1; k <= l->h; ++k) {
            int r = 2 * (k - 1) + i;
            acc += z[2 * (k - 1) + i];
            out[l->o_hup + r] = qp->dt * acc;
            out[l->o_hlo + r] = -qp->dt * acc;
        }
    }
    for (q = 0; q < l->ns; ++q) {
        const double *g = qp->soft_row + q * DDYN_QP_NV;
        double acc = 0.0;
        int len = soft_len(q);
        for (i = 0; i < len; ++i) {
            acc += g[i] * z[i];
        }
        out[l->o_sup + q] = acc - s[q];
        out[l->o_slo + q] = -acc - s[q];
        out[l->o_sg + q] = -s[q];
    }
}

/* (oz, os) = C' v */
static void mul_ct(const ddyn_mpc_qp *qp, const layout *l, const double *v, double *oz, double *os)
{
    int i, k, q;
    for (i = 0; i < l->n; ++i) {
        oz[i] = v[i] - v[l->o_lb + i];
    }
    for (i = 0; i < 2; ++i) {
        double suffix = 0.0;
        for (k = l->h; k >= 1; --k) {
            int r = 2 * (k - 1) + i;
            suffix += v[l->o_hup + r] - v[l->o_hlo + r];
            oz[2 * (k - 1) + i] += qp->dt * suffix; /* z[2j+i] enters every row with stage k > j */
        }
    }
    for (q = 0; q < l->ns; ++q) {
        const double *g = qp->soft_row + q * DDYN_QP_NV;
        double wq = v[l->o_sup + q] - v[l->o_slo + q];
        int len = soft_len(q);
        for (i = 0; i < len; ++i) {
            oz[i] += g[i] * wq;
        }
        os[q] = -v[l->o_sup + q] - v[l->o_slo + q] - v[l->o_sg + q];
    }
}

/* dot product of two contiguous vectors, four partial sums (the compiler may not reorder one sum) */
static double dot(const double *restrict a, const double *restrict b, int n)
{
    double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0;
    int k = 0;
    for (; k + 4 <= n; k += 4) {
        s0 += a[k] * b[k];
        s1 += a[k + 1] * b[k + 1];
        s2 += a[k + 2] * b[k + 2];
        s3 += a[k + 3] * b[k + 3];
    }
    for (; k < n; ++k) {
        s0 += a[k] * b[k];
    }
    return (s0 + s1) + (s2 + s3);
}

/* y += a x over contiguous memory: no reduction, so the compiler vectorises it without reassociating */
static void axpy(double *restrict y, const double *restrict x, double a, int n)
{
    int k;
    for (k = 0; k < n; ++k) {
        y[k] += a * x[k];
    }
}

/* y += a0 x0, then y += a1 x1, in one pass over y (the same roundings as two axpy calls in that order;
 * on the Cortex-M7 one load and one store of y per two multiply-adds) */
static void axpy2(double *restrict y, const double *restrict x0, double a0, const double *restrict x1, double a1,
                  int n)
{
    int k;
    for (k = 0; k < n; ++k) {
        y[k] = (y[k] + a0 * x0[k]) + a1 * x1[k];
    }
}

/* Two weighted sums down the rows of a row-major matrix M (row stride `stride`), over `rows` rows, for
 * the columns j = 0..3 of m (= &M[0][j0]) at once, with the weights of row r at c[r * cstride] and
 * c[r * cstride + 1]:
 *   acc0[j] = sum_r c[r cstride] m[r stride + j],   acc1[j] = sum_r c[r cstride + 1] m[r stride + j].
 * The factorisation's inner kernel: per row two weights and four entries loaded for eight multiply-adds,
 * the eight sums in registers. */
static void sum2x4(const double *restrict m, int stride, const double *restrict c, int cstride, int rows,
                   double acc0[4], double acc1[4])
{
    double a0 = 0.0, a1 = 0.0, a2 = 0.0, a3 = 0.0, b0 = 0.0, b1 = 0.0, b2 = 0.0, b3 = 0.0;
    const double *const end = c + rows * cstride;
    for (; c < end; c += cstride) {
        const double u = c[0], v = c[1], m0 = m[0], m1 = m[1], m2 = m[2], m3 = m[3];
        a0 += u * m0;
        a1 += u * m1;
        a2 += u * m2;
        a3 += u * m3;
        b0 += v * m0;
        b1 += v * m1;
        b2 += v * m2;
        b3 += v * m3;
        m += stride;
    }
    acc0[0] = a0;
    acc0[1] = a1;
    acc0[2] = a2;
    acc0[3] = a3;
    acc1[0] = b0;
    acc1[1] = b1;
    acc1[2] = b2;
    acc1[3] = b3;
}

/* the same for two columns (the last block of a row pair when n - i is not a multiple of four) */
static void sum2x2(const double *restrict m, int stride, const double *restrict c, int cstride, int rows,
                   double acc0[4], double acc1[4])
{
    double a0 = 0.0, a1 = 0.0, b0 = 0.0, b1 = 0.0;
    const double *const end = c + rows * cstride;
    for (; c < end; c += cstride) {
        const double u = c[0], v = c[1], m0 = m[0], m1 = m[1];
        a0 += u * m0;
        a1 += u * m1;
        b0 += v * m0;
        b1 += v * m1;
        m += stride;
    }
    acc0[0] = a0;
    acc0[1] = a1;
    acc1[0] = b0;
    acc1[1] = b1;
}

/* row i of K formed in y (columns i..n-1): scaled Hessian, box and integrator rows; the integrator term
 * (every other column from i on) added in the same pass over the row pairs (2p, 2p + 1) */
static void form_row(const ddyn_mpc_qp *qp, const layout *l, const double *D, double scale,
                     double suffix[2][DDYN_MPC_MAX_HORIZON], int i, double *restrict y)
{
    const double *restrict hcol = qp->hess + i * DDYN_QP_NV; /* H symmetric: column i is row i */
    const double *restrict sfx = suffix[i & 1];
    const int a = i / 2;
    int p;
    y[i] = (hcol[i] * scale + (D[i] + D[l->o_lb + i])) + sfx[a];
    if ((i & 1) == 0) { /* column i + 1 of the first pair: not an integrator column of row i */
        y[i + 1] = hcol[i + 1] * scale;
    }
    if (i & 1) {
        for (p = a + 1; p < l->h; ++p) {
            y[2 * p] = hcol[2 * p] * scale;
            y[2 * p + 1] = hcol[2 * p + 1] * scale + sfx[p];
        }
    } else {
        for (p = a + 1; p < l->h; ++p) {
            y[2 * p] = hcol[2 * p] * scale + sfx[p];
            y[2 * p + 1] = hcol[2 * p + 1] * scale;
        }
    }
}

/* the pivot of row i (regularised when too small; counted in *regularised), row i scaled by it */
static void finish_row(double *restrict y, int i, int n, double ref, int *regularised)
{
    double pivot = y[i], d, inv;
    int j;
    if (!(pivot > REG_PIVOT * (fabs(ref) + 1.0))) {
        pivot = REG_PIVOT * (fabs(ref) + 1.0);
        ++*regularised;
    }
    d = sqrt(pivot);
    inv = 1.0 / d;
    y[i] = d;
    for (j = i + 1; j < n; ++j) {
        y[j] *= inv;
    }
}

int ddyn_mpc_qp_newton_factor(ddyn_mpc_qp *qp, const double *D, double scale)
{
    double *K = qp->kkt;
    double suffix[2][DDYN_MPC_MAX_HORIZON], wsoft[DDYN_QP_NS], cs[DDYN_QP_NS][2];
    const layout lay = make_layout(qp->horizon);
    const layout *l = &lay;
    int n = l->n, i, j, k, q, ch, regularised = 0;
    /* integrator rows of channel ch: entry (2a+ch, 2b+ch) gets dt^2 * sum_{k > max(a, b)} W_k */
    for (ch = 0; ch < 2; ++ch) {
        double acc = 0.0;
        for (k = l->h; k >= 1; --k) {
            int r = 2 * (k - 1) + ch;
            acc += D[l->o_hup + r] + D[l->o_hlo + r];
            suffix[ch][k - 1] = qp->dt * qp->dt * acc;
        }
    }
    /* soft rows, slack eliminated: rank-one terms with weight Da + Db - (Db - Da)^2 / (2 rho2 + Da + Db + Dc) */
    for (q = 0; q < l->ns; ++q) {
        double da = D[l->o_sup + q], db = D[l->o_slo + q], dc = D[l->o_sg + q];
        double mq = 2.0 * qp->rho2 * scale + da + db + dc;
        wsoft[q] = da + db - (db - da) * (db - da) / mq;
    }
    /* Two rows at a time, i and i + 1 (n = 2H is even; upper triangle, ROW-major: element (i, j), j >= i,
     * at [i*n + j]): form both rows of K, add the soft rows' rank-one terms, eliminate both against the
     * finished rows of U above (left-looking Cholesky, K = U'U), finish row i, eliminate row i + 1 against
     * it, finish row i + 1. The sums run down the rows (sum2x4: four columns of both rows at once, the
     * partial results in registers), so that the Cortex-M7 loads 1.5 operands per multiply-add instead
     * of 2.5 plus a store (streaming along the rows, four rows at a time, before). Only the rounding of the
     * sums differs (their order). Row i + 1's entry in column i (lower triangle) is computed and dropped. */
    for (i = 0; i < n; i += 2) {
        double *restrict y0 = K + i * n, *restrict y1 = y0 + n;
        double ref0 = 0.0, ref1 = 0.0, acc0[4], acc1[4], u01;
        const int a = i / 2; /* both rows: soft row q reaches columns i and i + 1 when q >= i / 2 */
        form_row(qp, l, D, scale, suffix, i, y0);
        form_row(qp, l, D, scale, suffix, i + 1, y1);
        /* soft row q's entries from 2(q + 1) on are zero (explicit: ddyn_mpc_qp_solve), so columns j..j+3
         * need the rows q >= j / 2 */
        for (q = a; q < l->ns; ++q) {
            cs[q][0] = wsoft[q] * qp->soft_row[q * DDYN_QP_NV + i]; /* the two rows' weights side by side */
            cs[q][1] = wsoft[q] * qp->soft_row[q * DDYN_QP_NV + i + 1];
        }
        for (j = i; j < n; j += 4) {
            const int q0 = j / 2, w = n - j >= 4 ? 4 : 2;
            if (w == 4) {
                sum2x4(qp->soft_row + q0 * DDYN_QP_NV + j, DDYN_QP_NV, cs[q0], 2, l->ns - q0, acc0, acc1);
            } else {
                sum2x2(qp->soft_row + q0 * DDYN_QP_NV + j, DDYN_QP_NV, cs[q0], 2, l->ns - q0, acc0, acc1);
            }
            for (k = 0; k < w; ++k) {
                y0[j + k] += acc0[k];
                y1[j + k] += acc1[k];
            }
            if (j == i) {
                ref0 = y0[i];
                ref1 = y1[i + 1];
            }
            /* the rows of U above: y_j -= sum_{k < i} U_ki U_kj (and U_k,i+1 U_kj) */
            if (i > 0) {
                if (w == 4) {
                    sum2x4(K + j, n, K + i, n, i, acc0, acc1); /* U_ki, U_k,i+1 side by side */
                } else {
                    sum2x2(K + j, n, K + i, n, i, acc0, acc1);
                }
                for (k = 0; k < w; ++k) {
                    y0[j + k] -= acc0[k];
                    y1[j + k] -= acc1[k];
                }
            }
        }
        finish_row(y0, i, n, ref0, &regularised);
        u01 = y0[i + 1];
        for (j = i + 1; j < n; ++j) {
            y1[j] -= u01 * y0[j];
        }
        finish_row(y1, i + 1, n, ref1, &regularised);
    }
    return regularised;
}

void ddyn_mpc_qp_newton_solve(const ddyn_mpc_qp *qp, double *b)
{
    const double *U = qp->kkt;
    int n = 2 * qp->horizon, i;
    for (i = 0; i + 1 < n; i += 2) { /* U' y = b, by columns of U' (rows of U): axpy, two rows per pass */
        const double *u0 = U + i * n, *u1 = u0 + n;
        b[i] /= u0[i];
        b[i + 1] = (b[i + 1] + -b[i] * u0[i + 1]) / u1[i + 1];
        axpy2(b + i + 2, u0 + i + 2, -b[i], u1 + i + 2, -b[i + 1], n - i - 2);
    }
    if (i < n) {
        b[i] /= U[i * n + i];
    }
    for (i = n - 1; i >= 0; --i) { /* U x = y, by rows of U: dot */
        b[i] = (b[i] - dot(U + i * n + i + 1, b + i + 1, n - i - 1)) / U[i * n + i];
    }
}

/* Newton direction for complementarity target rc (t .* lam - rc = 0), given as rcl = rc ./ lam (one
 * division per row, done once by the caller): dz (z and s parts), dlam, dt. */
static void newton(ddyn_mpc_qp *qp, const layout *l, const double *D, const double *rcl, double scale, double *dz,
                   double *dlam, double *dt)
{
    double vz[DDYN_QP_NV], vs[DDYN_QP_NS], mq[DDYN_QP_NS], beta[DDYN_QP_NS];
    int i, q, n = l->n;
    for (i = 0; i < l->m; ++i) {
        qp->w[i] = D[i] * (qp->rp[i] - rcl[i]);
    }
    mul_ct(qp, l, qp->w, vz, vs);
    for (i = 0; i < n; ++i) {
        dz[i] = -qp->rd[i] - vz[i];
    }
    for (q = 0; q < l->ns; ++q) {
        const double *g = qp->soft_row + q * DDYN_QP_NV;
        double da = D[l->o_sup + q], db = D[l->o_slo + q], dc = D[l->o_sg + q];
        int len = soft_len(q);
        mq[q] = 2.0 * qp->rho2 * scale + da + db + dc;
        beta[q] = db - da;
        dz[n + q] = -qp->rd[n + q] - vs[q];
        axpy(dz, g, -beta[q] * dz[n + q] / mq[q], len);
    }
    ddyn_mpc_qp_newton_solve(qp, dz);
    for (q = 0; q < l->ns; ++q) {
        const double *g = qp->soft_row + q * DDYN_QP_NV;
        double gz = 0.0;
        int len = soft_len(q);
        for (i = 0; i < len; ++i) {
            gz += g[i] * dz[i];
        }
        dz[n + q] = (dz[n + q] - beta[q] * gz) / mq[q];
    }
    mul_c(qp, l, dz, dz + n, qp->cz);
    for (i = 0; i < l->m; ++i) {
        dlam[i] = D[i] * (qp->cz[i] + qp->rp[i] - rcl[i]);
        dt[i] = -qp->rp[i] - qp->cz[i];
    }
}

/* largest step in (0, 1] keeping t + a dt >= 0 and lam + a dlam >= 0 (both in one pass) */
static double max_step(const double *t, const double *dt, const double *lam, const double *dlam, int m)
{
    double a = 1.0;
    int i;
    for (i = 0; i < m; ++i) {
        if (dt[i] < 0.0) {
            double ai = -t[i] / dt[i];
            if (ai < a) {
                a = ai;
            }
        }
        if (dlam[i] < 0.0) {
            double ai = -lam[i] / dlam[i];
            if (ai < a) {
                a = ai;
            }
        }
    }
    return a;
}

static double inf_norm(const double *v, int n)
{
    double m = 0.0;
    int i;
    for (i = 0; i < n; ++i) {
        if (fabs(v[i]) > m) {
            m = fabs(v[i]);
        }
    }
    return m;
}

/* residuals at the current iterate (scaled objective); returns the convergence measure */
static double residuals(ddyn_mpc_qp *qp, const layout *l, double scale, double dnorm, double fnorm, double *mu)
{
    int i, j, q, n = l->n;
    double gap = 0.0, rp, rd, hz[DDYN_QP_NV];
    mul_c(qp, l, qp->z, qp->slack, qp->cz);
    for (i = 0; i < l->m; ++i) {
        qp->rp[i] = qp->cz[i] + qp->t[i] - qp->d[i];
        gap += qp->t[i] * qp->lam[i];
    }
    mul_ct(qp, l, qp->lam, qp->rd, qp->rd + n);
    for (i = 0; i < n; ++i) {
        hz[i] = qp->grad[i];
    }
    for (j = 0; j + 1 < n; j += 2) { /* H z + f by columns of H: axpy, two columns per pass */
        axpy2(hz, qp->hess + j * DDYN_QP_NV, qp->z[j], qp->hess + (j + 1) * DDYN_QP_NV, qp->z[j + 1], n);
    }
    if (j < n) {
        axpy(hz, qp->hess + j * DDYN_QP_NV, qp->z[j], n);
    }
    for (i = 0; i < n; ++i) {
        qp->rd[i] += scale * hz[i];
    }
    for (q = 0; q < l->ns; ++q) {
        qp->rd[n + q] += scale * (2.0 * qp->rho2 * qp->slack[q] + qp->rho1);
    }
    *mu = gap / l->m;
    rp = inf_norm(qp->rp, l->m) / (1.0 + dnorm);
    rd = inf_norm(qp->rd, n + l->ns) / (1.0 + fnorm);
    /* complementarity relative to the size of the (scaled) prices, like the dual residual */
    return fmax(fmax(rp, rd), *mu / (1.0 + fnorm));
}

static int problem_finite(const ddyn_mpc_qp *qp, const layout *l)
{
    int i, j;
    double v = qp->rho1 + qp->rho2 + qp->dt;
    for (j = 0; j < l->n; ++j) {
        v += qp->grad[j] + qp->lb[j] + qp->ub[j] + qp->hard_lo[j] + qp->hard_hi[j];
        for (i = 0; i < l->n; ++i) {
            v += qp->hess[i + j * DDYN_QP_NV];
        }
    }
    for (j = 0; j < l->ns; ++j) {
        v += qp->soft_lo[j] + qp->soft_hi[j];
        for (i = 0; i < soft_len(j); ++i) {
            v += qp->soft_row[j * DDYN_QP_NV + i];
        }
    }
    return isfinite(v); /* any NaN or inf makes the sum non-finite (overflow of finite data is not expected) */
}

ddyn_status ddyn_mpc_qp_solve(ddyn_mpc_qp *qp, int max_iterations, double tol)
{
    layout l;
    double scale, hdiag = 0.0, dnorm, fnorm, mu = 0.0, res = 0.0;
    double rc[DDYN_QP_NCON], D[DDYN_QP_NCON];
    int i, it, n;
    if (qp == NULL || qp->horizon < 1 || qp->horizon > DDYN_MPC_MAX_HORIZON || max_iterations < 1 || !(tol > 0.0) ||
        !(qp->rho2 > 0.0) || !(qp->rho1 >= 0.0) || !(qp->dt > 0.0)) {
        if (qp != NULL) {
            memset(qp->z, 0, sizeof qp->z);
            memset(qp->slack, 0, sizeof qp->slack);
        }
        return DDYN_ERR_ARGUMENT;
    }
    l = make_layout(qp->horizon);
    n = l.n;
    memset(qp->z, 0, sizeof qp->z);
    memset(qp->slack, 0, sizeof qp->slack);
    qp->iterations = 0;
    qp->converged = 0;
    qp->residual = INFINITY;
    if (!problem_finite(qp, &l)) {
        return DDYN_ERR_NONFINITE_INPUT;
    }
    for (i = 0; i < l.ns; ++i) { /* the factorisation runs the soft rows to the end: make their zeros explicit */
        memset(qp->soft_row + i * DDYN_QP_NV + soft_len(i), 0, (size_t)(DDYN_QP_NV - soft_len(i)) * sizeof(double));
    }
    for (i = 0; i < n; ++i) {
        hdiag += qp->hess[i + i * DDYN_QP_NV];
    }
    /* objective scaling: unit mean Hessian diagonal, so that the start t = lam = 1 is well balanced */
    scale = hdiag > 0.0 ? (double)n / hdiag : 1.0;
    for (i = 0; i < n; ++i) {
        qp->d[i] = qp->ub[i];
        qp->d[l.o_lb + i] = -qp->lb[i];
        qp->d[l.o_hup + i] = qp->hard_hi[i];
        qp->d[l.o_hlo + i] = -qp->hard_lo[i];
    }
    for (i = 0; i < l.ns; ++i) {
        qp->d[l.o_sup + i] = qp->soft_hi[i];
        qp->d[l.o_slo + i] = -qp->soft_lo[i];
        qp->d[l.o_sg + i] = 0.0;
    }
    dnorm = inf_norm(qp->d, l.m);
    /* the dual residual and complementarity are measured relative to the largest price in the problem,
     * the slack price rho1: in flat directions (the nearly free throttle rate) the answer may then sit
     * ~1e-3 (relative objective) from the exact optimum. Measured on the closed loop (docs/mpc.md):
     * testing against the gradient alone costs ~2 more iterations and made the real-time iteration
     * less robust (75 of 10,000 steps touching the bounds instead of none). */
    fnorm = scale * fmax(inf_norm(qp->grad, n), qp->rho1);
    /* infeasible start: z = 0, s = 0, constraint slacks t = max(d, 1), multipliers 1 except those of
     * s >= 0, which start at the slack price rho1 (the dual equation of s at s = 0) */
    for (i = 0; i < l.m; ++i) {
        qp->t[i] = fmax(qp->d[i], 1.0);
        qp->lam[i] = 1.0;
    }
    for (i = 0; i < l.ns; ++i) {
        qp->lam[l.o_sg + i] = fmax(1.0, scale * qp->rho1);
    }
    for (it = 0; it < max_iterations; ++it) {
        double a_aff, a, mu_aff = 0.0, sigma;
        res = residuals(qp, &l, scale, dnorm, fnorm, &mu);
        if (res <= tol) {
            qp->converged = 1;
            break;
        }
        for (i = 0; i < l.m; ++i) {
            D[i] = qp->lam[i] / qp->t[i];
        }
        ddyn_mpc_qp_newton_factor(qp, D, scale);
        /* predictor (affine scaling direction): target t .* lam = 0, i.e. rc ./ lam = t */
        newton(qp, &l, D, qp->t, scale, qp->dz, qp->dl_aff, qp->dt_aff);
        a_aff = max_step(qp->t, qp->dt_aff, qp->lam, qp->dl_aff, l.m);
        for (i = 0; i < l.m; ++i) {
            mu_aff += (qp->t[i] + a_aff * qp->dt_aff[i]) * (qp->lam[i] + a_aff * qp->dl_aff[i]);
        }
        mu_aff /= l.m;
        sigma = mu > 0.0 ? pow(mu_aff / mu, 3.0) : 0.0;
        if (sigma > 1.0) {
            sigma = 1.0;
        }
        /* corrector: second-order term and centring, same factorisation */
        for (i = 0; i < l.m; ++i) {
            rc[i] = qp->t[i] + (qp->dt_aff[i] * qp->dl_aff[i] - sigma * mu) / qp->lam[i];
        }
        newton(qp, &l, D, rc, scale, qp->dz, qp->dl_aff, qp->dt_aff);
        a = STEP_FRACTION * max_step(qp->t, qp->dt_aff, qp->lam, qp->dl_aff, l.m);
        if (a > 1.0) {
            a = 1.0;
        }
        for (i = 0; i < n; ++i) {
            qp->z[i] += a * qp->dz[i];
        }
        for (i = 0; i < l.ns; ++i) {
            qp->slack[i] += a * qp->dz[n + i];
        }
        for (i = 0; i < l.m; ++i) {
            qp->t[i] += a * qp->dt_aff[i];
            qp->lam[i] += a * qp->dl_aff[i];
            /* keep strictly positive against round-off */
            if (!(qp->t[i] > 1e-300)) {
                qp->t[i] = 1e-300;
            }
            if (!(qp->lam[i] > 1e-300)) {
                qp->lam[i] = 1e-300;
            }
        }
        qp->iterations = it + 1;
    }
    if (!qp->converged) {
        res = residuals(qp, &l, scale, dnorm, fnorm, &mu);
        qp->converged = res <= tol;
    }
    qp->residual = res;
    if (!ddyn_all_finite(qp->z, n) || !ddyn_all_finite(qp->slack, qp->horizon)) {
        /* the header promises a finite last iterate: never hand on NaN in z or in the slacks */
        memset(qp->z, 0, sizeof qp->z);
        memset(qp->slack, 0, sizeof qp->slack);
        qp->converged = 0;
    }
    return qp->converged ? DDYN_OK : DDYN_ERR_QP_NOT_CONVERGED;
}

int ddyn_mpc_qp_active_side(const ddyn_mpc_qp *qp, int c)
{
    layout l;
    int up, lo;
    if (qp == NULL || qp->horizon < 1 || qp->horizon > DDYN_MPC_MAX_HORIZON) {
        return 0;
    }
    l = make_layout(qp->horizon);
    if (c < 0 || c >= 2 * l.n + l.ns) {
        return 0;
    }
    if (c < l.n) {
        up = c;
        lo = l.o_lb + c;
    } else if (c < 2 * l.n) {
        up = l.o_hup + c - l.n;
        lo = l.o_hlo + c - l.n;
    } else {
        /* a soft row counts only when the plan violates it (slack above 1e-5 m): at the tolerance the
         * multipliers leave soft rows that just touch their bound ambiguous (lam / t of 1-30 against
         * 1e10 for violated rows, test_cold_start_beyond_daqp_cap_converges_in_its_period's QP), and a
         * soft row wrongly active made DAQP's next solve take 133 iterations instead of 12 there */
        if (!(qp->slack[c - 2 * l.n] > 1e-5)) {
            return 0;
        }
        up = l.o_sup + c - 2 * l.n;
        lo = l.o_slo + c - 2 * l.n;
    }
    /* strict complementarity near the optimum: an active constraint's multiplier is large and its
     * slack small, an inactive one's the other way round */
    if (qp->lam[up] > qp->t[up] && qp->lam[up] * qp->t[lo] >= qp->lam[lo] * qp->t[up]) {
        return 1;
    }
    return qp->lam[lo] > qp->t[lo] ? -1 : 0;
}
