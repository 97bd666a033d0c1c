/*
 * The generated C model against the Python model (tests/c/generated/ddyn_model_vectors.h,
 * written by `ddyn codegen model`): next states from numpy, Jacobians from torch autograd.
 * Also the wrapper's contract: bad input is refused by name and leaves outputs untouched.
 */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include <cmocka.h>

#include "ddyn/model.h"
#include "ddyn_model_vectors.h"

/* float64 agreement between two implementations of the same expressions */
#define STEP_RTOL 1e-12
#define JAC_RTOL 1e-9

static ddyn_model_work work;

static void assert_close(const double *got, const double *want, int n, double rtol, const char *what, int case_no)
{
    int i;
    double scale = 0.0;
    for (i = 0; i < n; ++i) {
        scale = fmax(scale, fabs(want[i]));
    }
    for (i = 0; i < n; ++i) {
        double tol = rtol * fmax(fabs(want[i]), scale * 1e-3) + 1e-300;
        if (!(fabs(got[i] - want[i]) <= tol)) {
            fail_msg("%s case %d element %d: C %.17g, Python %.17g (tolerance %.3g)", what, case_no, i, got[i],
                     want[i], tol);
        }
    }
}

typedef struct {
    const char *vehicle;
    const double *x, *u, *c;
    const double *next[DDYN_DISC_COUNT];
    const double *A[DDYN_DISC_COUNT], *B[DDYN_DISC_COUNT], *P[DDYN_DISC_COUNT];
} vector_set;

#define VECTOR_SET(V)                                                                                  \
    {                                                                                                  \
        #V, vec_##V##_x, vec_##V##_u, vec_##V##_c, {vec_##V##_euler_next, vec_##V##_rk4_next},         \
            {vec_##V##_euler_A, vec_##V##_rk4_A}, {vec_##V##_euler_B, vec_##V##_rk4_B},                \
            {vec_##V##_euler_P, vec_##V##_rk4_P}                                                       \
    }

static const vector_set sets[] = {VECTOR_SET(orca_1_43), VECTOR_SET(av21), VECTOR_SET(av21_powertrain),
                                  VECTOR_SET(av21_power)};

static void check_set(const vector_set *set)
{
    const ddyn_vehicle_model *model = ddyn_model_find(set->vehicle);
    int k, d;
    assert_non_null(model);
    for (d = 0; d < DDYN_DISC_COUNT; ++d) {
        for (k = 0; k < DDYN_VECTOR_CASES; ++k) {
            double next[DDYN_NX], A[DDYN_NX * DDYN_NX], B[DDYN_NX * DDYN_NU], P[DDYN_NX * DDYN_NC];
            const double *x = set->x + k * DDYN_NX, *u = set->u + k * DDYN_NU, *c = set->c + k * DDYN_NC;
            assert_int_equal(ddyn_model_step(model, (ddyn_discretisation)d, x, u, c, next, &work), DDYN_OK);
            assert_close(next, set->next[d] + k * DDYN_NX, DDYN_NX, STEP_RTOL, "x_next", k);
            assert_int_equal(ddyn_model_step_jacobians(model, (ddyn_discretisation)d, x, u, c, A, B, P, &work),
                             DDYN_OK);
            assert_close(A, set->A[d] + k * DDYN_NX * DDYN_NX, DDYN_NX * DDYN_NX, JAC_RTOL, "A", k);
            assert_close(B, set->B[d] + k * DDYN_NX * DDYN_NU, DDYN_NX * DDYN_NU, JAC_RTOL, "B", k);
            assert_close(P, set->P[d] + k * DDYN_NX * DDYN_NC, DDYN_NX * DDYN_NC, JAC_RTOL, "P", k);
        }
    }
}

static void test_orca_matches_python(void **state)
{
    (void)state;
    check_set(&sets[0]);
}

static void test_av21_matches_python(void **state)
{
    (void)state;
    check_set(&sets[1]);
}

/* the powertrain drivetrain (brake gain below zero throttle): the reference cases span throttle -1..1 */
static void test_av21_powertrain_matches_python(void **state)
{
    (void)state;
    check_set(&sets[2]);
}

/* the power-limited drivetrain (traction cap, power over speed, brake gain): throttle -1..1 as above */
static void test_av21_power_matches_python(void **state)
{
    (void)state;
    check_set(&sets[3]);
}

/* every sensor model of both vehicles against numpy values and torch-autograd Jacobians */
#define MEAS_CHECK(V, KIND, NAME)                                                                              \
    do {                                                                                                       \
        const ddyn_vehicle_model *m = ddyn_model_find(#V);                                                     \
        int k, dim = ddyn_meas_dim(KIND);                                                                      \
        for (k = 0; k < DDYN_VECTOR_CASES; ++k) {                                                              \
            double h[DDYN_MEAS_MAX_DIM], H[DDYN_MEAS_MAX_DIM * DDYN_NX];                                      \
            assert_int_equal(ddyn_model_measure(m, KIND, vec_##V##_x + k * DDYN_NX, vec_##V##_c + k * DDYN_NC, \
                                                h, H, &work),                                                  \
                             DDYN_OK);                                                                         \
            assert_close(h, vec_##V##_meas_##NAME##_h + k * dim, dim, STEP_RTOL, #NAME " h", k);              \
            assert_close(H, vec_##V##_meas_##NAME##_H + k * dim * DDYN_NX, dim * DDYN_NX, JAC_RTOL, #NAME " H", k); \
        }                                                                                                      \
    } while (0)

#define MEAS_CHECK_ALL(V)                                                                                      \
    do {                                                                                                       \
        MEAS_CHECK(V, DDYN_MEAS_GNSS_POSITION, gnss_position);                                                 \
        MEAS_CHECK(V, DDYN_MEAS_HEADING, heading);                                                             \
        MEAS_CHECK(V, DDYN_MEAS_YAW_RATE, yaw_rate);                                                           \
        MEAS_CHECK(V, DDYN_MEAS_ACCELERATION, acceleration);                                                   \
        MEAS_CHECK(V, DDYN_MEAS_WHEEL_SPEED, wheel_speed);                                                     \
        MEAS_CHECK(V, DDYN_MEAS_STEERING, steering);                                                           \
    } while (0)

static void test_sensor_models_match_python(void **state)
{
    (void)state;
    MEAS_CHECK_ALL(orca_1_43);
    MEAS_CHECK_ALL(av21);
    MEAS_CHECK_ALL(av21_powertrain);
    MEAS_CHECK_ALL(av21_power);
    assert_int_equal(ddyn_meas_dim(DDYN_MEAS_COUNT), 0);
}

static void test_unknown_vehicle_is_null(void **state)
{
    (void)state;
    assert_null(ddyn_model_find("no_such_car"));
    assert_null(ddyn_model_find(NULL));
}

static void test_nonfinite_input_refused_and_output_untouched(void **state)
{
    const ddyn_vehicle_model *model = ddyn_model_find("orca_1_43");
    double x[DDYN_NX], next[DDYN_NX];
    int i;
    (void)state;
    memcpy(x, vec_orca_1_43_x, sizeof x);
    x[3] = NAN;
    for (i = 0; i < DDYN_NX; ++i) {
        next[i] = 42.0;
    }
    assert_int_equal(ddyn_model_step(model, DDYN_DISC_EULER, x, vec_orca_1_43_u, vec_orca_1_43_c, next, &work),
                     DDYN_ERR_NONFINITE_INPUT);
    for (i = 0; i < DDYN_NX; ++i) {
        assert_true(next[i] == 42.0);
    }
}

static void test_zero_inertia_gives_nonfinite_output(void **state)
{
    const ddyn_vehicle_model *model = ddyn_model_find("orca_1_43");
    double c[DDYN_NC], next[DDYN_NX];
    (void)state;
    memcpy(c, vec_orca_1_43_c, sizeof c);
    c[16] = 0.0; /* Iz */
    assert_int_equal(ddyn_model_step(model, DDYN_DISC_EULER, vec_orca_1_43_x, vec_orca_1_43_u, c, next, &work),
                     DDYN_ERR_NONFINITE_OUTPUT);
    assert_string_equal(ddyn_status_name(DDYN_ERR_NONFINITE_OUTPUT), "DDYN_ERR_NONFINITE_OUTPUT");
}

static void test_bad_arguments(void **state)
{
    const ddyn_vehicle_model *model = ddyn_model_find("av21");
    double next[DDYN_NX];
    (void)state;
    assert_int_equal(ddyn_model_step(NULL, DDYN_DISC_EULER, vec_av21_x, vec_av21_u, vec_av21_c, next, &work),
                     DDYN_ERR_ARGUMENT);
    assert_int_equal(ddyn_model_step(model, DDYN_DISC_COUNT, vec_av21_x, vec_av21_u, vec_av21_c, next, &work),
                     DDYN_ERR_ARGUMENT);
    assert_int_equal(ddyn_model_step(model, DDYN_DISC_EULER, vec_av21_x, vec_av21_u, vec_av21_c, NULL, &work),
                     DDYN_ERR_ARGUMENT);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_orca_matches_python),
        cmocka_unit_test(test_av21_matches_python),
        cmocka_unit_test(test_av21_powertrain_matches_python),
        cmocka_unit_test(test_av21_power_matches_python),
        cmocka_unit_test(test_sensor_models_match_python),
        cmocka_unit_test(test_unknown_vehicle_is_null),
        cmocka_unit_test(test_nonfinite_input_refused_and_output_untouched),
        cmocka_unit_test(test_zero_inertia_gives_nonfinite_output),
        cmocka_unit_test(test_bad_arguments),
    };
    return cmocka_run_group_tests_name("model", tests, NULL, NULL);
}
