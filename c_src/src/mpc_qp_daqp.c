/* The MPC's condensed QP solved by DAQP's core on a static workspace (see ddyn/mpc_qp_daqp.h).
 *
 * DAQP solves min 1/2 x'Hx + f'x over lb <= x <= ub, blower <= A x <= bupper through the dual of the
 * least-distance problem (LDP) in u = R x + v, H = R'R, v = R^-T f: the constraints become
 * M u in [d_lo, d_hi] with M = A R^-1 (rows normalised) and d = b + M v. DAQP's api.c/utils.c form
 * that LDP with malloc'ed buffers and general-purpose branches (equality elimination, presolve,
 * hierarchies); here it is formed directly for the MPC's structure, following the same conventions
 * (packed Rinv rows, scaling of the simple bounds and of the rows of M, soft weights in the units of
 * the original problem) so that DAQP's daqp_ldp, ldp2qp_solution and daqp_refine_primal run on it
 * unchanged. The integrator rows (dt times a running sum of one input channel) make their rows of M
 * running sums of rows of Rinv: O(n) per row instead of O(n^2). */
#include "ddyn/mpc_qp_daqp.h"

#include "daqp.h"

#include <math.h>
#include <string.h>

typedef char daqp_real_matches[sizeof(c_float) == sizeof(ddyn_qp_real) ? 1 : -1];

/* packed upper-triangular row-major storage of an n x n matrix: start of row i */
static int row_start(int i, int n) { return i * n - i * (i - 1) / 2; }

void ddyn_mpc_qp_daqp_reset(ddyn_mpc_qp_daqp *w)
{
    if (w != NULL) {
        w->warm_n = 0;
        w->warm_h = 0;
    }
}

void ddyn_mpc_qp_daqp_seed(ddyn_mpc_qp_daqp *w, const ddyn_mpc_qp *qp)
{
    int c, m, h;
    if (w == NULL || qp == NULL || qp->horizon < 1 || qp->horizon > DDYN_MPC_MAX_HORIZON) {
        ddyn_mpc_qp_daqp_reset(w);
        return;
    }
    h = qp->horizon;
    m = 5 * h; /* 2H bounds, 2H integrator rows, H soft rows */
    w->warm_n = 0;
    for (c = 0; c < m && w->warm_n < DDYN_DAQP_WS; ++c) {
        const int side = ddyn_mpc_qp_active_side(qp, c);
        if (side != 0) { /* a linearly dependent one is dropped by DAQP's activation */
            w->warm_id[w->warm_n] = c;
            w->warm_lower[w->warm_n] = side < 0;
            ++w->warm_n;
        }
    }
    w->warm_h = h;
}

void ddyn_mpc_qp_daqp_adversarial_start(ddyn_mpc_qp_daqp *w, int horizon)
{
    int i;
    if (w == NULL || horizon < 1 || horizon > DDYN_MPC_MAX_HORIZON) {
        return;
    }
    /* ids 2 .. 2H - 1: the solve shifts them by one stage, to the bounds of stages 0 .. H - 2 */
    for (i = 0; i < 2 * horizon - 2; ++i) {
        w->warm_id[i] = i + 2;
        w->warm_lower[i] = 0;
    }
    w->warm_n = 2 * horizon - 2;
    w->warm_h = horizon;
}

static void default_settings(DAQPSettings *s, int max_iterations)
{
    memset(s, 0, sizeof *s);
    s->primal_tol = DAQP_DEFAULT_PRIM_TOL;
    s->dual_tol = DAQP_DEFAULT_DUAL_TOL;
    s->zero_tol = DAQP_DEFAULT_ZERO_TOL;
    s->pivot_tol = DAQP_DEFAULT_PIVOT_TOL;
    s->progress_tol = DAQP_DEFAULT_PROG_TOL;
    s->cycle_tol = DAQP_DEFAULT_CYCLE_TOL;
    s->iter_limit = max_iterations + 1; /* daqp_ldp runs iterations 1 .. iter_limit - 1 */
    s->fval_bound = DAQP_INF;
    s->eps_prox = DAQP_DEFAULT_EPS_PROX;
    s->eta_prox = DAQP_DEFAULT_ETA;
    s->rho_soft = DAQP_DEFAULT_RHO_SOFT;
    s->w_soft = DAQP_DEFAULT_W_SOFT;
    s->rel_subopt = DAQP_DEFAULT_REL_SUBOPT;
    s->abs_subopt = DAQP_DEFAULT_ABS_SUBOPT;
    s->sing_tol = DAQP_DEFAULT_SING_TOL;
    s->refactor_tol = DAQP_DEFAULT_REFACTOR_TOL;
    s->eq_reduction = DAQP_EQ_REDUCTION_OFF;
    s->presolve = 0;
}

/* what the factorisation reads: H, the soft rows, dt, the penalty */
static int matrices_finite(const ddyn_mpc_qp *qp, int n)
{
    int i;
    for (i = 0; i < n; ++i) {
        if (!ddyn_all_finite(qp->hess + i * DDYN_QP_NV, n) || !ddyn_all_finite(qp->soft_row + (i / 2) * DDYN_QP_NV, n)) {
            return 0;
        }
    }
    return isfinite(qp->dt) && isfinite(qp->rho1) && isfinite(qp->rho2);
}

/* what the solve reads besides: the gradient and the bounds (the feedback phase changes these) */
static int vectors_finite(const ddyn_mpc_qp *qp, int n, int h)
{
    return ddyn_all_finite(qp->grad, n) && ddyn_all_finite(qp->lb, n) && ddyn_all_finite(qp->ub, n) &&
           ddyn_all_finite(qp->hard_lo, n) && ddyn_all_finite(qp->hard_hi, n) && ddyn_all_finite(qp->soft_lo, h) &&
           ddyn_all_finite(qp->soft_hi, h);
}

/* H = R'R, then Rinv = R^-1 (both packed upper, row-major, in w->Rinv). Returns 0 if H is not
 * numerically positive definite. Sets *ill when cond(H) >= max (H^-1)_ii max H_ii exceeds DAQP's
 * refinement threshold (as DAQP's own setup does). */
static int factor_inverse(const ddyn_mpc_qp *qp, ddyn_mpc_qp_daqp *w, int n, int *ill)
{
    c_float *R = w->Rinv, hmax = 0, hinv_max = 0;
    int i, j, k;
    /* R: row i from H's row i minus the contributions of rows k < i */
    for (i = 0; i < n; ++i) {
        const int ri = row_start(i, n) - i; /* R(i, j) = R[ri + j] */
        const double *Hi = qp->hess + i * DDYN_QP_NV;
        c_float d;
        for (j = i; j < n; ++j) {
            R[ri + j] = (c_float)Hi[j];
        }
        for (k = 0; k < i; ++k) {
            const int rk = row_start(k, n) - k;
            const c_float rki = R[rk + i];
            for (j = i; j < n; ++j) {
                R[ri + j] -= rki * R[rk + j];
            }
        }
        d = R[ri + i];
        if (!(d > (c_float)DAQP_DEFAULT_ZERO_TOL * (c_float)Hi[i])) {
            return 0;
        }
        d = (c_float)sqrt(d);
        R[ri + i] = d;
        for (j = i + 1; j < n; ++j) {
            R[ri + j] /= d;
        }
        if (Hi[i] > hmax) {
            hmax = (c_float)Hi[i];
        }
    }
    /* Rinv in place, last row first: row i of R^-1 needs rows j > i of R^-1 only
     * (R^-1(i, j) = -(sum_{i<k<=j} R(i, k) R^-1(k, j)) / R(i, i)) */
    for (i = n - 1; i >= 0; --i) {
        const int ri = row_start(i, n) - i;
        const c_float inv = 1 / R[ri + i];
        c_float s2;
        for (j = n - 1; j > i; --j) {
            c_float acc = 0;
            for (k = i + 1; k <= j; ++k) {
                acc += R[ri + k] * R[row_start(k, n) - k + j];
            }
            R[ri + j] = -acc * inv; /* R(i, k > j) are read before row i's entry j is overwritten */
        }
        R[ri + i] = inv;
        for (j = i, s2 = 0; j < n; ++j) {
            s2 += R[ri + j] * R[ri + j];
        }
        if (s2 > hinv_max) {
            hinv_max = s2;
        }
    }
    *ill = hinv_max * hmax > (c_float)DAQP_REFINE_COND;
    return 1;
}

/* A's general rows (row-major): the integrator rows and the soft rows (DAQP's refinement reads A) */
static void build_rows(const ddyn_mpc_qp *qp, ddyn_mpc_qp_daqp *w, int n, int h)
{
    int i, j;
    for (i = 0; i < n; ++i) { /* integrator row r = 2(k-1) + ch: dt * sum_{j<k} z[2j + ch] */
        c_float *a = w->A + i * n;
        for (j = 0; j < n; ++j) {
            a[j] = (j % 2 == i % 2 && j <= i) ? (c_float)qp->dt : 0;
        }
    }
    for (i = 0; i < h; ++i) {
        c_float *a = w->A + (n + i) * n;
        for (j = 0; j < n; ++j) {
            a[j] = j < 2 * (i + 1) ? (c_float)qp->soft_row[i * DDYN_QP_NV + j] : 0;
        }
    }
}

/* bounds, sense (with the zero rows the factorisation found) and the soft weights. Returns 0 for
 * crossing hard bounds. */
static int build_bounds(const ddyn_mpc_qp *qp, ddyn_mpc_qp_daqp *w, int n, int h)
{
    const int m = 2 * n + h;
    int i;
    memset(w->soft_w, 0, sizeof w->soft_w);
    for (i = 0; i < n; ++i) {
        w->bupper[i] = (c_float)qp->ub[i];
        w->blower[i] = (c_float)qp->lb[i];
        w->bupper[n + i] = (c_float)qp->hard_hi[i];
        w->blower[n + i] = (c_float)qp->hard_lo[i];
    }
    for (i = 0; i < h; ++i) {
        const int id = 2 * n + i;
        double lo = qp->soft_lo[i], hi = qp->soft_hi[i];
        if (lo > hi) { /* no room at all (a raceline outside its bounds): aim at the middle */
            lo = hi = 0.5 * (lo + hi);
        }
        w->bupper[id] = (c_float)hi;
        w->blower[id] = (c_float)lo;
        /* penalty rho1 s + rho2 s^2 = w s + s^2 / (2 rho) per violated side (DAQP's types.h) */
        w->soft_w[id] = w->soft_w[m + id] = (c_float)(0.5 / qp->rho2);
        w->soft_w[2 * m + id] = w->soft_w[3 * m + id] = (c_float)qp->rho1;
    }
    for (i = 0; i < m; ++i) {
        const c_float gap = w->bupper[i] - w->blower[i];
        w->sense[i] = i >= 2 * n ? DAQP_SOFT : 0;
        if (i < 2 * n && gap < -(c_float)DAQP_DEFAULT_PRIM_TOL) {
            return 0;
        }
        if (i < 2 * n && gap < (c_float)DAQP_DEFAULT_ZERO_TOL) { /* an equality, as DAQP's check_bounds */
            w->sense[i] = DAQP_ACTIVE | DAQP_IMMUTABLE;
        }
        if (i >= n && w->zero_row[i - n]) { /* ignored, as DAQP's normalize_M does */
            w->sense[i] = DAQP_ZERO_ROW_MARK(w->sense[i]);
        }
    }
    return 1;
}

/* M = A Rinv (before Rinv's rows are normalised), then the rows of Rinv (simple bounds) and of M
 * normalised, their scaling kept (DAQP's normalize_Rinv, normalize_M) */
static void form_M(const ddyn_mpc_qp *qp, ddyn_mpc_qp_daqp *w, int n, int h)
{
    const c_float dt = (c_float)qp->dt;
    int i, j, k;
    c_float *R = w->Rinv;
    memset(w->M, 0, (size_t)((n + h) * n) * sizeof(c_float));
    for (i = 0; i < n; ++i) { /* integrator row i: row i - 2 plus dt * Rinv row i (zero left of i) */
        c_float *mi = w->M + i * n;
        const int ri = row_start(i, n) - i;
        if (i >= 2) {
            memcpy(mi, mi - 2 * n, (size_t)n * sizeof(c_float));
        }
        for (j = i; j < n; ++j) {
            mi[j] += dt * R[ri + j];
        }
    }
    for (k = 0; k < h; ++k) { /* soft row: g' Rinv over g's 2(k+1) nonzeros */
        c_float *mk = w->M + (n + k) * n;
        const c_float *g = w->A + (n + k) * n;
        for (i = 0; i < 2 * (k + 1); ++i) {
            const int ri = row_start(i, n) - i;
            const c_float gi = g[i];
            for (j = i; j < n; ++j) {
                mk[j] += gi * R[ri + j];
            }
        }
    }
    for (i = 0; i < n; ++i) { /* simple bounds: rows of Rinv */
        const int ri = row_start(i, n) - i;
        c_float s2 = 0, sc;
        for (j = i; j < n; ++j) {
            s2 += R[ri + j] * R[ri + j];
        }
        sc = 1 / (c_float)sqrt(s2);
        w->scaling[i] = sc;
        for (j = i; j < n; ++j) {
            R[ri + j] *= sc;
        }
    }
    for (i = 0; i < n + h; ++i) { /* general rows */
        c_float *mi = w->M + i * n, s2 = 0, sc;
        for (j = 0; j < n; ++j) {
            s2 += mi[j] * mi[j];
        }
        w->zero_row[i] = s2 < (c_float)DAQP_DEFAULT_ZERO_TOL; /* e.g. a soft row of a held channel */
        if (w->zero_row[i]) {
            w->scaling[n + i] = 1;
            continue;
        }
        sc = 1 / (c_float)sqrt(s2);
        w->scaling[n + i] = sc;
        for (j = 0; j < n; ++j) {
            mi[j] *= sc;
        }
    }
}

/* v = Rinv' f (from the normalised rows: Rinv(i, j) = Rn(i, j) / scaling_i, as DAQP's update_v), then
 * d = b scaling + (normalised row) v */
static void form_d(const ddyn_mpc_qp *qp, ddyn_mpc_qp_daqp *w, int n, int h)
{
    const c_float *R = w->Rinv;
    c_float fs[DDYN_DAQP_N];
    int i, j;
    for (i = 0; i < n; ++i) {
        fs[i] = (c_float)qp->grad[i] / w->scaling[i];
        w->v[i] = 0;
    }
    for (i = 0; i < n; ++i) { /* row-wise over the packed rows: v_j += Rn(i, j) fs_i */
        const int ri = row_start(i, n) - i;
        for (j = i; j < n; ++j) {
            w->v[j] += R[ri + j] * fs[i];
        }
    }
    for (i = 0; i < n; ++i) {
        const int ri = row_start(i, n) - i;
        c_float dv = 0;
        for (j = i; j < n; ++j) {
            dv += R[ri + j] * w->v[j];
        }
        w->dupper[i] = w->bupper[i] * w->scaling[i] + dv;
        w->dlower[i] = w->blower[i] * w->scaling[i] + dv;
    }
    for (i = 0; i < n + h; ++i) {
        const int id = n + i;
        const c_float *mi = w->M + i * n;
        c_float dv = 0;
        if (w->zero_row[i]) {
            w->dupper[id] = w->bupper[id];
            w->dlower[id] = w->blower[id];
            continue;
        }
        for (j = 0; j < n; ++j) {
            dv += mi[j] * w->v[j];
        }
        w->dupper[id] = w->bupper[id] * w->scaling[id] + dv;
        w->dlower[id] = w->blower[id] * w->scaling[id] + dv;
    }
}

/* The previous working set shifted by `shift` stages: stage k's constraints become stage k-shift's
 * (bounds and integrator rows have two per stage, soft rows one); stage 0's are dropped. */
static void apply_warm_start(ddyn_mpc_qp_daqp *w, int n, int h, int shift)
{
    int i;
    if (w->warm_h != h) {
        w->warm_n = 0;
    }
    for (i = 0; i < w->warm_n; ++i) {
        int id = w->warm_id[i];
        if (id < 2 * n) {
            id -= 2 * shift;
            if (id < 0 || (id < n) != (w->warm_id[i] < n)) {
                continue;
            }
        } else {
            id -= shift;
            if (id < 2 * n) {
                continue;
            }
        }
        if (id >= 2 * n + h || (w->sense[id] & (DAQP_IMMUTABLE | DAQP_ZERO_ROW))) {
            continue;
        }
        w->sense[id] |= DAQP_ACTIVE | (w->warm_lower[i] ? DAQP_LOWER : 0);
    }
}

static void outputs(ddyn_mpc_qp *qp, const ddyn_mpc_qp_daqp *w, int n, int h)
{
    double viol = 0.0;
    int i, j;
    for (i = 0; i < n; ++i) {
        qp->z[i] = (double)w->u[i];
        viol = fmax(viol, fmax(qp->z[i] - qp->ub[i], qp->lb[i] - qp->z[i]));
    }
    for (i = 0; i < n; ++i) {
        double a = 0.0;
        for (j = i % 2; j <= i; j += 2) {
            a += qp->z[j];
        }
        a *= qp->dt;
        viol = fmax(viol, fmax(a - qp->hard_hi[i], qp->hard_lo[i] - a));
    }
    for (i = 0; i < h; ++i) {
        const double *g = qp->soft_row + i * DDYN_QP_NV;
        double a = 0.0;
        for (j = 0; j < 2 * (i + 1); ++j) {
            a += g[j] * qp->z[j];
        }
        qp->slack[i] = fmax(0.0, fmax(a - qp->soft_hi[i], qp->soft_lo[i] - a));
    }
    qp->residual = viol;
}

static void clear_answer(ddyn_mpc_qp *qp)
{
    memset(qp->z, 0, sizeof qp->z);
    memset(qp->slack, 0, sizeof qp->slack);
    qp->iterations = 0;
    qp->converged = 0;
    qp->residual = 0.0;
}

ddyn_status ddyn_mpc_qp_daqp_factor(const ddyn_mpc_qp *qp, ddyn_mpc_qp_daqp *w)
{
    int n, h, ill = 0;
    if (qp == NULL || w == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    w->factored_h = 0;
    h = qp->horizon;
    if (h < 1 || h > DDYN_MPC_MAX_HORIZON) {
        w->factor_status = DDYN_ERR_ARGUMENT;
        return w->factor_status;
    }
    n = 2 * h;
    if (!matrices_finite(qp, n)) {
        w->factor_status = DDYN_ERR_NONFINITE_INPUT;
    } else if (!(qp->dt > 0.0) || qp->rho1 < 0.0 || !(qp->rho2 > 0.0) || !factor_inverse(qp, w, n, &ill)) {
        w->factor_status = DDYN_ERR_ARGUMENT;
    } else {
        build_rows(qp, w, n, h);
        form_M(qp, w, n, h);
        w->ill = ill;
        w->factored_h = h;
        w->factor_status = DDYN_OK;
    }
    return w->factor_status;
}

ddyn_status ddyn_mpc_qp_daqp_solve(ddyn_mpc_qp *qp, ddyn_mpc_qp_daqp *w, int max_iterations, int shift)
{
    ddyn_status st;
    if (qp == NULL || w == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    st = ddyn_mpc_qp_daqp_factor(qp, w);
    if (st != DDYN_OK) {
        clear_answer(qp);
        ddyn_mpc_qp_daqp_reset(w);
        return st;
    }
    return ddyn_mpc_qp_daqp_solve_factored(qp, w, max_iterations, shift);
}

ddyn_status ddyn_mpc_qp_daqp_solve_factored(ddyn_mpc_qp *qp, ddyn_mpc_qp_daqp *w, int max_iterations, int shift)
{
    DAQPProblem prob;
    DAQPSettings set;
    DAQPWorkspace work;
    int n, h, m, i, exitflag;
    if (qp == NULL || w == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    h = qp->horizon;
    clear_answer(qp);
    if (w->factor_status != DDYN_OK || w->factored_h != h) { /* a failed or missing factorisation */
        ddyn_mpc_qp_daqp_reset(w);
        return w->factor_status != DDYN_OK ? w->factor_status : DDYN_ERR_ARGUMENT;
    }
    w->factored_h = 0; /* one solve per factorisation: the caller may change H next */
    if (max_iterations < 1 || shift < 0) {
        ddyn_mpc_qp_daqp_reset(w);
        return DDYN_ERR_ARGUMENT;
    }
    n = 2 * h;
    m = 2 * n + h;
    if (!vectors_finite(qp, n, h)) {
        ddyn_mpc_qp_daqp_reset(w);
        return DDYN_ERR_NONFINITE_INPUT;
    }
    if (!build_bounds(qp, w, n, h)) { /* crossing hard bounds: no solution; the caller falls back */
        ddyn_mpc_qp_daqp_reset(w);
        w->exitflag = DAQP_EXIT_INFEASIBLE;
        return DDYN_ERR_QP_NOT_CONVERGED;
    }
    form_d(qp, w, n, h);
    w->cold = w->warm_n == 0 || w->warm_h != h;
    apply_warm_start(w, n, h, shift);

    memset(&prob, 0, sizeof prob);
    prob.n = n;
    prob.m = m;
    prob.ms = n;
    prob.A = w->A;
    prob.bupper = w->bupper;
    prob.blower = w->blower;
    prob.sense = w->sense;
    default_settings(&set, max_iterations);
    memset(&work, 0, sizeof work);
    work.qp = &prob;
    work.n = n;
    work.m = m;
    work.ms = n;
    work.M = w->M;
    work.dupper = w->dupper;
    work.dlower = w->dlower;
    work.Rinv = w->Rinv;
    work.v = w->v;
    work.sense = w->sense;
    work.scaling = w->scaling;
    work.u = w->u;
    work.x = w->u; /* as DAQP's own setup: x and u share storage */
    work.xold = w->xold;
    work.lam = w->lam;
    work.lam_star = w->lam_star;
    work.L = w->L;
    work.D = w->D;
    work.xldl = w->xldl;
    work.zldl = w->zldl;
    work.WS = w->WS;
    work.Mu = w->Mu;
    work.rho_ls = w->soft_w;
    work.rho_us = w->soft_w + m;
    work.w_ls = w->soft_w + 2 * m;
    work.w_us = w->soft_w + 3 * m;
    work.settings = &set;
    work.outer_iter = 1;
    work.state = DAQP_STATE_RINV_NORMALIZED | (w->ill ? DAQP_STATE_ILL_CONDITIONED : 0);
    memset(w->u, 0, sizeof w->u);
    memset(w->xold, 0, sizeof w->xold);
    reset_daqp_workspace(&work);
    if (daqp_activate_constraints(&work) < 0) { /* inconsistent equalities */
        ddyn_mpc_qp_daqp_reset(w);
        w->exitflag = DAQP_EXIT_OVERDETERMINED_INITIAL;
        return DDYN_ERR_QP_NOT_CONVERGED;
    }
    exitflag = daqp_ldp(&work);
    ldp2qp_solution(&work); /* also for a capped solve: the last dual-feasible iterate's primal */
    if (exitflag > 0) {
        daqp_refine_primal(&work);
    }
    w->exitflag = exitflag;
    qp->iterations = work.iterations > max_iterations ? max_iterations : work.iterations;
    for (i = 0; i < n; ++i) {
        if (!isfinite(w->u[i])) {
            memset(w->u, 0, sizeof w->u);
            break;
        }
    }
    outputs(qp, w, n, h);
    if (exitflag <= 0) {
        /* cycling, infeasible: the working set is no guide. At the iteration cap neither: going on from
         * the set reached missed in safe mode (the plan is not applied, so the shifted set no longer
         * fits) and capped again (ddyn sil run --faults restart_plant=2: capped, capped, cold, ... after
         * the restart), so the next solve starts cold (mpc.c: on the interior point, which seeds it) */
        ddyn_mpc_qp_daqp_reset(w);
        return DDYN_ERR_QP_NOT_CONVERGED;
    }
    w->warm_n = 0;
    for (i = 0; i < work.n_active && i < DDYN_DAQP_WS; ++i) {
        const int id = work.WS[i];
        if (w->sense[id] & DAQP_IMMUTABLE) {
            continue; /* equalities come back from the bounds by themselves */
        }
        w->warm_id[w->warm_n] = id;
        w->warm_lower[w->warm_n] = (w->sense[id] & DAQP_LOWER) != 0;
        ++w->warm_n;
    }
    w->warm_h = h;
    qp->converged = 1;
    return DDYN_OK;
}
