/*
 * Guard-network inference (c_src/src/guard_net.c) on the fixture network of
 * tests/c/generated/net_fixture: PyTorch parity, guard ranges, the feature range, refusals by name.
 * (The 10,000-history parity on real and simulated logs is tests/python/test_export.py.)
 */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include <cmocka.h>

#include "ddyn/guard_net.h"
#include "ddyn_net_fixture_vectors.h"

extern const ddyn_net_tables ddyn_net_weights;

static ddyn_guard_net net;

#define HISTORY(k) ((const double(*)[DDYN_NET_NFEAT])(net_fixture_history + (k)*DDYN_NET_TAU * DDYN_NET_NFEAT))
#define COEFF(k, i) (net_fixture_coeffs[(k)*DDYN_NET_NOUT + (i)])

static void test_matches_pytorch_and_stays_in_range(void **state)
{
    int k, i;
    (void)state;
    assert_int_equal(ddyn_guard_net_init(&net, &ddyn_net_weights), DDYN_NET_OK);
    for (k = 0; k < NET_FIXTURE_CASES; ++k) {
        double c[DDYN_NET_NOUT];
        assert_int_equal(ddyn_guard_net_infer(&net, HISTORY(k), c), DDYN_NET_OK);
        for (i = 0; i < DDYN_NET_NOUT; ++i) {
            double lo = ddyn_net_weights.lo[i], hi = ddyn_net_weights.hi[i];
            double tol = 1e-5 * fmax(fabs(COEFF(k, i)), hi - lo);
            if (!(fabs(c[i] - COEFF(k, i)) <= tol)) {
                fail_msg("case %d output %d: C %.9g, PyTorch %.9g", k, i, c[i], COEFF(k, i));
            }
            assert_true(c[i] >= lo && c[i] <= hi);
        }
    }
}

static void test_refuses_tables_of_another_shape_or_checkpoint(void **state)
{
    ddyn_net_tables t = ddyn_net_weights;
    (void)state;
    t.hidden += 1;
    assert_int_equal(ddyn_guard_net_init(&net, &t), DDYN_NET_ERR_SHAPE);
    t = ddyn_net_weights;
    t.checkpoint_sha256 = "not the checkpoint this runtime was built for";
    assert_int_equal(ddyn_guard_net_init(&net, &t), DDYN_NET_ERR_HASH);
    t = ddyn_net_weights;
    t.magic = 0;
    assert_int_equal(ddyn_guard_net_init(&net, &t), DDYN_NET_ERR_MAGIC);
    assert_string_equal(ddyn_net_status_name(DDYN_NET_ERR_HASH), "DDYN_ERR_NET_HASH");
}

static void test_refuses_a_normalisation_it_cannot_divide_by(void **state)
{
    /* infer() divides each feature by its std: a zero, negative or non-finite std, or a non-finite
     * mean, must stop init (it used to be accepted, and every history became inf/NaN features) */
    static ddyn_net_real std[DDYN_NET_NFEAT], mean[DDYN_NET_NFEAT];
    const ddyn_net_real bad_std[] = {(ddyn_net_real)0.0, (ddyn_net_real)-1.0, (ddyn_net_real)NAN,
                                     (ddyn_net_real)INFINITY};
    ddyn_net_tables t;
    unsigned k;
    (void)state;
    for (k = 0; k < sizeof bad_std / sizeof bad_std[0]; ++k) {
        t = ddyn_net_weights;
        memcpy(std, ddyn_net_weights.std, sizeof std);
        std[3] = bad_std[k];
        t.std = std;
        assert_int_equal(ddyn_guard_net_init(&net, &t), DDYN_NET_ERR_NORMALISATION);
    }
    t = ddyn_net_weights;
    memcpy(mean, ddyn_net_weights.mean, sizeof mean);
    mean[0] = (ddyn_net_real)NAN;
    t.mean = mean;
    assert_int_equal(ddyn_guard_net_init(&net, &t), DDYN_NET_ERR_NORMALISATION);
    assert_string_equal(ddyn_status_name(DDYN_NET_ERR_NORMALISATION), "DDYN_ERR_NET_NORMALISATION");
    assert_int_equal(ddyn_guard_net_init(&net, &ddyn_net_weights), DDYN_NET_OK);
}

static void test_holds_inputs_inside_the_trained_feature_range(void **state)
{
    /* a history beyond the range gives the coefficients of the same history at the range's edge, and
     * differs from what the network gives it unheld (tables without a range: NULL) */
    double far[DDYN_NET_TAU][DDYN_NET_NFEAT], edge[DDYN_NET_TAU][DDYN_NET_NFEAT];
    double c_far[DDYN_NET_NOUT], c_edge[DDYN_NET_NOUT], c_unheld[DDYN_NET_NOUT], differs = 0.0;
    ddyn_net_tables t = ddyn_net_weights;
    int step, f, i;
    (void)state;
    assert_non_null(ddyn_net_weights.feature_lo);
    for (step = 0; step < DDYN_NET_TAU; ++step) {
        for (f = 0; f < DDYN_NET_NFEAT; ++f) {
            /* alternate sides: far above the top, far below the bottom */
            int up = (step + f) % 2 == 0;
            double lo = ddyn_net_weights.feature_lo[f], hi = ddyn_net_weights.feature_hi[f];
            far[step][f] = up ? hi + 10.0 * (hi - lo) : lo - 10.0 * (hi - lo);
            edge[step][f] = up ? hi : lo;
        }
    }
    assert_int_equal(ddyn_guard_net_init(&net, &ddyn_net_weights), DDYN_NET_OK);
    assert_int_equal(ddyn_guard_net_infer(&net, (const double(*)[DDYN_NET_NFEAT])far, c_far), DDYN_NET_OK);
    assert_int_equal(ddyn_guard_net_infer(&net, (const double(*)[DDYN_NET_NFEAT])edge, c_edge), DDYN_NET_OK);
    t.feature_lo = NULL;
    t.feature_hi = NULL;
    assert_int_equal(ddyn_guard_net_init(&net, &t), DDYN_NET_OK);
    assert_int_equal(ddyn_guard_net_infer(&net, (const double(*)[DDYN_NET_NFEAT])far, c_unheld), DDYN_NET_OK);
    for (i = 0; i < DDYN_NET_NOUT; ++i) {
        assert_true(c_far[i] == c_edge[i]);
        differs = fmax(differs, fabs(c_unheld[i] - c_far[i]) / (ddyn_net_weights.hi[i] - ddyn_net_weights.lo[i]));
    }
    assert_true(differs > 1e-3);
}

static void test_refuses_a_feature_range_it_cannot_hold_to(void **state)
{
    static ddyn_net_real lo[DDYN_NET_NFEAT];
    const ddyn_net_real bad[] = {(ddyn_net_real)NAN, (ddyn_net_real)INFINITY, (ddyn_net_real)1e6};
    ddyn_net_tables t;
    unsigned k;
    (void)state;
    for (k = 0; k < sizeof bad / sizeof bad[0]; ++k) {   /* NaN, inf, above the feature's top */
        t = ddyn_net_weights;
        memcpy(lo, ddyn_net_weights.feature_lo, sizeof lo);
        lo[2] = bad[k];
        t.feature_lo = lo;
        assert_int_equal(ddyn_guard_net_init(&net, &t), DDYN_NET_ERR_NORMALISATION);
    }
    t = ddyn_net_weights;
    t.feature_hi = NULL;   /* one side only */
    assert_int_equal(ddyn_guard_net_init(&net, &t), DDYN_NET_ERR_NORMALISATION);
    assert_int_equal(ddyn_guard_net_init(&net, &ddyn_net_weights), DDYN_NET_OK);
}

static void test_refuses_uninitialised_and_nonfinite(void **state)
{
    double h[DDYN_NET_TAU][DDYN_NET_NFEAT];
    double c[DDYN_NET_NOUT];
    (void)state;
    memset(&net, 0, sizeof net);
    memcpy(h, net_fixture_history, sizeof h);
    assert_int_equal(ddyn_guard_net_infer(&net, (const double(*)[DDYN_NET_NFEAT])h, c),
                     DDYN_NET_ERR_NOT_INITIALISED);
    assert_int_equal(ddyn_guard_net_init(&net, &ddyn_net_weights), DDYN_NET_OK);
    h[1][2] = NAN;
    assert_int_equal(ddyn_guard_net_infer(&net, (const double(*)[DDYN_NET_NFEAT])h, c),
                     DDYN_NET_ERR_NONFINITE_INPUT);
    assert_int_equal(ddyn_guard_net_infer(NULL, (const double(*)[DDYN_NET_NFEAT])h, c), DDYN_NET_ERR_ARGUMENT);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_matches_pytorch_and_stays_in_range),
        cmocka_unit_test(test_refuses_tables_of_another_shape_or_checkpoint),
        cmocka_unit_test(test_refuses_uninitialised_and_nonfinite),
        cmocka_unit_test(test_refuses_a_normalisation_it_cannot_divide_by),
        cmocka_unit_test(test_holds_inputs_inside_the_trained_feature_range),
        cmocka_unit_test(test_refuses_a_feature_range_it_cannot_hold_to),
    };
    return cmocka_run_group_tests_name("guard_net", tests, NULL, NULL);
}
