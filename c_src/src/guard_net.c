/* Guard-network inference: straight-line loops over compile-time sizes, no allocation. */
#include "ddyn/guard_net.h"

#include <math.h>
#include <stddef.h>
#include <string.h>

#ifdef DDYN_NET_DOUBLE
#define NET_EXP exp
#define NET_TANH tanh
#define NET_LOG1P log1p
#define NET_FABS fabs
#else
#define NET_EXP expf
#define NET_TANH tanhf
#define NET_LOG1P log1pf
#define NET_FABS fabsf
#endif

/* width of the features entering the dense layers */
#define NET_FLAT_WIDTH (DDYN_NET_GRU_LAYERS > 0 ? DDYN_NET_HIDDEN : DDYN_NET_TAU * DDYN_NET_NFEAT)

static ddyn_net_real sigmoid(ddyn_net_real z)
{
    /* split by sign so exp never overflows */
    if (z >= 0) {
        return (ddyn_net_real)1 / ((ddyn_net_real)1 + NET_EXP(-z));
    } else {
        ddyn_net_real e = NET_EXP(z);
        return e / ((ddyn_net_real)1 + e);
    }
}

static ddyn_net_real mish(ddyn_net_real x)
{
    /* softplus(x) = max(x, 0) + log1p(exp(-|x|)), stable for any x */
    ddyn_net_real softplus = (x > 0 ? x : (ddyn_net_real)0) + NET_LOG1P(NET_EXP(-NET_FABS(x)));
    return x * NET_TANH(softplus);
}

/* y[r] = b[r] + sum_c W[r][c] x[c].
 * The dot product keeps NET_LANES independent partial sums: a single running sum is a chain
 * of dependent additions the compiler may not reorder (IEEE semantics without -ffast-math),
 * so it runs at one add per FP latency; independent lanes let it use SIMD registers and
 * pipelining. The summation order differs from PyTorch's either way (it blocks its own sums);
 * the parity tests bound the difference. */
#define NET_LANES 8
static void affine(const ddyn_net_real *W, const ddyn_net_real *b, const ddyn_net_real *x, int rows, int cols,
                   ddyn_net_real *y)
{
    const int blocked = cols - cols % NET_LANES;
    int r, c, k;
    for (r = 0; r < rows; ++r) {
        ddyn_net_real lane[NET_LANES] = {0};
        ddyn_net_real acc = b[r];
        const ddyn_net_real *w = W + (size_t)r * (size_t)cols;
        for (c = 0; c < blocked; c += NET_LANES) {
            for (k = 0; k < NET_LANES; ++k) {
                lane[k] += w[c + k] * x[c + k];
            }
        }
        for (; c < cols; ++c) {
            acc += w[c] * x[c];
        }
        for (k = 0; k < NET_LANES; ++k) {
            acc += lane[k];
        }
        y[r] = acc;
    }
}

/* One PyTorch GRU cell step (gate order r, z, n) updating h in place. */
static void gru_cell(ddyn_guard_net *net, int layer, const ddyn_net_real *x, int in_dim, ddyn_net_real *h)
{
    const ddyn_net_tables *t = net->tables;
    const int H = DDYN_NET_HIDDEN;
    int i;
    affine(t->gru_w_ih[layer], t->gru_b_ih[layer], x, 3 * H, in_dim, net->gates_ih);
    affine(t->gru_w_hh[layer], t->gru_b_hh[layer], h, 3 * H, H, net->gates_hh);
    for (i = 0; i < H; ++i) {
        ddyn_net_real r = sigmoid(net->gates_ih[i] + net->gates_hh[i]);
        ddyn_net_real z = sigmoid(net->gates_ih[H + i] + net->gates_hh[H + i]);
        ddyn_net_real n = NET_TANH(net->gates_ih[2 * H + i] + r * net->gates_hh[2 * H + i]);
        h[i] = ((ddyn_net_real)1 - z) * n + z * h[i];
    }
}

ddyn_net_status ddyn_guard_net_init(ddyn_guard_net *net, const ddyn_net_tables *tables)
{
    if (net == NULL || tables == NULL) {
        return DDYN_NET_ERR_ARGUMENT;
    }
    memset(net, 0, sizeof *net);
    if (tables->magic != DDYN_NET_TABLES_MAGIC) {
        return DDYN_NET_ERR_MAGIC;
    }
    if (tables->tau != DDYN_NET_TAU || tables->n_features != DDYN_NET_NFEAT || tables->hidden != DDYN_NET_HIDDEN ||
        tables->layers != DDYN_NET_LAYERS || tables->gru_layers != DDYN_NET_GRU_LAYERS ||
        tables->n_out != DDYN_NET_NOUT || tables->guarded != DDYN_NET_GUARDED) {
        return DDYN_NET_ERR_SHAPE;
    }
    if (tables->checkpoint_sha256 == NULL || strcmp(tables->checkpoint_sha256, DDYN_NET_CHECKPOINT_SHA256) != 0) {
        return DDYN_NET_ERR_HASH;
    }
    {
        /* infer() divides by std: a zero, negative or non-finite entry (a corrupt or hand-made table)
         * would turn every history into inf/NaN features */
        int f;
        if (tables->mean == NULL || tables->std == NULL) {
            return DDYN_NET_ERR_ARGUMENT;
        }
        for (f = 0; f < DDYN_NET_NFEAT; ++f) {
            if (!isfinite((double)tables->mean[f]) || !((double)tables->std[f] > 0.0) ||
                !isfinite((double)tables->std[f])) {
                return DDYN_NET_ERR_NORMALISATION;
            }
        }
        /* the feature range: both or neither, finite, lo <= hi (a NaN bound would let every input through) */
        if ((tables->feature_lo == NULL) != (tables->feature_hi == NULL)) {
            return DDYN_NET_ERR_NORMALISATION;
        }
        for (f = 0; tables->feature_lo != NULL && f < DDYN_NET_NFEAT; ++f) {
            if (!isfinite((double)tables->feature_lo[f]) || !isfinite((double)tables->feature_hi[f]) ||
                !(tables->feature_lo[f] <= tables->feature_hi[f])) {
                return DDYN_NET_ERR_NORMALISATION;
            }
        }
    }
    net->tables = tables;
    net->initialised = 1;
    return DDYN_NET_OK;
}

ddyn_net_status ddyn_guard_net_infer(ddyn_guard_net *net, const double history[DDYN_NET_TAU][DDYN_NET_NFEAT],
                                     double coeffs[DDYN_NET_NOUT])
{
    const ddyn_net_tables *t;
    ddyn_net_real *feat;
    ddyn_net_real z[DDYN_NET_NOUT];
    int step, f, l, i, width;
    if (net == NULL || history == NULL || coeffs == NULL) {
        return DDYN_NET_ERR_ARGUMENT;
    }
    if (!net->initialised) {
        return DDYN_NET_ERR_NOT_INITIALISED;
    }
    t = net->tables;
    for (step = 0; step < DDYN_NET_TAU; ++step) {
        for (f = 0; f < DDYN_NET_NFEAT; ++f) {
            if (!isfinite(history[step][f])) {
                return DDYN_NET_ERR_NONFINITE_INPUT;
            }
        }
    }
    /* held inside the trained feature range, normalised, flattened row-major (oldest row first) into a */
    for (step = 0; step < DDYN_NET_TAU; ++step) {
        for (f = 0; f < DDYN_NET_NFEAT; ++f) {
            ddyn_net_real x = (ddyn_net_real)history[step][f];
            if (t->feature_lo != NULL) {
                x = x < t->feature_lo[f] ? t->feature_lo[f] : (x > t->feature_hi[f] ? t->feature_hi[f] : x);
            }
            net->a[step * DDYN_NET_NFEAT + f] = (x - t->mean[f]) / t->std[f];
        }
    }
    feat = net->a;
    width = NET_FLAT_WIDTH;
    if (DDYN_NET_GRU_LAYERS > 0) {
        /* copy the normalised rows out of a, which the GRU loop does not touch afterwards */
        ddyn_net_real rows[DDYN_NET_TAU * DDYN_NET_NFEAT];
        memcpy(rows, net->a, sizeof rows);
        for (l = 0; l < DDYN_NET_GRU_LAYERS; ++l) {
            for (i = 0; i < DDYN_NET_HIDDEN; ++i) {
                net->h[l][i] = 0;
            }
        }
        for (step = 0; step < DDYN_NET_TAU; ++step) {
            for (l = 0; l < DDYN_NET_GRU_LAYERS; ++l) {
                const ddyn_net_real *in = l == 0 ? rows + step * DDYN_NET_NFEAT : net->h[l - 1];
                gru_cell(net, l, in, l == 0 ? DDYN_NET_NFEAT : DDYN_NET_HIDDEN, net->h[l]);
            }
        }
        feat = net->h[DDYN_NET_GRU_LAYERS > 0 ? DDYN_NET_GRU_LAYERS - 1 : 0];
        width = DDYN_NET_HIDDEN;
    }
    for (l = 0; l < DDYN_NET_LAYERS; ++l) {
        ddyn_net_real *out = (l % 2 == 0) ? net->b : net->a;
        affine(t->dense_w[l], t->dense_b[l], feat, DDYN_NET_HIDDEN, width, out);
        for (i = 0; i < DDYN_NET_HIDDEN; ++i) {
            out[i] = mish(out[i]);
        }
        feat = out;
        width = DDYN_NET_HIDDEN;
    }
    affine(t->head_w, t->head_b, feat, DDYN_NET_NOUT, width, z);
    for (i = 0; i < DDYN_NET_NOUT; ++i) {
        double c = DDYN_NET_GUARDED ? (double)t->lo[i] + ((double)t->hi[i] - (double)t->lo[i]) * (double)sigmoid(z[i])
                                    : (double)z[i];
        if (!isfinite(c)) {
            return DDYN_NET_ERR_NONFINITE_OUTPUT;
        }
        coeffs[i] = c;
    }
    return DDYN_NET_OK;
}
