/* Extended Kalman filter over the generated single-track model (see ddyn/ekf.h). */
#include "ddyn/ekf.h"

#include <math.h>
#include <stddef.h>
#include <string.h>

#define N DDYN_NX
#define MMAX DDYN_MEAS_MAX_DIM
#define AT(M, r, c, rows) ((M)[(size_t)(c) * (rows) + (r)]) /* column-major element */

static const double PI = 3.14159265358979323846;

static void symmetrise(double *P)
{
    int r, c;
    for (c = 0; c < N; ++c) {
        for (r = c + 1; r < N; ++r) {
            double m = 0.5 * (AT(P, r, c, N) + AT(P, c, r, N));
            AT(P, r, c, N) = m;
            AT(P, c, r, N) = m;
        }
    }
}

/* In-place Cholesky factor (lower) of an m x m column-major matrix; 0 if not positive definite. */
static int cholesky(double *S, int m)
{
    int i, j, k;
    for (j = 0; j < m; ++j) {
        double d = AT(S, j, j, m);
        for (k = 0; k < j; ++k) {
            d -= AT(S, j, k, m) * AT(S, j, k, m);
        }
        if (!(d > 0.0)) {
            return 0;
        }
        AT(S, j, j, m) = sqrt(d);
        for (i = j + 1; i < m; ++i) {
            double v = AT(S, i, j, m);
            for (k = 0; k < j; ++k) {
                v -= AT(S, i, k, m) * AT(S, j, k, m);
            }
            AT(S, i, j, m) = v / AT(S, j, j, m);
        }
    }
    return 1;
}

/* Solve (L L') x = b in place for one right-hand side of length m. */
static void cholesky_solve(const double *L, int m, double *b)
{
    int i, k;
    for (i = 0; i < m; ++i) {
        for (k = 0; k < i; ++k) {
            b[i] -= AT(L, i, k, m) * b[k];
        }
        b[i] /= AT(L, i, i, m);
    }
    for (i = m - 1; i >= 0; --i) {
        for (k = i + 1; k < m; ++k) {
            b[i] -= AT(L, k, i, m) * b[k];
        }
        b[i] /= AT(L, i, i, m);
    }
}

ddyn_status ddyn_ekf_init(ddyn_ekf *ekf, const ddyn_vehicle_model *model, ddyn_discretisation disc,
                          const double x0[DDYN_NX], const double p0_diag[DDYN_NX], const double q_diag[DDYN_NX])
{
    int i;
    if (ekf == NULL || model == NULL || x0 == NULL || p0_diag == NULL || q_diag == NULL ||
        (unsigned)disc >= (unsigned)DDYN_DISC_COUNT) {
        return DDYN_ERR_ARGUMENT;
    }
    if (!ddyn_all_finite(x0, N) || !ddyn_all_finite(p0_diag, N) || !ddyn_all_finite(q_diag, N)) {
        return DDYN_ERR_NONFINITE_INPUT;
    }
    for (i = 0; i < N; ++i) {
        if (!(p0_diag[i] > 0.0) || q_diag[i] < 0.0) {
            return DDYN_ERR_NOT_POSITIVE_DEFINITE;
        }
    }
    memset(ekf, 0, sizeof *ekf);
    ekf->model = model;
    ekf->disc = disc;
    memcpy(ekf->x, x0, sizeof ekf->x);
    memcpy(ekf->q, q_diag, sizeof ekf->q);
    for (i = 0; i < N; ++i) {
        AT(ekf->P, i, i, N) = p0_diag[i];
    }
    return DDYN_OK;
}

ddyn_status ddyn_ekf_predict(ddyn_ekf *ekf, const double u[DDYN_NU], const double c[DDYN_NC])
{
    double xn[N], A[N * N], AP[N * N], Pn[N * N];
    int r, col, k;
    ddyn_status s;
    if (ekf == NULL || ekf->model == NULL) {
        return DDYN_ERR_ARGUMENT;
    }
    s = ddyn_model_step(ekf->model, ekf->disc, ekf->x, u, c, xn, &ekf->work);
    if (s != DDYN_OK) {
        return s;
    }
    ddyn_model_add_bank(ekf->bank, ekf->model->sample_time, ekf->x, xn); /* constant over x: A unchanged */
    ddyn_model_add_grade(ekf->grade, ekf->model->sample_time, ekf->x, xn);
    s = ddyn_model_step_jacobians(ekf->model, ekf->disc, ekf->x, u, c, A, NULL, NULL, &ekf->work);
    if (s != DDYN_OK) {
        return s;
    }
    /* Pn = A P A' + diag(q) */
    for (col = 0; col < N; ++col) {
        for (r = 0; r < N; ++r) {
            double v = 0.0;
            for (k = 0; k < N; ++k) {
                v += AT(A, r, k, N) * AT(ekf->P, k, col, N);
            }
            AT(AP, r, col, N) = v;
        }
    }
    for (col = 0; col < N; ++col) {
        for (r = 0; r < N; ++r) {
            double v = 0.0;
            for (k = 0; k < N; ++k) {
                v += AT(AP, r, k, N) * AT(A, col, k, N);
            }
            AT(Pn, r, col, N) = v + (r == col ? ekf->q[r] : 0.0);
        }
    }
    if (!ddyn_all_finite(Pn, N * N)) {
        return DDYN_ERR_NONFINITE_OUTPUT;
    }
    memcpy(ekf->x, xn, sizeof xn);
    memcpy(ekf->P, Pn, sizeof Pn);
    symmetrise(ekf->P);
    return DDYN_OK;
}

ddyn_status ddyn_ekf_update(ddyn_ekf *ekf, ddyn_meas_kind kind, const double *z, const double *r_diag,
                            const double c[DDYN_NC], double *nis)
{
    /* zero-initialised: only the first m (dimension of the sensor) entries are used */
    double h[MMAX] = {0}, H[MMAX * N] = {0}, y[MMAX] = {0}, S[MMAX * MMAX] = {0}, w[MMAX] = {0};
    double PHt[N * MMAX], K[N * MMAX], IKH[N * N], T[N * N], Pn[N * N], xn[N];
    int m = ddyn_meas_dim(kind);
    int r, col, k, i;
    double nis_value = 0.0;
    ddyn_status s;
    if (ekf == NULL || ekf->model == NULL || z == NULL || r_diag == NULL || m == 0) {
        return DDYN_ERR_ARGUMENT;
    }
    if (!ddyn_all_finite(z, m) || !ddyn_all_finite(r_diag, m)) {
        return DDYN_ERR_NONFINITE_INPUT;
    }
    for (i = 0; i < m; ++i) {
        if (!(r_diag[i] > 0.0)) {
            return DDYN_ERR_NOT_POSITIVE_DEFINITE;
        }
    }
    s = ddyn_model_measure(ekf->model, kind, ekf->x, c, h, H, &ekf->work);
    if (s != DDYN_OK) {
        return s;
    }
    for (i = 0; i < m; ++i) {
        y[i] = z[i] - h[i];
    }
    if (kind == DDYN_MEAS_HEADING) {
        y[0] = fmod(y[0] + PI, 2.0 * PI);
        y[0] = (y[0] < 0.0 ? y[0] + 2.0 * PI : y[0]) - PI;
    }
    /* PHt = P H' (N x m), S = H P H' + R (m x m) */
    for (col = 0; col < m; ++col) {
        for (r = 0; r < N; ++r) {
            double v = 0.0;
            for (k = 0; k < N; ++k) {
                v += AT(ekf->P, r, k, N) * AT(H, col, k, m);
            }
            AT(PHt, r, col, N) = v;
        }
    }
    for (col = 0; col < m; ++col) {
        for (r = 0; r < m; ++r) {
            double v = 0.0;
            for (k = 0; k < N; ++k) {
                v += AT(H, r, k, m) * AT(PHt, k, col, N);
            }
            AT(S, r, col, m) = v + (r == col ? r_diag[r] : 0.0);
        }
    }
    if (!cholesky(S, m)) {
        return DDYN_ERR_NOT_POSITIVE_DEFINITE;
    }
    /* K = PHt S^-1, row by row: S K(r,:)' = PHt(r,:)' */
    for (r = 0; r < N; ++r) {
        for (i = 0; i < m; ++i) {
            w[i] = AT(PHt, r, i, N);
        }
        cholesky_solve(S, m, w);
        for (i = 0; i < m; ++i) {
            AT(K, r, i, N) = w[i];
        }
    }
    for (i = 0; i < m; ++i) {
        w[i] = y[i];
    }
    cholesky_solve(S, m, w);
    for (i = 0; i < m; ++i) {
        nis_value += y[i] * w[i];
    }
    for (r = 0; r < N; ++r) {
        double v = 0.0;
        for (i = 0; i < m; ++i) {
            v += AT(K, r, i, N) * y[i];
        }
        xn[r] = ekf->x[r] + v;
    }
    /* Joseph form: Pn = (I - K H) P (I - K H)' + K R K' */
    for (col = 0; col < N; ++col) {
        for (r = 0; r < N; ++r) {
            double v = r == col ? 1.0 : 0.0;
            for (i = 0; i < m; ++i) {
                v -= AT(K, r, i, N) * AT(H, i, col, m);
            }
            AT(IKH, r, col, N) = v;
        }
    }
    for (col = 0; col < N; ++col) {
        for (r = 0; r < N; ++r) {
            double v = 0.0;
            for (k = 0; k < N; ++k) {
                v += AT(IKH, r, k, N) * AT(ekf->P, k, col, N);
            }
            AT(T, r, col, N) = v;
        }
    }
    for (col = 0; col < N; ++col) {
        for (r = 0; r < N; ++r) {
            double v = 0.0;
            for (k = 0; k < N; ++k) {
                v += AT(T, r, k, N) * AT(IKH, col, k, N);
            }
            for (i = 0; i < m; ++i) {
                v += AT(K, r, i, N) * r_diag[i] * AT(K, col, i, N);
            }
            AT(Pn, r, col, N) = v;
        }
    }
    if (!ddyn_all_finite(xn, N) || !ddyn_all_finite(Pn, N * N)) {
        return DDYN_ERR_NONFINITE_OUTPUT;
    }
    memcpy(ekf->x, xn, sizeof xn);
    memcpy(ekf->P, Pn, sizeof Pn);
    symmetrise(ekf->P);
    if (nis != NULL) {
        *nis = nis_value;
    }
    return DDYN_OK;
}
