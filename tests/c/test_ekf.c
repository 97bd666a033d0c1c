/*
 * EKF contract (c_src/src/ekf.c): refusals by name leave the filter unchanged, heading
 * innovations wrap, an update shrinks the variance it observes. Consistency (NEES/NIS)
 * on simulated sensor data is tests/python/test_ekf.py.
 */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include <cmocka.h>

#include "ddyn/ekf.h"
#include "ddyn_models.h"
#include "ddyn_test_vehicles.h"

static ddyn_ekf ekf;
static const double P0[DDYN_NX] = {1e-4, 1e-4, 1e-4, 1e-3, 1e-4, 1e-2, 1e-8, 1e-8};
static const double Q[DDYN_NX] = {1e-8, 1e-8, 1e-8, 1e-6, 1e-6, 1e-4, 1e-12, 1e-12};
/* the ORCA car's true coefficients, from its vehicle file (generated: ddyn_test_vehicles.h) */
static const double C[DDYN_NC] = DDYN_TEST_ORCA_1_43_TRUE_COEFFS;

static void init_at_yaw(double yaw)
{
    double x0[DDYN_NX] = {0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.2, 0.0};
    x0[2] = yaw;
    assert_int_equal(ddyn_ekf_init(&ekf, &ddyn_model_orca_1_43, DDYN_DISC_EULER, x0, P0, Q), DDYN_OK);
}

static void test_refusals_leave_filter_unchanged(void **state)
{
    ddyn_ekf before;
    double z[2] = {0.01, 0.0}, r[2] = {1e-4, 0.0}, nan_z[1] = {NAN}, r1[1] = {1e-4};
    (void)state;
    init_at_yaw(0.0);
    before = ekf;
    assert_int_equal(ddyn_ekf_update(&ekf, DDYN_MEAS_GNSS_POSITION, z, r, C, NULL), DDYN_ERR_NOT_POSITIVE_DEFINITE);
    assert_int_equal(ddyn_ekf_update(&ekf, DDYN_MEAS_YAW_RATE, nan_z, r1, C, NULL), DDYN_ERR_NONFINITE_INPUT);
    assert_int_equal(ddyn_ekf_update(&ekf, DDYN_MEAS_COUNT, z, r, C, NULL), DDYN_ERR_ARGUMENT);
    assert_memory_equal(&before, &ekf, sizeof ekf);
    assert_int_equal(ddyn_ekf_init(&ekf, &ddyn_model_orca_1_43, DDYN_DISC_COUNT, before.x, P0, Q), DDYN_ERR_ARGUMENT);
}

static void test_heading_innovation_wraps(void **state)
{
    const double pi = 3.14159265358979323846;
    double z[1], r[1] = {1e-4}, nis = -1.0;
    (void)state;
    init_at_yaw(pi - 0.01);
    z[0] = -pi + 0.01; /* 0.02 rad ahead across the wrap, not 6.26 rad behind */
    assert_int_equal(ddyn_ekf_update(&ekf, DDYN_MEAS_HEADING, z, r, C, &nis), DDYN_OK);
    assert_true(ekf.x[2] > pi - 0.01 && ekf.x[2] < pi + 0.01);
    assert_true(nis > 0.0 && nis < 10.0);
}

static void test_update_shrinks_observed_variance_and_predict_grows_it(void **state)
{
    double z[1] = {0.1}, r[1] = {1e-4}, u[DDYN_NU] = {0.0, 0.0};
    double p_omega;
    (void)state;
    init_at_yaw(0.0);
    p_omega = ekf.P[5 * DDYN_NX + 5];
    assert_int_equal(ddyn_ekf_update(&ekf, DDYN_MEAS_YAW_RATE, z, r, C, NULL), DDYN_OK);
    assert_true(ekf.P[5 * DDYN_NX + 5] < p_omega);
    assert_true(ekf.x[5] > 0.0 && ekf.x[5] < 0.1);
    p_omega = ekf.P[0];
    assert_int_equal(ddyn_ekf_predict(&ekf, u, C), DDYN_OK);
    assert_true(ekf.P[0] > p_omega);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_refusals_leave_filter_unchanged),
        cmocka_unit_test(test_heading_innovation_wraps),
        cmocka_unit_test(test_update_shrinks_observed_variance_and_predict_grows_it),
    };
    return cmocka_run_group_tests_name("ekf", tests, NULL, NULL);
}
