/*
 * Controller step contract (c_src/src/controller.c): the history rows the guard network reads,
 * and every defined fallback with its status bit, safe command and recovery. Runs on the
 * fixture network (tests/c/generated/net_fixture, orca_1_43) with a closed loop: the plant is the
 * generated model step with the true coefficients, the readings its exact sensor models.
 */
#include <float.h>
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include <cmocka.h>

#include "ddyn/controller.h"
#include "ddyn_models.h"
#include "ddyn_test_vehicles.h"

extern const ddyn_net_tables ddyn_net_weights;

#define TRACK_N 120
#define RADIUS 1.5
#define SPEED 1.0

/* the ORCA car's true coefficients, from its vehicle file (generated: ddyn_test_vehicles.h) */
static const double C_TRUE[DDYN_NC] = DDYN_TEST_ORCA_1_43_TRUE_COEFFS;

/* the closed-loop PID test's bounds on the speed error over its last 2 s (m/s) */
#define PID_WORST_ERROR 0.02
#define PID_MEAN_ERROR 0.005

static ddyn_ctrl ctl;
static ddyn_ctrl_config cfg;
static double plant[DDYN_NX];
static double plant_c[DDYN_NC]; /* the plant's coefficients: C_TRUE unless a test says otherwise */
static ddyn_model_work plant_work;
static const ddyn_vehicle_model *model = &ddyn_model_orca_1_43;

static double clamp_d(double v, double lo, double hi)
{
    return v < lo ? lo : (v > hi ? hi : v);
}

/* a circle driven counter-clockwise at SPEED: the car starts on it, tangent, at vx0 (with the
 * throttle that holds SPEED) */
static void start_on_circle_at(const ddyn_net_tables *tables, double vx0)
{
    static double x[TRACK_N], y[TRACK_N], speed[TRACK_N], wl[TRACK_N], wr[TRACK_N];
    const double pi = 3.14159265358979323846;
    int i;
    for (i = 0; i < TRACK_N; ++i) {
        double a = 2.0 * pi * i / TRACK_N;
        x[i] = RADIUS * cos(a);
        y[i] = RADIUS * sin(a);
        speed[i] = SPEED;
        wl[i] = 0.15;
        wr[i] = 0.15;
    }
    plant[0] = RADIUS;
    plant[1] = 0.0;
    plant[2] = pi / 2.0;
    plant[3] = vx0;
    plant[4] = 0.0;
    plant[5] = vx0 / RADIUS;
    plant[6] = (C_TRUE[14] + C_TRUE[15] * SPEED * SPEED) / (C_TRUE[12] - C_TRUE[13] * SPEED);
    plant[7] = atan((0.029 + 0.033) / RADIUS);
    assert_int_equal(ddyn_ctrl_init(&ctl, model, tables, &cfg, plant), DDYN_OK);
    assert_int_equal(ddyn_ctrl_set_track(&ctl, TRACK_N, x, y, speed, wl, wr), DDYN_OK);
}

static void start_on_circle(const ddyn_net_tables *tables)
{
    start_on_circle_at(tables, SPEED);
}

static int setup(void **state)
{
    (void)state;
    assert_int_equal(ddyn_ctrl_default_config(model, &cfg), DDYN_OK);
    memcpy(cfg.c_nominal, C_TRUE, sizeof C_TRUE);
    memcpy(plant_c, C_TRUE, sizeof C_TRUE);
    start_on_circle(&ddyn_net_weights);
    return 0;
}

/* exact readings of the plant: every sensor every period (GNSS and heading every 5th), except the
 * accelerometer: its model involves the tyre forces, so with the fixture network's random (if
 * guarded) coefficients the filter's prediction of it is metres per second squared off, and the
 * innovation gate would rightly reject it */
static void readings(ddyn_ctrl_input *in, int period)
{
    int k;
    memset(in, 0, sizeof *in);
    for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
        double h[DDYN_MEAS_MAX_DIM], H[DDYN_MEAS_MAX_DIM * DDYN_NX];
        if (((k == DDYN_MEAS_GNSS_POSITION || k == DDYN_MEAS_HEADING) && period % 5 != 0) ||
            k == DDYN_MEAS_ACCELERATION) {
            continue;
        }
        assert_int_equal(ddyn_model_measure(model, (ddyn_meas_kind)k, plant, plant_c, h, H, &plant_work), DDYN_OK);
        in->reading[k].valid = 1;
        in->reading[k].z[0] = h[0];
        in->reading[k].z[1] = h[1];
    }
}

/* one closed-loop period with the given input; the plant moves by the command */
static ddyn_ctrl_status run(const ddyn_ctrl_input *in, ddyn_ctrl_output *out)
{
    double next[DDYN_NX];
    ddyn_ctrl_status st = ddyn_ctrl_step(&ctl, in, out);
    assert_int_equal(st, out->status);
    assert_true(isfinite(out->u[0]) && isfinite(out->u[1]));
    assert_int_equal(ddyn_model_step(model, DDYN_DISC_RK4, plant, out->u, plant_c, next, &plant_work), DDYN_OK);
    memcpy(plant, next, sizeof next);
    return st;
}

static ddyn_ctrl_status run_exact(int period, ddyn_ctrl_output *out)
{
    ddyn_ctrl_input in;
    readings(&in, period);
    return run(&in, out);
}

static void test_init_names_what_is_wrong_with_the_network(void **state)
{
    /* the network's own error, not one code for all (ddyn/status.h: the runtime's one error type) */
    ddyn_net_tables t = ddyn_net_weights;
    static ddyn_net_real std0[DDYN_NET_NFEAT];
    (void)state;
    t.magic ^= 1u;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &t, &cfg, plant), DDYN_ERR_NET_MAGIC);
    t = ddyn_net_weights;
    t.hidden += 1;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &t, &cfg, plant), DDYN_ERR_NET_SHAPE);
    t = ddyn_net_weights;
    t.checkpoint_sha256 = "0000000000000000000000000000000000000000000000000000000000000000";
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &t, &cfg, plant), DDYN_ERR_NET_HASH);
    t = ddyn_net_weights;
    t.std = std0; /* all zero */
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &t, &cfg, plant), DDYN_ERR_NET_NORMALISATION);
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_OK);
    assert_string_equal(ddyn_status_name(DDYN_ERR_NET_HASH), "DDYN_ERR_NET_HASH");
}

static void test_every_status_has_its_own_name(void **state)
{
    int a, b;
    (void)state;
    for (a = DDYN_OK; a <= DDYN_ERR_RANGE; ++a) {
        assert_true(strncmp(ddyn_status_name((ddyn_status)a), "DDYN_", 5) == 0);
        assert_string_not_equal(ddyn_status_name((ddyn_status)a), "DDYN_ERR_UNKNOWN");
        for (b = 0; b < a; ++b) {
            assert_string_not_equal(ddyn_status_name((ddyn_status)a), ddyn_status_name((ddyn_status)b));
        }
    }
    assert_string_equal(ddyn_status_name((ddyn_status)(DDYN_ERR_RANGE + 1)), "DDYN_ERR_UNKNOWN");
}

static void test_bad_arguments_and_configurations(void **state)
{
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    ddyn_ctrl_config bad;
    (void)state;
    memset(&in, 0, sizeof in);
    assert_int_equal(ddyn_ctrl_step(NULL, &in, &out), DDYN_CTRL_ERR_ARGUMENT);
    assert_true(out.u[0] == 0.0 && out.u[1] == 0.0);
    assert_int_equal(ddyn_ctrl_step(&ctl, NULL, &out), DDYN_CTRL_ERR_ARGUMENT);
    assert_int_equal(ddyn_ctrl_step(&ctl, &in, NULL), DDYN_CTRL_ERR_ARGUMENT);
    bad = cfg;
    memset(bad.c_nominal, 0, sizeof bad.c_nominal); /* no nominal coefficients: no fallback */
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &bad, plant), DDYN_ERR_ARGUMENT);
    assert_int_equal(ddyn_ctrl_step(&ctl, &in, &out), DDYN_CTRL_ERR_ARGUMENT); /* refused init: unusable */
    bad = cfg;
    bad.max_plan_shift = bad.mpc.horizon; /* a shifted plan has only horizon - 1 stages left */
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &bad, plant), DDYN_ERR_ARGUMENT);
    bad = cfg;
    bad.p_max[3] = bad.p0_diag[3]; /* would call the fresh filter diverged */
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &bad, plant), DDYN_ERR_ARGUMENT);
    bad = cfg;
    bad.r_diag[DDYN_MEAS_WHEEL_SPEED][1] = NAN;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &bad, plant), DDYN_ERR_ARGUMENT);
    /* coefficient source and throttle mode */
    assert_int_equal(ddyn_ctrl_init(&ctl, model, NULL, &cfg, plant), DDYN_ERR_ARGUMENT); /* network needs tables */
    bad = cfg;
    bad.coeff_source = DDYN_CTRL_SOURCE_FIXED; /* c_fixed left at 0: Iz = 0, no drive */
    assert_int_equal(ddyn_ctrl_init(&ctl, model, NULL, &bad, plant), DDYN_ERR_ARGUMENT);
    memcpy(bad.c_fixed, C_TRUE, sizeof C_TRUE);
    assert_int_equal(ddyn_ctrl_init(&ctl, model, NULL, &bad, plant), DDYN_OK); /* fixed: no tables needed */
    bad.c_fixed[DDYN_NC - 1] = NAN;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, NULL, &bad, plant), DDYN_ERR_ARGUMENT);
    bad = cfg;
    bad.coeff_source = DDYN_CTRL_SOURCE_COUNT;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &bad, plant), DDYN_ERR_ARGUMENT);
    bad = cfg;
    bad.throttle_mode = DDYN_CTRL_THROTTLE_MODE_COUNT;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &bad, plant), DDYN_ERR_ARGUMENT);
    bad = cfg;
    bad.pid.ki = -1.0;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &bad, plant), DDYN_ERR_ARGUMENT);
    bad = cfg;
    bad.pid.kd = INFINITY;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &bad, plant), DDYN_ERR_ARGUMENT);
}

static void test_status_bits_have_distinct_names(void **state)
{
    int i, j;
    (void)state;
    for (i = 0; i < DDYN_CTRL_STATUS_BITS; ++i) {
        const char *a = ddyn_ctrl_status_name((ddyn_ctrl_status)1u << i);
        assert_true(strncmp(a, "DDYN_CTRL_", 10) == 0 && strcmp(a, "DDYN_CTRL_UNKNOWN") != 0);
        for (j = 0; j < i; ++j) {
            assert_string_not_equal(a, ddyn_ctrl_status_name((ddyn_ctrl_status)1u << j));
        }
    }
    assert_string_equal(ddyn_ctrl_status_name((ddyn_ctrl_status)1u << DDYN_CTRL_STATUS_BITS), "DDYN_CTRL_UNKNOWN");
    assert_string_equal(ddyn_ctrl_status_name(DDYN_CTRL_SAFE_COMMAND | DDYN_CTRL_NET_FAULT), "DDYN_CTRL_UNKNOWN");
}

static void test_safe_command_brakes_then_holds(void **state)
{
    double x[DDYN_NX] = {0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.5, 0.2}, u[DDYN_NU];
    const double dt = model->sample_time;
    (void)state;
    ddyn_ctrl_safe_command(&ctl, x, u);
    assert_true(u[0] == cfg.mpc.rate_lo[0]); /* 0.5 -> -0.1 needs -30/s: limited to the rate bound */
    assert_true(u[1] == 0.0);                /* steering held */
    x[6] = -0.05;
    ddyn_ctrl_safe_command(&ctl, x, u);
    assert_float_equal(u[0], (cfg.mpc.state_lo[0] - x[6]) / dt, 1e-12); /* braking value within one period */
    x[3] = 0.5 * cfg.safe_stop_speed;                                   /* stopped: hold, do not reverse */
    x[6] = 0.1;
    ddyn_ctrl_safe_command(&ctl, x, u);
    assert_float_equal(u[0], (C_TRUE[14] / C_TRUE[12] - x[6]) / dt, 1e-12);
    x[6] = NAN;
    ddyn_ctrl_safe_command(&ctl, x, u);
    assert_true(u[0] == cfg.mpc.rate_lo[0] && u[1] == 0.0);
}

static void test_history_rows_are_the_training_rows(void **state)
{
    ddyn_ctrl_output out, prev;
    ddyn_guard_net net;
    double expect[DDYN_NC], hist[DDYN_NET_TAU][DDYN_NET_NFEAT];
    int k, f;
    (void)state;
    assert_int_equal(ddyn_guard_net_init(&net, &ddyn_net_weights), DDYN_NET_OK);
    for (k = 0; k <= DDYN_NET_TAU; ++k) {
        ddyn_ctrl_status st = run_exact(k, &out);
        if (k < DDYN_NET_TAU) {
            /* row k of the history needs period k's estimate and command: not there yet */
            assert_true(st & DDYN_CTRL_HISTORY_FILLING);
            assert_true(st & DDYN_CTRL_COEFF_NOMINAL);
            assert_memory_equal(out.coeffs, C_TRUE, sizeof C_TRUE);
        } else {
            assert_false(st & (DDYN_CTRL_HISTORY_FILLING | DDYN_CTRL_COEFF_NOMINAL | DDYN_CTRL_COEFF_LAST_GOOD));
        }
        if (k > 0) {
            /* newest row: the previous period's estimate (vx..steering) and the command applied from it */
            for (f = 0; f < 5; ++f) {
                assert_true(ctl.history[DDYN_NET_TAU - 1][f] == prev.x_est[3 + f]);
            }
            assert_true(ctl.history[DDYN_NET_TAU - 1][5] == prev.u[0]);
            assert_true(ctl.history[DDYN_NET_TAU - 1][6] == prev.u[1]);
        }
        prev = out;
    }
    /* the coefficients of the full history are the network's output for exactly that history */
    memcpy(hist, ctl.history, sizeof hist);
    assert_int_equal(ddyn_guard_net_infer(&net, (const double(*)[DDYN_NET_NFEAT])hist, expect), DDYN_NET_OK);
    assert_memory_equal(out.coeffs, expect, sizeof expect);
    assert_memory_not_equal(out.coeffs, C_TRUE, sizeof C_TRUE);
}

static void test_nonfinite_readings_rejected_counted_then_sensor_fault(void **state)
{
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    double x_before[DDYN_NX];
    int k;
    (void)state;
    run_exact(0, &out);
    for (k = 1; k <= cfg.max_sensor_faults; ++k) {
        ddyn_ctrl_status st;
        readings(&in, k);
        in.reading[DDYN_MEAS_YAW_RATE].z[0] = NAN;
        in.reading[DDYN_MEAS_WHEEL_SPEED].z[1] = INFINITY;
        memcpy(x_before, ctl.ekf.x, sizeof x_before);
        st = run(&in, &out);
        assert_true(st & DDYN_CTRL_MEAS_NONFINITE);
        assert_int_equal(ctl.nonfinite_count[DDYN_MEAS_YAW_RATE], k);
        assert_int_equal(ctl.nonfinite_count[DDYN_MEAS_WHEEL_SPEED], k);
        assert_int_equal(ctl.nonfinite_count[DDYN_MEAS_STEERING], 0);
        /* the filter went on: predicted (the car moved ~ vx dt) and fused the good readings */
        assert_true(fabs(out.x_est[1] - x_before[1]) > 0.5 * SPEED * model->sample_time);
        assert_true(isfinite(out.x_est[5]));
        assert_false(st & DDYN_CTRL_NO_MEASUREMENTS);
        if (k < cfg.max_sensor_faults) {
            assert_false(st & DDYN_CTRL_SENSOR_FAULT);
        } else {
            assert_true(st & DDYN_CTRL_SENSOR_FAULT);
            assert_true(st & DDYN_CTRL_SAFE_COMMAND);
            assert_true(out.u[1] == 0.0);
        }
    }
    /* a silent faulty sensor stays faulty */
    readings(&in, 7);
    in.reading[DDYN_MEAS_YAW_RATE].valid = 0;
    in.reading[DDYN_MEAS_WHEEL_SPEED].valid = 0;
    assert_true(run(&in, &out) & DDYN_CTRL_SENSOR_FAULT);
    /* good readings again clear the fault; safe mode still holds until recovery */
    readings(&in, 8);
    assert_false(run(&in, &out) & DDYN_CTRL_SENSOR_FAULT);
    assert_true(out.status & DDYN_CTRL_SAFE_COMMAND);
    assert_int_equal(ctl.sensor_fault_run[DDYN_MEAS_YAW_RATE], 0);
}

static void test_outlier_readings_are_gated_then_the_filter_restarts(void **state)
{
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    int k;
    (void)state;
    run_exact(0, &out);
    for (k = 1; k <= 2 * cfg.max_sensor_faults + 1; ++k) {
        ddyn_ctrl_status st;
        readings(&in, 0);
        /* a finite but absurd GNSS fix: a kilometre away, or the largest double */
        in.reading[DDYN_MEAS_GNSS_POSITION].z[0] = k % 2 ? 1000.0 : DBL_MAX;
        st = run(&in, &out);
        assert_true(st & DDYN_CTRL_MEAS_REJECTED);
        assert_false(st & DDYN_CTRL_MEAS_NONFINITE);
        assert_int_equal(ctl.rejected_count[DDYN_MEAS_GNSS_POSITION], k);
        assert_true(fabs(out.x_est[0] - plant[0]) < 0.1); /* the estimate did not jump towards it */
        /* the gate's verdict restarts the filter when the sensor becomes faulty, and again (wider)
         * after max_sensor_faults further rejections; a kilometre stays outside the wider gate */
        assert_int_equal((st & DDYN_CTRL_EKF_DIVERGED) != 0, k == cfg.max_sensor_faults || k == 2 * cfg.max_sensor_faults);
        assert_int_equal((st & DDYN_CTRL_SENSOR_FAULT) != 0, k >= cfg.max_sensor_faults);
    }
    assert_true(out.status & DDYN_CTRL_SAFE_COMMAND);
}

static void test_no_readings_for_too_long_is_safe(void **state)
{
    ddyn_ctrl_output out;
    ddyn_ctrl_input none;
    int k;
    (void)state;
    memset(&none, 0, sizeof none);
    for (k = 0; k < cfg.max_blind_steps; ++k) {
        assert_false(run(&none, &out) & DDYN_CTRL_NO_MEASUREMENTS);
    }
    assert_true(run(&none, &out) & DDYN_CTRL_NO_MEASUREMENTS);
    assert_true(out.status & DDYN_CTRL_SAFE_COMMAND);
    assert_false(run_exact(0, &out) & DDYN_CTRL_NO_MEASUREMENTS);
}

static void test_out_of_range_history_falls_back_last_good_then_nominal(void **state)
{
    ddyn_ctrl_output out;
    double last_good[DDYN_NC];
    int k;
    (void)state;
    for (k = 0; k <= DDYN_NET_TAU; ++k) {
        run_exact(k, &out);
    }
    assert_false(out.status & (DDYN_CTRL_OUT_OF_RANGE | DDYN_CTRL_COEFF_LAST_GOOD | DDYN_CTRL_COEFF_NOMINAL));
    memcpy(last_good, out.coeffs, sizeof last_good);
    /* the same car, judged against a range of a millionth of a standard deviation */
    ctl.cfg.range_sigmas = 1e-6;
    for (k = 1; k <= cfg.max_coeff_age; ++k) {
        ddyn_ctrl_status st = run_exact(k, &out);
        assert_true(st & DDYN_CTRL_OUT_OF_RANGE);
        assert_true(st & DDYN_CTRL_COEFF_LAST_GOOD);
        assert_memory_equal(out.coeffs, last_good, sizeof last_good);
    }
    run_exact(0, &out);
    assert_true(out.status & DDYN_CTRL_OUT_OF_RANGE);
    assert_true(out.status & DDYN_CTRL_COEFF_NOMINAL); /* the last good ones are too old now */
    assert_memory_equal(out.coeffs, C_TRUE, sizeof C_TRUE);
    /* back in range: the network's coefficients again */
    ctl.cfg.range_sigmas = cfg.range_sigmas;
    run_exact(1, &out);
    assert_false(out.status & (DDYN_CTRL_OUT_OF_RANGE | DDYN_CTRL_COEFF_LAST_GOOD | DDYN_CTRL_COEFF_NOMINAL));
    assert_memory_not_equal(out.coeffs, C_TRUE, sizeof C_TRUE);
}

/* a full history on the circle with a network whose every output is refused: NET_FAULT, and the
 * nominal coefficients (the true ones here) since no output was ever good */
static void drive_refused_network(const ddyn_net_tables *tables, ddyn_ctrl_output *out)
{
    int k;
    start_on_circle(tables);
    for (k = 0; k <= DDYN_NET_TAU; ++k) {
        run_exact(k, out);
    }
    assert_true(out->status & DDYN_CTRL_NET_FAULT);
    assert_true(out->status & DDYN_CTRL_COEFF_NOMINAL);
    assert_memory_equal(out->coeffs, C_TRUE, sizeof C_TRUE);
    assert_int_equal(ctl.last_good_age, -1);
}

static void test_nonfinite_network_output_falls_back_to_nominal(void **state)
{
    static ddyn_net_real nan_bias[DDYN_NET_NOUT];
    ddyn_net_tables broken = ddyn_net_weights;
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    int k;
    (void)state;
    for (k = 0; k < DDYN_NET_NOUT; ++k) {
        nan_bias[k] = (ddyn_net_real)NAN; /* a corrupted weight table */
    }
    broken.head_b = nan_bias;
    drive_refused_network(&broken, &out);
    /* several causes in one period are all reported */
    readings(&in, 1);
    in.reading[DDYN_MEAS_STEERING].z[0] = -INFINITY;
    run(&in, &out);
    assert_true((out.status & (DDYN_CTRL_NET_FAULT | DDYN_CTRL_MEAS_NONFINITE | DDYN_CTRL_COEFF_NOMINAL)) ==
                (DDYN_CTRL_NET_FAULT | DDYN_CTRL_MEAS_NONFINITE | DDYN_CTRL_COEFF_NOMINAL));
}

static void test_unusable_network_coefficients_fall_back_to_nominal(void **state)
{
    /* a network whose output is finite but not a car the model can step with (here Iz < 0 through
     * a corrupt range table): refused as the fixed and nominal sets are, not only when non-finite */
    static ddyn_net_real lo[DDYN_NET_NOUT], head_b[DDYN_NET_NOUT];
    ddyn_net_tables broken = ddyn_net_weights;
    ddyn_ctrl_output out;
    (void)state;
    memcpy(lo, ddyn_net_weights.lo, sizeof lo);
    memcpy(head_b, ddyn_net_weights.head_b, sizeof head_b);
    lo[DDYN_NET_NOUT - 1] = (ddyn_net_real)-1.0;         /* Iz range from -1 ... */
    head_b[DDYN_NET_NOUT - 1] = (ddyn_net_real)-1000.0; /* ... and the sigmoid at its lower end */
    broken.lo = lo;
    broken.head_b = head_b;
    drive_refused_network(&broken, &out);
}

static void test_indefinite_covariance_restarts_the_filter(void **state)
{
    /* a P whose diagonal is sound but which is no covariance (x-y correlation above 1): the old
     * diagonal-only check let it stand, and the position update it breaks was refused every period */
    ddyn_ctrl_output out;
    int i;
    (void)state;
    start_on_circle(&ddyn_net_weights);
    run_exact(0, &out);
    assert_false(out.status & DDYN_CTRL_EKF_DIVERGED);
    ctl.ekf.P[0 * DDYN_NX + 1] = ctl.ekf.P[1 * DDYN_NX + 0] = 3.0 * sqrt(ctl.ekf.P[0] * ctl.ekf.P[DDYN_NX + 1]);
    run_exact(1, &out);
    assert_true(out.status & DDYN_CTRL_EKF_DIVERGED);
    assert_true(out.status & DDYN_CTRL_SAFE_COMMAND);
    for (i = 0; i < DDYN_NX; ++i) { /* restarted with the initial covariance */
        assert_true(ctl.ekf.P[i * DDYN_NX + i] == cfg.p0_diag[i]);
    }
}

static void test_covariance_blowup_resets_filter_and_is_safe(void **state)
{
    ddyn_ctrl_output out;
    ddyn_ctrl_input none;
    int k, i;
    (void)state;
    /* position variance may grow to twice its initial value; without readings it does */
    cfg.p_max[0] = 2.0 * cfg.p0_diag[0];
    start_on_circle(&ddyn_net_weights);
    memset(&none, 0, sizeof none);
    for (k = 0; k < 1000 && !(run(&none, &out) & DDYN_CTRL_EKF_DIVERGED); ++k) {
        assert_true(ctl.ekf.P[0] <= cfg.p_max[0]);
    }
    assert_true(k < 1000);
    assert_true(out.status & DDYN_CTRL_SAFE_COMMAND);
    for (i = 0; i < DDYN_NX; ++i) { /* restarted with the initial covariance */
        assert_true(ctl.ekf.P[i * DDYN_NX + i] == cfg.p0_diag[i]);
    }
    assert_true(isfinite(out.x_est[0]) && isfinite(out.x_est[1]));
}

static void test_mpc_without_track_is_safe(void **state)
{
    ddyn_ctrl_output out;
    (void)state;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_OK); /* no track */
    run_exact(0, &out);
    assert_int_equal(out.mpc_status, DDYN_ERR_NOT_READY);
    assert_true(out.status & DDYN_CTRL_MPC_FAILED);
    assert_false(out.status & DDYN_CTRL_PLAN_SHIFTED);
    assert_true(out.status & DDYN_CTRL_SAFE_COMMAND);
}

/* A "perfectly trained" network for the closed-loop tests: the fixture's tables with a zero head
 * and the head bias that makes the guard output the true coefficients, and a normalisation wide
 * enough that the MPC's commands stay in range. The random fixture network would let the MPC
 * predict with coefficients that are anything inside the guard's ranges. */
static const ddyn_net_tables *oracle_tables(void)
{
    static ddyn_net_tables t;
    static ddyn_net_real head_w[DDYN_NET_NOUT * DDYN_NET_HIDDEN], head_b[DDYN_NET_NOUT];
    static const ddyn_net_real mean[DDYN_NET_NFEAT] = {1.0f, 0.0f, 0.0f, 0.3f, 0.0f, 0.0f, 0.0f};
    static const ddyn_net_real std[DDYN_NET_NFEAT] = {1.0f, 0.5f, 3.0f, 0.5f, 0.2f, 3.0f, 1.5f};
    int i;
    t = ddyn_net_weights;
    for (i = 0; i < DDYN_NET_NOUT; ++i) {
        double p = (C_TRUE[i] - (double)t.lo[i]) / ((double)t.hi[i] - (double)t.lo[i]);
        head_b[i] = (ddyn_net_real)log(p / (1.0 - p)); /* sigmoid^-1 */
    }
    t.head_w = head_w;
    t.head_b = head_b;
    t.mean = mean;
    t.std = std;
    return &t;
}

/* periods of healthy driving: the MPC converges, nothing falls back */
static void drive_healthy(int periods)
{
    ddyn_ctrl_output out;
    int k;
    for (k = 0; k < periods; ++k) {
        ddyn_ctrl_status st = run_exact(k, &out);
        double r = hypot(plant[0], plant[1]);
        assert_false(st & (DDYN_CTRL_SAFE_COMMAND | DDYN_CTRL_MEAS_NONFINITE | DDYN_CTRL_MEAS_REJECTED |
                           DDYN_CTRL_EKF_DIVERGED | DDYN_CTRL_PLAN_SHIFTED | DDYN_CTRL_MPC_FAILED));
        assert_true(fabs(r - RADIUS) < 0.15); /* on the track */
    }
}

static void test_healthy_closed_loop_follows_the_track(void **state)
{
    int i;
    (void)state;
    start_on_circle(oracle_tables());
    drive_healthy(150);
    for (i = 0; i < DDYN_NC; ++i) { /* the network's coefficients: the true ones, to float precision */
        double range = (double)ddyn_net_weights.hi[i] - (double)ddyn_net_weights.lo[i];
        assert_true(fabs(ctl.coeffs[i] - C_TRUE[i]) <= 1e-6 * range);
    } /* 3 s: more than half a lap of the 1.5 m circle at 1 m/s */
    assert_true(ctl.last_good_age == 0);
    assert_true(ctl.plan_horizon == cfg.mpc.horizon && ctl.plan_age == 0);
}

static void test_prepared_iteration_drives_like_the_full_one(void **state)
{
    /* ddyn_ctrl_prepare after each command: the next step only does the MPC's feedback phase. The
     * car follows the track as healthily, with commands close to the full iteration's. */
    static ddyn_ctrl twin;
    ddyn_ctrl_output out, out_full;
    ddyn_ctrl_input in;
    double diff = 0.0, size = 0.0;
    int k;
    (void)state;
    start_on_circle(oracle_tables());
    assert_int_equal(ddyn_ctrl_prepare(&ctl), DDYN_ERR_ARGUMENT); /* nothing to predict from yet */
    drive_healthy(20);
    for (k = 20; k < 150; ++k) {
        assert_int_equal(ddyn_ctrl_prepare(&ctl), DDYN_OK);
        assert_true(ctl.mpc.prepared);
        twin = ctl; /* the same controller, whose MPC does the whole iteration this period */
        twin.mpc.prepared = 0;
        readings(&in, k);
        assert_false(ddyn_ctrl_step(&twin, &in, &out_full) & (DDYN_CTRL_SAFE_COMMAND | DDYN_CTRL_MPC_FAILED));
        assert_false(run(&in, &out) & (DDYN_CTRL_SAFE_COMMAND | DDYN_CTRL_MPC_FAILED | DDYN_CTRL_PLAN_SHIFTED));
        assert_false(ctl.mpc.prepared); /* consumed by the step's feedback */
        assert_true(fabs(hypot(plant[0], plant[1]) - RADIUS) < 0.15);
        diff += fabs(out.u[0] - out_full.u[0]) + fabs(out.u[1] - out_full.u[1]);
        size += fabs(out_full.u[0]) + fabs(out_full.u[1]);
    }
    print_message("prepared vs full iteration: mean |du| %g of mean |u| %g\n", diff / 130, size / 130);
    assert_true(diff < 0.05 * size);
    /* a preparation made with coefficients the next period replaces (here: Bf moved by half its guard
     * range, as a fallback would) is dropped: the step runs the whole iteration, prepared at the
     * estimate itself, instead of the feedback from the predicted state */
    assert_int_equal(ddyn_ctrl_prepare(&ctl), DDYN_OK);
    ctl.mpc.c[0] += 0.5 * ((double)ddyn_net_weights.hi[0] - (double)ddyn_net_weights.lo[0]);
    readings(&in, 150);
    run(&in, &out);
    assert_memory_equal(ctl.mpc.prep_x0, out.x_est, sizeof out.x_est);
    assert_int_equal(ddyn_ctrl_prepare(&ctl), DDYN_OK); /* unchanged coefficients: the feedback runs */
    readings(&in, 151);
    run(&in, &out);
    assert_memory_not_equal(ctl.mpc.prep_x0, out.x_est, sizeof out.x_est);
}

static void test_recovery_after_a_sensor_fault(void **state)
{
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    int k;
    (void)state;
    start_on_circle(oracle_tables());
    drive_healthy(20);
    for (k = 0; k < cfg.max_sensor_faults; ++k) {
        readings(&in, k);
        in.reading[DDYN_MEAS_WHEEL_SPEED].z[0] = NAN;
        run(&in, &out);
    }
    assert_true(out.status & DDYN_CTRL_SENSOR_FAULT);
    assert_true(out.status & DDYN_CTRL_SAFE_COMMAND);
    for (k = 1; k < cfg.recovery_steps; ++k) { /* good again, but safe mode holds */
        assert_true(run_exact(k, &out) & DDYN_CTRL_SAFE_COMMAND);
        assert_false(out.status & (DDYN_CTRL_SENSOR_FAULT | DDYN_CTRL_RECOVERED));
    }
    run_exact(0, &out);
    assert_true(out.status & DDYN_CTRL_RECOVERED);
    assert_false(out.status & DDYN_CTRL_SAFE_COMMAND);
    drive_healthy(20); /* and drives on */
}

static void test_filter_reacquires_a_car_that_moved_beyond_the_gate(void **state)
{
    /* the car jumps a quarter of the circle (2.1 m, heading +90 degrees), as after a plant restart from
     * a snapshot or a filter blind while the car moved: its position and heading readings fall outside
     * the gate of the filter restarted at P0 too. The filter used to restart once per episode and then
     * gate them to the end (sensor fault, safe to the end); it now restarts again, wider, after
     * max_sensor_faults further rejections, fuses them, and the controller recovers and drives on */
    const double a = 3.14159265358979323846 / 2.0;
    ddyn_ctrl_output out;
    double px, py;
    int k, recovered = -1, faulty = 0, restarts = 0;
    (void)state;
    start_on_circle(oracle_tables());
    drive_healthy(20);
    px = plant[0];
    py = plant[1];
    plant[0] = cos(a) * px - sin(a) * py;
    plant[1] = sin(a) * px + cos(a) * py;
    plant[2] += a;
    for (k = 0; k < 300 && recovered < 0; ++k) {
        run_exact(k, &out);
        faulty |= (out.status & DDYN_CTRL_SENSOR_FAULT) != 0;
        restarts += (out.status & DDYN_CTRL_EKF_DIVERGED) != 0;
        if (out.status & DDYN_CTRL_RECOVERED) {
            recovered = k;
        }
    }
    print_message("jump of a quarter circle: %d filter restarts, recovered in period %d\n", restarts, recovered);
    assert_true(faulty && restarts >= 2);
    assert_true(recovered >= 0);
    assert_true(hypot(out.x_est[0] - plant[0], out.x_est[1] - plant[1]) < 0.1);
    for (k = 0; k < 100; ++k) { /* drives on along the circle, never safe again */
        run_exact(k, &out);
        assert_false(out.status & (DDYN_CTRL_SAFE_COMMAND | DDYN_CTRL_SENSOR_FAULT));
    }
    assert_true(fabs(hypot(plant[0], plant[1]) - RADIUS) < 0.15 && plant[3] > 0.5);
}

/* A blind spell with the car frozen (a plant that restarts from its snapshot: its time stops while the
 * controller's goes on): the filter predicts on for `blind` periods without a reading, then the frozen
 * car's readings return, with (first_period 0) or without (1: a period caught up without its position
 * frame) the position and heading. */
static void blind_spell_then_readings(int blind, int first_period)
{
    ddyn_ctrl_output out;
    ddyn_ctrl_input none;
    double frozen[DDYN_NX];
    int k, recovered = -1, faulty = 0;
    start_on_circle(oracle_tables());
    drive_healthy(20);
    memcpy(frozen, plant, sizeof frozen);
    memset(&none, 0, sizeof none);
    for (k = 0; k < blind; ++k) {
        run(&none, &out); /* the safe command brakes the filter's car */
    }
    /* the prediction ran on: the estimate is away from the frozen car */
    assert_true(hypot(out.x_est[0] - frozen[0], out.x_est[1] - frozen[1]) > 0.05);
    memcpy(plant, frozen, sizeof frozen);
    /* the DBW unit takes set-points (ddyn_sil_node): the actuators go to the controller's, which the
     * filter knows (this harness integrates rates, so it is put there) */
    plant[6] = out.x_est[6];
    plant[7] = out.x_est[7];
    run_exact(first_period, &out);
    /* the filter restarted on the readings that came back: every state they read directly */
    assert_true(out.status & DDYN_CTRL_EKF_DIVERGED);
    assert_true(fabs(out.x_est[3] - plant[3]) < 0.05);
    if (first_period % 5 == 0) {
        assert_true(hypot(out.x_est[0] - plant[0], out.x_est[1] - plant[1]) < 0.05);
    }
    for (k = first_period + 1; k < 200 && recovered < 0; ++k) {
        run_exact(k, &out);
        faulty |= (out.status & (DDYN_CTRL_SENSOR_FAULT | DDYN_CTRL_EKF_DIVERGED)) != 0;
        if (out.status & DDYN_CTRL_RECOVERED) {
            recovered = k;
        }
    }
    print_message("blind %d periods, first readings at period %d: recovered in period %d\n", blind, first_period,
                  recovered);
    /* no reading gated into a sensor fault, no further restart; recovery after recovery_steps */
    assert_false(faulty);
    assert_true(recovered >= 0 && recovered <= first_period + cfg.recovery_steps + 5);
    assert_true(hypot(out.x_est[0] - plant[0], out.x_est[1] - plant[1]) < 0.05);
    for (k = 0; k < 100; ++k) { /* drives on along the circle, never safe again */
        run_exact(k, &out);
        assert_false(out.status & (DDYN_CTRL_SAFE_COMMAND | DDYN_CTRL_SENSOR_FAULT));
    }
    assert_true(fabs(hypot(plant[0], plant[1]) - RADIUS) < 0.15 && plant[3] > 0.5);
}

static void test_filter_restarts_on_the_readings_after_a_blind_spell(void **state)
{
    /* the SIL's plant restart: 0.5 s without frames (25 periods) and more; before, the filter restarted at
     * its predicted estimate and gated the returning readings (in one guest run it stayed at vx -0.5 m/s
     * to the end of the run) */
    (void)state;
    blind_spell_then_readings(25, 0);
    blind_spell_then_readings(40, 0);
    blind_spell_then_readings(cfg.max_sensor_faults, 0);
    /* the first period back without its position: the position starts wide and its reading fuses */
    blind_spell_then_readings(25, 1);
}

static void test_qp_not_converged_shifts_the_plan_then_safe(void **state)
{
    double plan[DDYN_MPC_NV];
    ddyn_ctrl_output out;
    int a, iterations = cfg.mpc.qp_max_iterations;
    (void)state;
    start_on_circle(oracle_tables());
    drive_healthy(20);
    memcpy(plan, ctl.plan_u, sizeof plan);
    ctl.mpc.cfg.qp_max_iterations = 1; /* white box: a QP that cannot converge in one iteration */
    ctl.mpc.cfg.qp_tolerance = 1e-300; /* (the interior point; DAQP gets a wrong working set below) */
    for (a = 1; a <= cfg.max_plan_shift; ++a) {
        ddyn_ctrl_status st;
        ddyn_mpc_qp_daqp_adversarial_start(&ctl.mpc.daqp, ctl.mpc.cfg.horizon);
        st = run_exact(a, &out);
        assert_int_equal(out.mpc_status, DDYN_ERR_QP_NOT_CONVERGED);
        assert_true(st & DDYN_CTRL_MPC_NOT_CONVERGED);
        assert_true(st & DDYN_CTRL_PLAN_SHIFTED);
        assert_false(st & DDYN_CTRL_SAFE_COMMAND);
        /* the converged plan of `a` periods ago, at the stage that is now */
        assert_true(out.u[0] == plan[a * DDYN_NU] && out.u[1] == plan[a * DDYN_NU + 1]);
    }
    ddyn_mpc_qp_daqp_adversarial_start(&ctl.mpc.daqp, ctl.mpc.cfg.horizon);
    run_exact(0, &out);
    assert_true(out.status & DDYN_CTRL_MPC_NOT_CONVERGED);
    assert_false(out.status & DDYN_CTRL_PLAN_SHIFTED);
    assert_true(out.status & DDYN_CTRL_SAFE_COMMAND);
    assert_true(out.u[1] == 0.0);
    /* the solver converges again: safe mode holds for recovery_steps periods, then the MPC drives */
    ctl.mpc.cfg.qp_max_iterations = iterations;
    ctl.mpc.cfg.qp_tolerance = cfg.mpc.qp_tolerance;
    for (a = 1; a < cfg.recovery_steps; ++a) {
        assert_true(run_exact(a, &out) & DDYN_CTRL_SAFE_COMMAND);
    }
    assert_true(run_exact(0, &out) & DDYN_CTRL_RECOVERED);
    drive_healthy(20);
}


/* ---- fixed coefficients and the throttle PID ------------------------------------------------ */

/* the controller on the circle with fixed coefficients c (no network tables at all), throttle by
 * PID with the given gains, the car (plant) starting on the circle at vx0 with the throttle it had */
static void start_pid_on_circle(const double c[DDYN_NC], double vx0, double kp, double ki, double kd)
{
    cfg.coeff_source = DDYN_CTRL_SOURCE_FIXED;
    memcpy(cfg.c_fixed, c, sizeof cfg.c_fixed);
    cfg.throttle_mode = DDYN_CTRL_THROTTLE_PID;
    cfg.pid.kp = kp;
    cfg.pid.ki = ki;
    cfg.pid.kd = kd;
    start_on_circle_at(NULL, vx0);
}

static void test_fixed_coefficients_bypass_the_network(void **state)
{
    ddyn_ctrl_output out;
    double c[DDYN_NC];
    int k;
    (void)state;
    memcpy(c, C_TRUE, sizeof c);
    c[DDYN_NC - 1] *= 1.2; /* Iz + 20 %: not the nominal ones */
    cfg.coeff_source = DDYN_CTRL_SOURCE_FIXED;
    memcpy(cfg.c_fixed, c, sizeof c);
    start_on_circle(&ddyn_net_weights); /* tables given: validated, never run */
    for (k = 0; k < 3 * DDYN_NET_TAU + 5; ++k) {
        ddyn_ctrl_status st = run_exact(k, &out);
        /* every period, from the first: no history filling, no range check, no fallback */
        assert_true(st & DDYN_CTRL_COEFF_FIXED);
        assert_false(st & (DDYN_CTRL_HISTORY_FILLING | DDYN_CTRL_OUT_OF_RANGE | DDYN_CTRL_NET_FAULT |
                           DDYN_CTRL_COEFF_LAST_GOOD | DDYN_CTRL_COEFF_NOMINAL | DDYN_CTRL_SAFE_COMMAND));
        assert_memory_equal(out.coeffs, c, sizeof c);
        assert_memory_equal(ctl.mpc.c, c, sizeof c); /* the MPC predicts with them */
    }
    assert_int_equal(ctl.last_good_age, -1); /* the network never ran */
    /* a range check of a millionth of a standard deviation (what the SIL used to bypass the network
     * with) changes nothing here */
    ctl.cfg.range_sigmas = 1e-6;
    assert_false(run_exact(0, &out) & DDYN_CTRL_OUT_OF_RANGE);
    /* the network mode's default is unchanged: it does not report fixed coefficients */
    cfg.coeff_source = DDYN_CTRL_SOURCE_NETWORK;
    start_on_circle(&ddyn_net_weights);
    assert_false(run_exact(0, &out) & DDYN_CTRL_COEFF_FIXED);
}

static void test_pid_throttle_follows_the_law_and_the_plan_holds_it(void **state)
{
    /* the documented law (ddyn/controller.h), computed here from the controller's own estimate, and
     * the MPC's plan: throttle rate dthrottle at stage 0, then 0, so the throttle stays put */
    const double kp = 0.8, ki = 2.0, kd = 0.05, dt = model->sample_time;
    double integral = 0.0, vx_prev = 0.0, xp[(DDYN_MPC_MAX_HORIZON + 1) * DDYN_NX], up[DDYN_MPC_NV];
    ddyn_ctrl_output out;
    int k, j, saturated = 0, unsaturated = 0;
    (void)state;
    start_pid_on_circle(C_TRUE, 0.2, kp, ki, kd);
    for (k = 0; k < 100; ++k) {
        const double *x;
        double e, raw, target, rate, applied;
        ddyn_ctrl_status st = run_exact(k, &out);
        assert_false(st & (DDYN_CTRL_SAFE_COMMAND | DDYN_CTRL_PLAN_SHIFTED | DDYN_CTRL_MPC_FAILED));
        assert_int_equal(out.mpc_status, DDYN_OK);
        x = out.x_est; /* the estimate the period acted on */
        assert_true(out.pid_ref_speed == SPEED); /* the circle's table speed */
        e = SPEED - x[3];
        raw = kp * e + integral - (k > 0 ? kd * (x[3] - vx_prev) / dt : 0.0);
        target = clamp_d(raw, cfg.mpc.state_lo[0], cfg.mpc.state_hi[0]);
        rate = clamp_d((target - x[6]) / dt, cfg.mpc.rate_lo[0], cfg.mpc.rate_hi[0]);
        applied = x[6] + dt * rate;
        assert_float_equal(out.pid_throttle, target, 1e-12);
        assert_float_equal(out.u[0], rate, 1e-9);
        if (fabs(raw - applied) > 1e-9) {
            saturated += 1;
            assert_true(st & DDYN_CTRL_PID_SATURATED);
        } else {
            unsaturated += 1;
            assert_false(st & DDYN_CTRL_PID_SATURATED);
        }
        if (!((raw > applied + 1e-9 && e > 0.0) || (raw < applied - 1e-9 && e < 0.0))) {
            integral = clamp_d(integral + ki * e * dt, cfg.mpc.state_lo[0], cfg.mpc.state_hi[0]);
        }
        assert_float_equal(out.pid_integral, integral, 1e-9);
        vx_prev = x[3];
        /* the plan: the PID's rate first, then a held throttle; the steering is planned */
        assert_int_equal(ddyn_mpc_plan(&ctl.mpc, xp, up), cfg.mpc.horizon);
        assert_true(up[0] == out.u[0] && up[1] == out.u[1]);
        for (j = 1; j < cfg.mpc.horizon; ++j) {
            assert_true(up[j * DDYN_NU] == 0.0);
            assert_float_equal(xp[(j + 1) * DDYN_NX + 6], xp[DDYN_NX + 6], 1e-12);
        }
        assert_float_equal(xp[DDYN_NX + 6], applied, 1e-12);
    }
    print_message("pid law: %d periods cut by a bound, %d not\n", saturated, unsaturated);
    /* the start (0.8 m/s below the reference) drove the throttle into its rate bound, later not */
    assert_true(saturated > 0 && unsaturated > 10);
}

static void test_pid_closed_loop_reaches_and_holds_the_speed(void **state)
{
    /* true coefficients, default gains: from 0.3 m/s to the circle's 1 m/s, then held */
    ddyn_ctrl_output out;
    double worst = 0.0, sum = 0.0;
    int k;
    (void)state;
    start_pid_on_circle(C_TRUE, 0.3, cfg.pid.kp, cfg.pid.ki, cfg.pid.kd);
    for (k = 0; k < 750; ++k) { /* 15 s: the default ki (0.5) removes the last of the error slowly */
        ddyn_ctrl_status st = run_exact(k, &out);
        assert_false(st & (DDYN_CTRL_SAFE_COMMAND | DDYN_CTRL_MPC_FAILED));
        assert_true(fabs(hypot(plant[0], plant[1]) - RADIUS) < 0.15); /* the steering MPC keeps the track */
        if (k >= 650) { /* the last 2 s: the true speed */
            worst = fmax(worst, fabs(plant[3] - SPEED));
            sum += plant[3] - SPEED;
        }
    }
    print_message("pid closed loop: worst |vx - v_ref| %.4f m/s, mean %.5f m/s over the last 2 s\n", worst,
                  sum / 100.0);
    assert_true(worst < PID_WORST_ERROR);
    assert_true(fabs(sum / 100.0) < PID_MEAN_ERROR);
}

static void test_pid_anti_windup(void **state)
{
    /* a car too weak for the reference: Cm1 at 30 %, top speed ~0.63 m/s against 1 m/s. The throttle
     * sits at its upper bound; the integral must not grow while it does (a plain integral would gain
     * ki * 0.4 m/s per second, far past the throttle's range). Then the reference drops below the
     * car's speed, and the throttle must leave the bound at once, not after unwinding an integral. */
    static double x[TRACK_N], y[TRACK_N], v[TRACK_N], wl[TRACK_N], wr[TRACK_N];
    const double pi = 3.14159265358979323846, kp = 0.8, ki = 2.0, dt = model->sample_time;
    double weak[DDYN_NC], integral = 0.0, plain = 0.0, vx;
    ddyn_ctrl_output out;
    int k, saturated = 0;
    (void)state;
    memcpy(weak, C_TRUE, sizeof weak);
    weak[12] *= 0.3;
    memcpy(plant_c, weak, sizeof weak);
    start_pid_on_circle(weak, 0.4, kp, ki, 0.0);
    for (k = 0; k < 150; ++k) { /* 3 s */
        run_exact(k, &out);
        plain += ki * (SPEED - out.x_est[3]) * dt;
        /* at the bound up to rounding: thr + dt * ((hi - thr) / dt) need not be hi exactly */
        if (out.pid_throttle >= cfg.mpc.state_hi[0] - 1e-9 && plant[6] >= cfg.mpc.state_hi[0] - 1e-9) {
            saturated += 1; /* the output was cut at full throttle, the speed error positive: */
            assert_true(out.status & DDYN_CTRL_PID_SATURATED);
            assert_true(out.pid_integral == integral); /* the integral held */
        }
        integral = out.pid_integral;
        assert_true(fabs(hypot(plant[0], plant[1]) - RADIUS) < 0.15);
    }
    print_message("anti-windup: %d of 150 periods at full throttle, integral %.3f (plain integral %.2f), "
                  "vx %.3f m/s\n", saturated, out.pid_integral, plain, plant[3]);
    assert_true(saturated > 100);
    assert_true(plant[3] > 0.5 && plant[3] < 0.7 && plant[6] > 0.999); /* full throttle, below the reference */
    /* the integral sits where kp e + I just reaches the bound (1 - 0.8 * 0.37 m/s), not at the
     * throttle's cap of 1 where a plain integral (past 1.5) would sit */
    assert_true(plain > 1.5 && out.pid_integral < 0.8);
    /* the reference drops to 0.3 m/s: the very next period's target is kp e + I, off the bound (with a
     * wound-up integral at its cap of 1 it would still be above 0.7) */
    for (k = 0; k < TRACK_N; ++k) {
        double a = 2.0 * pi * k / TRACK_N;
        x[k] = RADIUS * cos(a);
        y[k] = RADIUS * sin(a);
        v[k] = 0.3;
        wl[k] = 0.15;
        wr[k] = 0.15;
    }
    vx = ctl.ekf.x[3];
    assert_int_equal(ddyn_ctrl_set_track(&ctl, TRACK_N, x, y, v, wl, wr), DDYN_OK);
    run_exact(0, &out);
    print_message("anti-windup: after the drop the target is %.3f\n", out.pid_throttle);
    assert_true(out.pid_throttle < 0.5);
    assert_true(fabs(out.pid_throttle - (kp * (0.3 - vx) + integral)) < 0.02); /* vx: the last estimate */
    assert_true(out.u[0] < 0.0);
}

/* ---- degraded-bus mode (ddyn_ctrl_degraded_config) ---- */

static void test_degraded_config_is_checked(void **state)
{
    ddyn_ctrl_config bad;
    (void)state;
    bad = cfg;
    bad.degraded.r_scale = 0.5; /* would trust the degraded bus more */
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &bad, plant), DDYN_ERR_ARGUMENT);
    bad = cfg;
    bad.degraded.speed_scale = 0.0;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &bad, plant), DDYN_ERR_ARGUMENT);
    bad = cfg;
    bad.degraded.max_age = (DDYN_CTRL_AGE_PERIODS + 1) * model->sample_time; /* beyond the stored estimates */
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &bad, plant), DDYN_ERR_ARGUMENT);
    bad = cfg;
    bad.degraded.recovery_periods = 0;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &bad, plant), DDYN_ERR_ARGUMENT);
    bad = cfg;
    bad.degraded.rate_weight_scale = NAN;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &bad, plant), DDYN_ERR_ARGUMENT);
}

static void test_bus_faults_enter_degraded_mode_and_recovery_has_hysteresis(void **state)
{
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    int k;
    (void)state;
    cfg.degraded.rate_weight_scale = 4.0;
    cfg.degraded.speed_scale = 0.8;
    cfg.degraded.recovery_periods = 10;
    start_on_circle(oracle_tables());
    drive_healthy(20);
    assert_false(ctl.degraded);
    assert_int_equal(ddyn_ctrl_stale_limit(&ctl, 1), 1);
    readings(&in, 20);
    in.bus_faults = 3u; /* e.g. three frames lost since the last period */
    assert_true(run(&in, &out) & DDYN_CTRL_BUS_DEGRADED);
    assert_true(ctl.mpc.cfg.r_rate[1] == 4.0 * cfg.mpc.r_rate[1]); /* heavier input-rate weights */
    assert_true(ctl.mpc.track.speed_scale == 0.8);                  /* a slower reference */
    assert_int_equal(ddyn_ctrl_stale_limit(&ctl, 1), 1 + cfg.degraded.stale_extra_periods);
    for (k = 1; k < cfg.degraded.recovery_periods; ++k) { /* clean, but not long enough */
        assert_true(run_exact(20 + k, &out) & DDYN_CTRL_BUS_DEGRADED);
        assert_false(out.status & DDYN_CTRL_BUS_RECOVERED);
    }
    readings(&in, 30);
    in.bus_faults = 1u; /* a fault before the end: the count starts again */
    assert_true(run(&in, &out) & DDYN_CTRL_BUS_DEGRADED);
    for (k = 1; k < cfg.degraded.recovery_periods; ++k) {
        assert_true(run_exact(30 + k, &out) & DDYN_CTRL_BUS_DEGRADED);
    }
    run_exact(40, &out);
    assert_true(out.status & DDYN_CTRL_BUS_RECOVERED);
    assert_false(out.status & DDYN_CTRL_BUS_DEGRADED);
    assert_true(ctl.mpc.cfg.r_rate[1] == cfg.mpc.r_rate[1]); /* the racing weights and speed again */
    assert_true(ctl.mpc.track.speed_scale == 1.0);
    assert_int_equal(ddyn_ctrl_stale_limit(&ctl, 1), 1);
    assert_int_equal((int)ctl.degraded_periods, 2 * cfg.degraded.recovery_periods);
    assert_false(out.status & DDYN_CTRL_SAFE_COMMAND); /* degraded is not safe mode */
}

static void test_old_readings_and_latency_mark_the_bus_degraded(void **state)
{
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    (void)state;
    start_on_circle(oracle_tables());
    drive_healthy(10);
    readings(&in, 10);
    in.reading[DDYN_MEAS_YAW_RATE].age = 0.5 * cfg.degraded.age_tolerance; /* within the tolerance */
    assert_false(run(&in, &out) & DDYN_CTRL_BUS_DEGRADED);
    readings(&in, 11);
    in.reading[DDYN_MEAS_YAW_RATE].age = 2.0 * cfg.degraded.age_tolerance;
    assert_true(run(&in, &out) & DDYN_CTRL_BUS_DEGRADED);
    start_on_circle(oracle_tables());
    drive_healthy(10);
    readings(&in, 10);
    in.latency = 2.0 * cfg.degraded.age_tolerance; /* the period itself runs late */
    assert_true(run(&in, &out) & DDYN_CTRL_BUS_DEGRADED);
    /* a reading as old as the period is current relative to it */
    start_on_circle(oracle_tables());
    drive_healthy(10);
    readings(&in, 10);
    in.latency = 0.5 * cfg.degraded.age_tolerance;
    in.reading[DDYN_MEAS_YAW_RATE].age = 1.4 * cfg.degraded.age_tolerance;
    assert_false(run(&in, &out) & DDYN_CTRL_BUS_DEGRADED);
    readings(&in, 11);
    in.reading[DDYN_MEAS_STEERING].age = -1.0; /* a caller's bug: not fusable, counted */
    assert_true(run(&in, &out) & DDYN_CTRL_MEAS_REJECTED);
}

/* readings of the state x (every sensor but the accelerometer; GNSS and heading every 5th period) */
static void readings_of(const double x[DDYN_NX], ddyn_ctrl_input *in, int period)
{
    double saved[DDYN_NX];
    memcpy(saved, plant, sizeof saved);
    memcpy(plant, x, sizeof saved);
    readings(in, period);
    memcpy(plant, saved, sizeof saved);
}

static void test_aged_readings_are_moved_to_the_period_time(void **state)
{
    /* every reading two periods old (as on a bus that delays them): the controller told their age
     * places them on its own trajectory; a twin given the same readings as if fresh lags behind */
    static ddyn_ctrl twin;
    double past[3][DDYN_NX], err_aged = 0.0, err_fresh = 0.0;
    ddyn_ctrl_output out, out_twin;
    ddyn_ctrl_input in;
    int k;
    (void)state;
    cfg.degraded.r_scale = 1.0; /* the same measurement noise in both: only the dating differs */
    start_on_circle(oracle_tables());
    drive_healthy(20);
    twin = ctl;
    for (k = 0; k < 3; ++k) {
        memcpy(past[k], plant, sizeof plant);
    }
    for (k = 0; k < 100; ++k) {
        readings_of(past[2], &in, k); /* the plant two periods ago */
        ddyn_ctrl_step(&twin, &in, &out_twin);
        for (int j = 0; j < DDYN_MEAS_COUNT; ++j) {
            in.reading[j].age = 2.0 * model->sample_time;
        }
        run(&in, &out);
        assert_false(out.status & (DDYN_CTRL_SAFE_COMMAND | DDYN_CTRL_MEAS_REJECTED));
        memcpy(twin.u_prev, ctl.u_prev, sizeof twin.u_prev); /* the plant got ctl's commands */
        memcpy(past[2], past[1], sizeof plant);
        memcpy(past[1], past[0], sizeof plant);
        memcpy(past[0], plant, sizeof plant);
        if (k >= 20) {
            /* position error against the plant at the end of the period the estimates are for */
            err_aged += hypot(out.x_est[0] - past[1][0], out.x_est[1] - past[1][1]);
            err_fresh += hypot(out_twin.x_est[0] - past[1][0], out_twin.x_est[1] - past[1][1]);
        }
    }
    print_message("position error over 80 periods: aged readings dated %g m, taken as fresh %g m\n",
                  err_aged / 80, err_fresh / 80);
    assert_true(err_aged < 0.5 * err_fresh);
    assert_true(err_aged / 80 < 0.01);
    /* older than max_age: not fused, not the sensor's fault */
    readings(&in, 1);
    in.reading[DDYN_MEAS_WHEEL_SPEED].age = cfg.degraded.max_age + model->sample_time;
    assert_true(run(&in, &out) & DDYN_CTRL_MEAS_REJECTED);
    assert_int_equal(ctl.sensor_fault_run[DDYN_MEAS_WHEEL_SPEED], 0);
}

static void test_the_plan_starts_after_the_latency(void **state)
{
    /* the same period, 40 ms late: the MPC starts from the estimate predicted 40 ms ahead (about 4 cm
     * further along the circle at 1 m/s); a latency beyond max_age is cut there */
    static ddyn_ctrl a, b, c;
    ddyn_ctrl_output oa, ob, oc;
    ddyn_ctrl_input in;
    double lat = 0.040;
    (void)state;
    cfg.degraded.r_scale = 1.0; /* (a late period is degraded: the same filter in all three) */
    start_on_circle(oracle_tables());
    drive_healthy(30);
    a = ctl;
    b = ctl;
    c = ctl;
    readings(&in, 30);
    ddyn_ctrl_step(&a, &in, &oa);
    in.latency = lat;
    ddyn_ctrl_step(&b, &in, &ob);
    in.latency = 1.0;
    ddyn_ctrl_step(&c, &in, &oc);
    print_message("progress %g, %g after %g s latency, %g after 1 s\n", oa.mpc_info.progress, ob.mpc_info.progress, lat,
                  oc.mpc_info.progress);
    assert_true(fabs(ob.mpc_info.progress - oa.mpc_info.progress - lat * SPEED) < 0.25 * lat * SPEED);
    assert_true(fabs(oc.mpc_info.progress - oa.mpc_info.progress - cfg.degraded.max_age * SPEED) <
                0.25 * cfg.degraded.max_age * SPEED);
    assert_memory_equal(oa.x_est, ob.x_est, sizeof oa.x_est); /* the estimate itself is not moved */
}

static void test_a_command_not_sent_is_predicted_held(void **state)
{
    static ddyn_ctrl twin;
    ddyn_ctrl_output out, out_twin;
    ddyn_ctrl_input in;
    (void)state;
    start_on_circle(oracle_tables());
    drive_healthy(25);
    run_exact(25, &out);
    assert_true(fabs(out.u[1]) > 0.0);
    twin = ctl;
    ddyn_ctrl_command_not_sent(&ctl);
    assert_true(ctl.u_prev[0] == 0.0 && ctl.u_prev[1] == 0.0);
    memset(&in, 0, sizeof in); /* no readings: the estimate is the prediction alone */
    ddyn_ctrl_step(&ctl, &in, &out);
    ddyn_ctrl_step(&twin, &in, &out_twin);
    assert_true(out.x_est[7] == ctl.x_hist[1][7]);        /* steering held */
    assert_true(out_twin.x_est[7] != twin.x_hist[1][7]); /* the twin assumed the command applied */
    /* another command went out (the caller's safe command): the filter predicts with it */
    {
        const double sent[DDYN_NU] = {-1.0, 0.25}, bad[DDYN_NU] = {NAN, 0.0};
        ddyn_ctrl_command_applied(&ctl, sent);
        ddyn_ctrl_command_applied(&ctl, bad); /* ignored */
        assert_true(ctl.u_prev[0] == sent[0] && ctl.u_prev[1] == sent[1]);
        ddyn_ctrl_step(&ctl, &in, &out);
        assert_true(fabs(out.x_est[7] - (ctl.x_hist[1][7] + model->sample_time * sent[1])) < 1e-12);
    }
}

/* ---- actuation delays (ddyn_ctrl_delay_config, ddyn_ctrl_delay_line) ---- */

static void test_delay_line_returns_the_command_sent_n_periods_ago_and_wraps(void **state)
{
    ddyn_ctrl_delay_line d;
    const int ring = DDYN_CTRL_MAX_DELAY_STEPS + 1;
    int pushed, n;
    (void)state;
    ddyn_ctrl_delay_line_reset(&d, -7.0);
    for (n = 0; n <= DDYN_CTRL_MAX_DELAY_STEPS; ++n) {
        assert_true(ddyn_ctrl_delay_line_ago(&d, n) == -7.0); /* "since forever" */
    }
    /* three times round the ring: value p is the p-th command sent */
    for (pushed = 1; pushed <= 3 * ring + 1; ++pushed) {
        ddyn_ctrl_delay_line_push(&d, (double)pushed);
        for (n = 0; n <= DDYN_CTRL_MAX_DELAY_STEPS; ++n) {
            const double want = pushed - n >= 1 ? (double)(pushed - n) : -7.0;
            assert_true(ddyn_ctrl_delay_line_ago(&d, n) == want);
        }
    }
    /* outside 0..max: NaN, never another entry */
    assert_true(isnan(ddyn_ctrl_delay_line_ago(&d, -1)));
    assert_true(isnan(ddyn_ctrl_delay_line_ago(&d, DDYN_CTRL_MAX_DELAY_STEPS + 1)));
    /* the caller sent another command: only the newest changes */
    ddyn_ctrl_delay_line_set_newest(&d, 0.5);
    assert_true(ddyn_ctrl_delay_line_ago(&d, 0) == 0.5);
    assert_true(ddyn_ctrl_delay_line_ago(&d, 1) == (double)(3 * ring));
}

static void test_delay_above_the_compiled_maximum_is_refused_at_init(void **state)
{
    const double dt = model->sample_time, max_s = DDYN_CTRL_MAX_DELAY_STEPS * dt;
    ddyn_ctrl_delay_config d = {0.0, 0.0};
    int steps[DDYN_NU] = {-1, -1};
    (void)state;
    /* seconds to the NEAREST whole period (a half rounds up, to 1e-6 of a period; issue 34: it was floor) */
    d.steering = 0.04;
    d.throttle = 0.1;
    assert_int_equal(ddyn_ctrl_delay_steps(&d, 0.02, steps), DDYN_OK);
    assert_int_equal(steps[DDYN_CTRL_CH_STEERING], 2);
    assert_int_equal(steps[DDYN_CTRL_CH_THROTTLE], 5);
    d.steering = 0.057; /* 2.85 periods: 3 (floor gave 2) */
    d.throttle = 0.029; /* 1.45 periods: 1 */
    assert_int_equal(ddyn_ctrl_delay_steps(&d, 0.02, steps), DDYN_OK);
    assert_int_equal(steps[DDYN_CTRL_CH_STEERING], 3);
    assert_int_equal(steps[DDYN_CTRL_CH_THROTTLE], 1);
    d.steering = 0.03; /* 1.5 periods (0.03 / 0.02 = 1.4999999999999998 in doubles): 2 */
    d.throttle = 0.009; /* 0.45 periods: none */
    assert_int_equal(ddyn_ctrl_delay_steps(&d, 0.02, steps), DDYN_OK);
    assert_int_equal(steps[DDYN_CTRL_CH_STEERING], 2);
    assert_int_equal(steps[DDYN_CTRL_CH_THROTTLE], 0);
    d.steering = 0.05; /* 2.5 periods: 3 */
    d.throttle = 0.0;
    assert_int_equal(ddyn_ctrl_delay_steps(&d, 0.02, steps), DDYN_OK);
    assert_int_equal(steps[DDYN_CTRL_CH_STEERING], 3);
    assert_int_equal(steps[DDYN_CTRL_CH_THROTTLE], 0);
    d.steering = max_s;
    assert_int_equal(ddyn_ctrl_delay_steps(&d, dt, steps), DDYN_OK);
    assert_int_equal(steps[DDYN_CTRL_CH_STEERING], DDYN_CTRL_MAX_DELAY_STEPS);
    d.steering = max_s + 0.4 * dt; /* rounds to the maximum */
    assert_int_equal(ddyn_ctrl_delay_steps(&d, dt, steps), DDYN_OK);
    assert_int_equal(steps[DDYN_CTRL_CH_STEERING], DDYN_CTRL_MAX_DELAY_STEPS);
    /* rounding above the maximum, negative, not finite: refused, steps untouched */
    steps[0] = steps[1] = -1;
    d.steering = max_s + 0.5 * dt;
    assert_int_equal(ddyn_ctrl_delay_steps(&d, dt, steps), DDYN_ERR_ARGUMENT);
    d.steering = -1e-9;
    assert_int_equal(ddyn_ctrl_delay_steps(&d, dt, steps), DDYN_ERR_ARGUMENT);
    d.steering = NAN;
    assert_int_equal(ddyn_ctrl_delay_steps(&d, dt, steps), DDYN_ERR_ARGUMENT);
    d.steering = 0.0;
    d.throttle = INFINITY;
    assert_int_equal(ddyn_ctrl_delay_steps(&d, dt, steps), DDYN_ERR_ARGUMENT);
    assert_true(steps[0] == -1 && steps[1] == -1);
    /* at init: the controller refuses it (no silent cut to the maximum) */
    cfg.delay.steering = (DDYN_CTRL_MAX_DELAY_STEPS + 1) * dt;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_ERR_ARGUMENT);
    cfg.delay.steering = 0.0;
    cfg.delay.throttle = (DDYN_CTRL_MAX_DELAY_STEPS + 1) * dt;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_ERR_ARGUMENT);
    cfg.delay.throttle = max_s;
    cfg.delay.steering = max_s;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_OK);
    assert_int_equal(ctl.delay_steps[DDYN_CTRL_CH_STEERING], DDYN_CTRL_MAX_DELAY_STEPS);
}

/* the delayed plant: the command sent `ds` (steering) and `dt_` (throttle) periods ago acts over the
 * period; sent[j] is the command of period j */
#define DELAY_PERIODS 60
static double sent_log[DELAY_PERIODS][DDYN_NU];

static void run_delayed_plant(int period, int ds, int dthr, const ddyn_ctrl_output *out)
{
    double u[DDYN_NU], next[DDYN_NX];
    memcpy(sent_log[period], out->u, sizeof sent_log[period]);
    u[0] = period - dthr >= 0 ? sent_log[period - dthr][0] : 0.0;
    u[1] = period - ds >= 0 ? sent_log[period - ds][1] : 0.0;
    assert_int_equal(ddyn_model_step(model, DDYN_DISC_RK4, plant, u, plant_c, next, &plant_work), DDYN_OK);
    memcpy(plant, next, sizeof next);
}

static void test_a_steering_delay_shortens_the_horizon_by_its_periods(void **state)
{
    /* issue 34: the plan ends where it would without the delay. With a steering delay of n periods the
     * MPC's horizon is cfg.mpc.horizon - n (the config kept as given); a throttle delay alone keeps it;
     * a config whose max_plan_shift the shortened horizon does not exceed is refused */
    const double dt = model->sample_time;
    const int h = cfg.mpc.horizon;
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    double up[DDYN_MPC_NV];
    int k;
    (void)state;
    cfg.delay.steering = 3.0 * dt;
    start_on_circle(oracle_tables());
    assert_int_equal(ctl.mpc.cfg.horizon, h - 3);
    assert_int_equal(ctl.cfg.mpc.horizon, h);
    for (k = 0; k < 5; ++k) {
        readings(&in, k);
        ddyn_ctrl_step(&ctl, &in, &out);
        run_delayed_plant(k, 3, 0, &out);
    }
    assert_int_equal(ddyn_mpc_plan_inputs(&ctl.mpc, up), h - 3);
    assert_int_equal(ctl.plan_horizon, h - 3);
    cfg.delay.steering = 0.0;
    cfg.delay.throttle = 3.0 * dt;
    start_on_circle(oracle_tables());
    assert_int_equal(ctl.mpc.cfg.horizon, h);
    /* the plan shift must stay inside the shortened horizon */
    cfg.delay.throttle = 0.0;
    cfg.delay.steering = 2.0 * dt;
    cfg.mpc.horizon = 5;
    cfg.max_plan_shift = 3;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_ERR_ARGUMENT);
    cfg.max_plan_shift = 2;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_OK);
    assert_int_equal(ctl.mpc.cfg.horizon, 3);
    /* a delay that leaves no stage is refused, not cut */
    cfg.max_plan_shift = 0;
    cfg.mpc.horizon = 2;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_ERR_ARGUMENT);
    cfg.mpc.horizon = 3;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_OK);
    assert_int_equal(ctl.mpc.cfg.horizon, 1);
    /* a longer throttle delay's known stages stop one short of the shortened horizon */
    cfg.mpc.horizon = 6;
    cfg.delay.throttle = 6.0 * dt; /* 4 periods after the steering's; the horizon is 4 */
    start_on_circle(oracle_tables());
    readings(&in, 0);
    ddyn_ctrl_step(&ctl, &in, &out);
    assert_int_equal(ctl.mpc.fix_n, 3);
}

static void test_the_filter_predicts_with_the_command_sent_delay_ago(void **state)
{
    /* steering 3 periods, throttle 1: drive the delayed plant with readings, then two periods without
     * any (the estimate is the prediction alone): the throttle and steering states move by the rates
     * sent 1 and 3 periods before, not by the last ones */
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    double before[DDYN_NX];
    const double dt = model->sample_time;
    int k;
    (void)state;
    cfg.delay.steering = 3.0 * dt;
    cfg.delay.throttle = 1.0 * dt;
    start_on_circle(oracle_tables());
    for (k = 0; k < 30; ++k) {
        readings(&in, k);
        ddyn_ctrl_step(&ctl, &in, &out);
        assert_false(out.status & (DDYN_CTRL_SAFE_COMMAND | DDYN_CTRL_MEAS_REJECTED | DDYN_CTRL_EKF_DIVERGED));
        run_delayed_plant(k, 3, 1, &out);
    }
    /* the filter follows the delayed actuators (a filter predicting with the last command would be
     * ~3 periods of steering rate off and fight the steering sensor) */
    assert_true(fabs(out.x_est[7] - plant[7]) < 2e-3);
    memset(&in, 0, sizeof in);
    for (k = 30; k < 32; ++k) {
        memcpy(before, out.x_est, sizeof before);
        ddyn_ctrl_step(&ctl, &in, &out);
        assert_true(fabs(out.x_est[7] - (before[7] + dt * sent_log[k - 1 - 3][1])) < 1e-12);
        assert_true(fabs(out.x_est[6] - (before[6] + dt * sent_log[k - 1 - 1][0])) < 1e-12);
        assert_true(ctl.u_acting[1] == sent_log[k - 1 - 3][1] && ctl.u_acting[0] == sent_log[k - 1 - 1][0]);
        assert_true(sent_log[k - 1 - 3][1] != sent_log[k - 1][1]); /* the test can tell them apart */
        run_delayed_plant(k, 3, 1, &out);
    }
    /* the history row of the guard network holds the input that acted */
    assert_true(ctl.history[DDYN_NET_TAU - 1][DDYN_NET_NFEAT - 1] == sent_log[30 - 3][1]);
}

static void test_the_mpc_plans_from_the_state_after_the_pipe(void **state)
{
    /* steering 3 periods, throttle 1: the MPC's start is the estimate stepped by the filter's model with
     * the commands still in the pipe (steering sent 3, 2, 1 periods before this period's, throttle 1
     * period before, then held), and ddyn_ctrl_predict_pipe between periods is the same stepping */
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    double x[DDYN_NX], xn[DDYN_NX], x_api[DDYN_NX], q[DDYN_CTRL_MAX_DELAY_STEPS];
    const double dt = model->sample_time;
    int k, i;
    (void)state;
    cfg.delay.steering = 3.0 * dt;
    cfg.delay.throttle = 1.0 * dt;
    start_on_circle(oracle_tables());
    for (k = 0; k < 25; ++k) {
        readings(&in, k);
        ddyn_ctrl_step(&ctl, &in, &out);
        run_delayed_plant(k, 3, 1, &out);
    }
    readings(&in, 25);
    assert_int_equal(ctl.thr_hold, 2); /* the throttle held back to the steering's 3 periods */
    memcpy(q, ctl.thr_queue, sizeof q);
    ddyn_ctrl_step(&ctl, &in, &out);
    memcpy(x, out.x_est, sizeof x);
    for (i = 0; i < 3; ++i) {
        /* this period's command is sent_log-to-be: the pipe is the commands of periods 22 .. 24, the
         * throttle's after the one of period 24 the held-back ones (sent in periods 25, 26) */
        double u[DDYN_NU];
        u[1] = sent_log[22 + i][1];
        u[0] = i < 1 ? sent_log[24][0] : q[i - 1];
        assert_int_equal(ddyn_model_step(model, cfg.ekf_disc, x, u, ctl.coeffs, xn, &plant_work), DDYN_OK);
        memcpy(x, xn, sizeof x);
    }
    assert_memory_equal(out.x_mpc0, x, sizeof x);
    assert_true(fabs(out.x_mpc0[0] - out.x_est[0]) + fabs(out.x_mpc0[1] - out.x_est[1]) > 0.03); /* 3 periods ahead */
    /* between periods: the pipe is now the commands of periods 23 .. 25 */
    assert_int_equal(ddyn_ctrl_predict_pipe(&ctl, out.x_est, x_api), DDYN_OK);
    memcpy(x, out.x_est, sizeof x);
    for (i = 0; i < 3; ++i) {
        double u[DDYN_NU];
        u[1] = i == 2 ? out.u[1] : sent_log[23 + i][1];
        u[0] = i < 1 ? out.u[0] : ctl.thr_queue[i - 1];
        assert_int_equal(ddyn_model_step(model, cfg.ekf_disc, x, u, ctl.coeffs, xn, &plant_work), DDYN_OK);
        memcpy(x, xn, sizeof x);
    }
    assert_memory_equal(x_api, x, sizeof x);
    /* without a steering delay nothing is predicted: the MPC starts at the estimate */
    cfg.delay.steering = 0.0;
    cfg.delay.throttle = 0.0;
    start_on_circle(oracle_tables());
    drive_healthy(5);
    readings(&in, 5);
    ddyn_ctrl_step(&ctl, &in, &out);
    assert_memory_equal(out.x_mpc0, out.x_est, sizeof out.x_est);
    assert_int_equal(ddyn_ctrl_predict_pipe(&ctl, out.x_est, x_api), DDYN_OK);
    assert_memory_equal(x_api, out.x_est, sizeof x_api);
}

static void test_the_preparation_plans_from_the_same_delayed_state(void **state)
{
    /* with a steering delay the preparation predicts the next period's MPC start (the filter's step with
     * the command acting, then the pipe): with no reading in between, the next step starts exactly there */
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    double prepared_at[DDYN_NX];
    const double dt = model->sample_time;
    int k;
    (void)state;
    cfg.delay.steering = 2.0 * dt;
    cfg.coeff_source = DDYN_CTRL_SOURCE_FIXED; /* coefficients that do not move between the two */
    memcpy(cfg.c_fixed, C_TRUE, sizeof C_TRUE);
    start_on_circle(oracle_tables());
    for (k = 0; k < 20; ++k) {
        readings(&in, k);
        ddyn_ctrl_step(&ctl, &in, &out);
        run_delayed_plant(k, 2, 0, &out);
    }
    assert_int_equal(ddyn_ctrl_prepare(&ctl), DDYN_OK);
    memcpy(prepared_at, ctl.mpc.prep_x0, sizeof prepared_at);
    memset(&in, 0, sizeof in);
    ddyn_ctrl_step(&ctl, &in, &out);
    assert_memory_equal(out.x_mpc0, prepared_at, sizeof prepared_at);
    assert_false(out.status & (DDYN_CTRL_SAFE_COMMAND | DDYN_CTRL_MPC_FAILED));
}

/* a second controller for the side-by-side tests (large: static) */
static ddyn_ctrl ctl_b;

static void test_a_shorter_throttle_delay_is_held_back_to_the_steerings(void **state)
{
    /* issue 34 (80 ms steering delay left the track): steering 2 periods, throttle none. The controller
     * holds its throttle back 2 periods, so that it is the controller told a throttle delay of 2 periods
     * exactly: with the same readings, the same estimates and steering, and its throttle the other's
     * two periods later (bit for bit). The safe command goes out at once and empties the queue. */
    ddyn_ctrl_output out, out_b;
    ddyn_ctrl_input in;
    static double thr_b[DELAY_PERIODS];
    const double dt = model->sample_time;
    double u_safe[DDYN_NU];
    int k, i;
    (void)state;
    cfg.delay.steering = 2.0 * dt;
    cfg.delay.throttle = 2.0 * dt;
    start_on_circle(oracle_tables());
    memcpy(&ctl_b, &ctl, sizeof ctl_b);
    assert_int_equal(ctl_b.thr_hold, 0);
    cfg.delay.throttle = 0.0;
    start_on_circle(oracle_tables());
    assert_int_equal(ctl.thr_hold, 2);
    for (k = 0; k < 40; ++k) {
        readings(&in, k);
        ddyn_ctrl_step(&ctl, &in, &out);
        ddyn_ctrl_step(&ctl_b, &in, &out_b);
        assert_false(out.status & (DDYN_CTRL_SAFE_COMMAND | DDYN_CTRL_EKF_DIVERGED));
        thr_b[k] = out_b.u[0];
        assert_memory_equal(out.x_est, out_b.x_est, sizeof out.x_est);
        assert_memory_equal(out.x_mpc0, out_b.x_mpc0, sizeof out.x_mpc0);
        assert_true(out.u[1] == out_b.u[1]);
        assert_true(out.u[0] == (k >= 2 ? thr_b[k - 2] : 0.0));
        run_delayed_plant(k, 2, 0, &out); /* the plant: steering 2 periods, throttle at once */
    }
    assert_true(thr_b[37] != thr_b[39]); /* the test can tell them apart */
    /* no readings until the safe command: it goes out at once, the queue becomes holds */
    memset(&in, 0, sizeof in);
    for (i = 0; i < 2 * cfg.max_blind_steps + 2 && !(out.status & DDYN_CTRL_SAFE_COMMAND); ++i) {
        ddyn_ctrl_step(&ctl, &in, &out);
    }
    assert_true(out.status & DDYN_CTRL_SAFE_COMMAND);
    ddyn_ctrl_safe_command(&ctl, out.x_est, u_safe);
    assert_true(out.u[0] == u_safe[0]);
    for (i = 0; i < DDYN_CTRL_MAX_DELAY_STEPS; ++i) {
        assert_true(ctl.thr_queue[i] == 0.0);
    }
}

static void test_a_longer_throttle_delay_is_known_in_the_first_stages(void **state)
{
    /* issue 34 (a told throttle delay made the laps worse): steering none, throttle 3 periods. The
     * throttle still in the pipe (sent 3, 2, 1 periods ago) is the MPC's first 3 stages' throttle
     * (ddyn_mpc_fix_throttle), and the throttle sent is the plan's stage 3, where it acts; the
     * preparation fixes the same; the PID throttle fixes nothing. */
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    double up[DDYN_MPC_NV];
    const double dt = model->sample_time;
    int k, j, checked = 0;
    (void)state;
    cfg.delay.steering = 0.0;
    cfg.delay.throttle = 3.0 * dt;
    start_on_circle(oracle_tables());
    assert_int_equal(ctl.thr_hold, 0);
    for (k = 0; k < 40; ++k) {
        readings(&in, k);
        ddyn_ctrl_step(&ctl, &in, &out);
        assert_false(out.status & (DDYN_CTRL_SAFE_COMMAND | DDYN_CTRL_EKF_DIVERGED));
        assert_int_equal(ctl.mpc.fix_n, 3);
        if (!(out.status & (DDYN_CTRL_PLAN_SHIFTED | DDYN_CTRL_MPC_NOT_CONVERGED))) {
            assert_int_equal(ddyn_mpc_plan_inputs(&ctl.mpc, up), cfg.mpc.horizon);
            for (j = 0; j < 3; ++j) {
                assert_true(up[2 * j] == (k - 3 + j >= 0 ? sent_log[k - 3 + j][0] : 0.0));
            }
            assert_true(out.u[0] == up[2 * 3]);
            assert_true(out.u[1] == up[1]);
            checked += 1;
        }
        run_delayed_plant(k, 0, 3, &out);
    }
    assert_true(checked > 30);
    assert_true(fabs(out.x_est[3] - SPEED) < 0.1); /* it holds the speed */
    /* the preparation: the same known stages for the next period (its pipe: periods 37 .. 39) */
    assert_int_equal(ddyn_ctrl_prepare(&ctl), DDYN_OK);
    for (j = 0; j < 3; ++j) {
        assert_true(ctl.mpc.fix_u[j] == sent_log[37 + j][0]);
    }
    /* the PID throttle: nothing fixed (its held-throttle QP plans the steering alone) */
    cfg.throttle_mode = DDYN_CTRL_THROTTLE_PID;
    start_on_circle(oracle_tables());
    for (k = 0; k < 5; ++k) {
        readings(&in, k);
        ddyn_ctrl_step(&ctl, &in, &out);
        run_delayed_plant(k, 0, 3, &out);
        assert_int_equal(ctl.mpc.fix_n, 0);
    }
}

/* ---- mass offset (ddyn_ctrl_config.mass_offset) ---- */

static void test_the_mass_scaled_coefficients_are_the_heavier_car(void **state)
{
    /* issue 34: the coefficients scaled for a mass (1 + offset) give the rigid body of that mass: dvx and
     * dvy's force parts divided by (1 + offset), domega (Iz unchanged) and the kinematics as before */
    const double x[DDYN_NX] = {1.0, -0.5, 0.3, 2.1, -0.12, 1.4, 0.35, 0.08};
    const double u[DDYN_NU] = {0.5, -0.2};
    const double offsets[3] = {0.2, -0.3, 1.0};
    double c[DDYN_NC], raw[DDYN_NX], heavy[DDYN_NX];
    int i, k;
    (void)state;
    assert_int_equal(ddyn_model_derivatives(model, x, u, C_TRUE, raw, &plant_work), DDYN_OK);
    for (k = 0; k < 3; ++k) {
        const double m = 1.0 + offsets[k];
        memcpy(c, C_TRUE, sizeof c);
        ddyn_ctrl_mass_scale(c, offsets[k]);
        assert_int_equal(ddyn_model_derivatives(model, x, u, c, heavy, &plant_work), DDYN_OK);
        assert_true(fabs((heavy[3] - x[4] * x[5]) - (raw[3] - x[4] * x[5]) / m) < 1e-12);
        assert_true(fabs((heavy[4] + x[3] * x[5]) - (raw[4] + x[3] * x[5]) / m) < 1e-12);
        assert_true(fabs(heavy[5] - raw[5]) < 1e-12 * fabs(raw[5]) + 1e-15);
        for (i = 0; i < 3; ++i) {
            assert_true(heavy[i] == raw[i]); /* positions and heading: kinematics */
        }
        /* the test is not blind: every force part is there (here -0.07, 5.0 m/s^2 and 30.7 rad/s^2) */
        assert_true(fabs(raw[3] - x[4] * x[5]) > 0.01 && fabs(raw[4] + x[3] * x[5]) > 1.0 && fabs(raw[5]) > 1.0);
    }
    memcpy(c, C_TRUE, sizeof c);
    ddyn_ctrl_mass_scale(c, 0.0);
    assert_memory_equal(c, C_TRUE, sizeof c); /* none: bit-identical */
}

static void test_the_controller_uses_the_mass_scaled_coefficients_and_refuses_a_bad_offset(void **state)
{
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    double want[DDYN_NC];
    int k;
    (void)state;
    /* the fixed set, scaled from the start and every period */
    cfg.mass_offset = 0.25;
    cfg.coeff_source = DDYN_CTRL_SOURCE_FIXED;
    memcpy(cfg.c_fixed, C_TRUE, sizeof C_TRUE);
    memcpy(want, C_TRUE, sizeof want);
    ddyn_ctrl_mass_scale(want, 0.25);
    start_on_circle(oracle_tables());
    assert_memory_equal(ctl.coeffs, want, sizeof want);
    for (k = 0; k < 3; ++k) {
        readings(&in, k);
        ddyn_ctrl_step(&ctl, &in, &out);
        assert_memory_equal(out.coeffs, want, sizeof want);
        /* the heavier car's line: the reference speeds times 1 / sqrt(1.25) */
        assert_true(fabs(ctl.mpc.track.speed_scale - 1.0 / sqrt(1.25)) < 1e-15);
    }
    /* a lighter car keeps the line's speeds */
    cfg.mass_offset = -0.2;
    start_on_circle(oracle_tables());
    readings(&in, 0);
    ddyn_ctrl_step(&ctl, &in, &out);
    assert_true(ctl.mpc.track.speed_scale == 1.0);
    cfg.mass_offset = 0.25;
    /* the network's: scaled once, its last good set kept as it gave it */
    cfg.coeff_source = DDYN_CTRL_SOURCE_NETWORK;
    start_on_circle(&ddyn_net_weights);
    for (k = 0; k < 12; ++k) {
        readings(&in, k);
        ddyn_ctrl_step(&ctl, &in, &out);
    }
    assert_int_equal(ctl.last_good_age, 0);
    memcpy(want, ctl.last_good, sizeof want);
    ddyn_ctrl_mass_scale(want, 0.25);
    assert_memory_equal(out.coeffs, want, sizeof want);
    assert_true(out.coeffs[16] < ctl.last_good[16]);
    /* out of range (also NaN): refused */
    cfg.mass_offset = DDYN_CTRL_MASS_OFFSET_MIN - 1e-9;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_ERR_ARGUMENT);
    cfg.mass_offset = 1.0 + 1e-9;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_ERR_ARGUMENT);
    cfg.mass_offset = NAN;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_ERR_ARGUMENT);
    cfg.mass_offset = DDYN_CTRL_MASS_OFFSET_MAX;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_OK);
    cfg.mass_offset = DDYN_CTRL_MASS_OFFSET_MIN;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_OK);
}

/* ---- downforce (ddyn_ctrl_config.downforce) ---- */

static void test_the_controller_evaluates_its_model_at_the_downforce_of_its_speed(void **state)
{
    /* issue 34: with a known downforce the MPC is given it, the filter predicts with the coefficients of its
     * own speed (D_f, D_r times 1 + k vx^2), the coefficients it reports stay the set it was given */
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    double expect[DDYN_NX], plain[DDYN_NX], c_at[DDYN_NC];
    const double k_df = 0.3;
    int k, i;
    (void)state;
    cfg.coeff_source = DDYN_CTRL_SOURCE_FIXED;
    memcpy(cfg.c_fixed, C_TRUE, sizeof C_TRUE);
    cfg.downforce = k_df;
    start_on_circle(oracle_tables());
    assert_true(ctl.mpc.downforce == k_df);
    for (k = 0; k < 5; ++k) {
        readings(&in, k);
        ddyn_ctrl_step(&ctl, &in, &out);
        assert_false(out.status & DDYN_CTRL_SAFE_COMMAND);
        assert_memory_equal(out.coeffs, C_TRUE, sizeof C_TRUE); /* reported as given */
        /* the preparation's step (the filter's model step): the coefficients of the filter's speed */
        assert_int_equal(ddyn_ctrl_prepare(&ctl), DDYN_OK);
        ddyn_model_downforce(C_TRUE, k_df, ctl.ekf.x[3], c_at);
        assert_int_equal(ddyn_model_step(model, cfg.ekf_disc, ctl.ekf.x, ctl.u_acting, c_at, expect, &plant_work),
                         DDYN_OK);
        assert_int_equal(ddyn_model_step(model, cfg.ekf_disc, ctl.ekf.x, ctl.u_acting, C_TRUE, plain, &plant_work),
                         DDYN_OK);
        for (i = 0; i < DDYN_NX; ++i) {
            assert_true(fabs(ctl.mpc.prep_x0[i] - expect[i]) < 1e-14 * (1.0 + fabs(expect[i])));
        }
        assert_true(fabs(plain[5] - expect[5]) > 1e-6); /* not blind: the extra grip turns the car harder */
        run(&in, &out);
    }
    /* out of range (also NaN): refused */
    cfg.downforce = -1e-9;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_ERR_ARGUMENT);
    cfg.downforce = DDYN_MODEL_DOWNFORCE_MAX + 1e-9;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_ERR_ARGUMENT);
    cfg.downforce = NAN;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_ERR_ARGUMENT);
    cfg.downforce = DDYN_MODEL_DOWNFORCE_MAX;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_OK);
}

/* ---- steering lag (ddyn_ctrl_lag_config) ---- */

static void test_the_lag_step_is_the_exact_discretisation(void **state)
{
    /* a set-point held over a period: the closed form of d(delta)/dt = (cmd - delta) / tau is
     * delta(t) = cmd + (delta0 - cmd) e^{-t/tau}; ddyn_ctrl_lag_step over n periods of dt equals it at
     * t = n dt (no Euler error), and ddyn_ctrl_lag_invert is its inverse in cmd */
    const double dt = 0.02, taus[3] = {0.05, 0.1, 0.013};
    int i, n;
    (void)state;
    for (i = 0; i < 3; ++i) {
        const double tau = taus[i], decay = ddyn_ctrl_lag_decay(tau, dt);
        double delta = -0.2, cmd = 0.3;
        assert_true(fabs(decay - exp(-dt / tau)) <= 1e-15);
        for (n = 1; n <= 40; ++n) {
            const double closed = cmd + (-0.2 - cmd) * exp(-(double)n * dt / tau);
            delta = ddyn_ctrl_lag_step(delta, cmd, decay);
            assert_true(fabs(delta - closed) <= 1e-14);
        }
        /* piecewise constant set-points: the closed form period by period (a staircase) */
        delta = 0.1;
        for (n = 0; n < 10; ++n) {
            const double c = 0.03 * (double)n - 0.1;
            const double closed = c + (delta - c) * exp(-dt / tau);
            delta = ddyn_ctrl_lag_step(delta, c, decay);
            assert_true(fabs(delta - closed) <= 1e-15);
        }
        /* the inversion: the set-point that takes delta to target in one period */
        for (n = 0; n < 5; ++n) {
            const double d0 = -0.1 + 0.05 * (double)n, target = 0.12 - 0.07 * (double)n;
            const double c = ddyn_ctrl_lag_invert(d0, target, decay);
            assert_true(fabs(ddyn_ctrl_lag_step(d0, c, decay) - target) <= 1e-14);
        }
    }
    /* tau = 0: no lag (the set-point acts at once); bad tau or dt: NaN */
    assert_true(ddyn_ctrl_lag_decay(0.0, dt) == 0.0);
    assert_true(ddyn_ctrl_lag_step(0.4, -0.1, 0.0) == -0.1);
    assert_true(fabs(ddyn_ctrl_lag_invert(0.4, -0.1, 0.0) + 0.1) <= 1e-15);
    assert_true(isnan(ddyn_ctrl_lag_decay(-1e-9, dt)));
    assert_true(isnan(ddyn_ctrl_lag_decay(NAN, dt)));
    assert_true(isnan(ddyn_ctrl_lag_decay(INFINITY, dt)));
    assert_true(isnan(ddyn_ctrl_lag_decay(0.05, 0.0)));
}

static void test_a_bad_lag_is_refused_at_init(void **state)
{
    (void)state;
    cfg.lag.steering = -0.01;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_ERR_ARGUMENT);
    cfg.lag.steering = NAN;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_ERR_ARGUMENT);
    cfg.lag.steering = INFINITY;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_ERR_ARGUMENT);
    cfg.lag.steering = 1e300; /* e^{-dt/tau} == 1 in doubles: the inversion would divide by 0 */
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_ERR_ARGUMENT);
    cfg.lag.steering = 0.1;
    assert_int_equal(ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, plant), DDYN_OK);
    assert_true(fabs(ctl.lag_decay - exp(-model->sample_time / 0.1)) <= 1e-15);
    assert_true(ctl.lag_act == plant[7] && ctl.lag_cmd == plant[7]);
}

/* the lagged (and delayed) plant: the set-point integrates the rates sent (within the steering bounds), the
 * acting angle follows the set-point sent `ds` periods ago through the exact lag; the model runs the
 * acting rate */
static double lag_setpoint[DELAY_PERIODS + 1], lag_acting;

static void run_lagged_plant(int period, int ds, double decay, const ddyn_ctrl_output *out)
{
    const double dt = model->sample_time, lo = cfg.mpc.state_lo[1], hi = cfg.mpc.state_hi[1];
    double u[DDYN_NU], next[DDYN_NX], cmd, a_next;
    memcpy(sent_log[period], out->u, sizeof sent_log[period]);
    lag_setpoint[period + 1] = lag_setpoint[period] + dt * out->u[1];
    lag_setpoint[period + 1] = lag_setpoint[period + 1] < lo ? lo : (lag_setpoint[period + 1] > hi ? hi : lag_setpoint[period + 1]);
    cmd = lag_setpoint[period + 1 - ds >= 0 ? period + 1 - ds : 0];
    a_next = cmd + (lag_acting - cmd) * decay;
    u[0] = sent_log[period][0];
    u[1] = (a_next - lag_acting) / dt;
    lag_acting = a_next;
    assert_int_equal(ddyn_model_step(model, DDYN_DISC_RK4, plant, u, plant_c, next, &plant_work), DDYN_OK);
    memcpy(plant, next, sizeof next);
}

static void test_the_filter_and_history_use_the_acting_steering_of_the_lag(void **state)
{
    /* lag 60 ms and a steering delay of 2 periods: the controller's acting angle is the lagged plant's,
     * exactly; the filter predicts with its rate (no readings: the estimate moves by it) and the
     * history row holds it */
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    double before[DDYN_NX], a_prev;
    const double dt = model->sample_time, tau = 0.06, decay = exp(-dt / tau);
    int k;
    (void)state;
    cfg.lag.steering = tau;
    cfg.delay.steering = 2.0 * dt;
    start_on_circle(oracle_tables());
    lag_setpoint[0] = lag_acting = plant[7];
    for (k = 0; k < 30; ++k) {
        readings(&in, k);
        ddyn_ctrl_step(&ctl, &in, &out);
        assert_false(out.status & (DDYN_CTRL_SAFE_COMMAND | DDYN_CTRL_EKF_DIVERGED));
        run_lagged_plant(k, 2, decay, &out);
    }
    assert_true(fabs(out.x_est[7] - plant[7]) < 2e-3);
    memset(&in, 0, sizeof in);
    for (k = 30; k < 33; ++k) {
        memcpy(before, out.x_est, sizeof before);
        a_prev = ctl.lag_act;
        ddyn_ctrl_step(&ctl, &in, &out);
        /* the lag estimate is the plant's acting angle at this period's start */
        assert_true(fabs(ctl.lag_act - lag_acting) <= 1e-14);
        assert_true(fabs(ctl.u_acting[1] - (ctl.lag_act - a_prev) / dt) <= 1e-12);
        assert_true(fabs(out.x_est[7] - (before[7] + dt * ctl.u_acting[1])) < 1e-12);
        assert_true(fabs(ctl.u_acting[1] - sent_log[k - 1 - 2][1]) > 1e-6); /* not the rate sent */
        assert_true(ctl.history[DDYN_NET_TAU - 1][DDYN_NET_NFEAT - 1] == ctl.u_acting[1]);
        run_lagged_plant(k, 2, decay, &out);
    }
}

static void test_the_first_command_inverts_the_lag(void **state)
{
    /* no delay, lag 100 ms: the MPC plans the acting angle; the rate sent is the one whose set-point takes
     * the acting angle (after this period) to the MPC's first planned angle, within the bounds; the
     * preparation and the step plan from the same lagged state */
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    const double dt = model->sample_time, tau = 0.1, decay = exp(-dt / tau);
    double u_mpc[DDYN_MPC_NV], prepared_at[DDYN_NX];
    int k, inverted = 0, clipped = 0;
    (void)state;
    cfg.lag.steering = tau;
    cfg.coeff_source = DDYN_CTRL_SOURCE_FIXED;
    memcpy(cfg.c_fixed, C_TRUE, sizeof C_TRUE);
    start_on_circle(oracle_tables());
    lag_setpoint[0] = lag_acting = plant[7];
    for (k = 0; k < 40; ++k) {
        readings(&in, k);
        ddyn_ctrl_step(&ctl, &in, &out);
        assert_false(out.status & (DDYN_CTRL_SAFE_COMMAND | DDYN_CTRL_MPC_FAILED | DDYN_CTRL_PLAN_SHIFTED));
        /* the controller's acting angle is the lagged plant's (the same discretisation) */
        assert_true(fabs(ctl.lag_act - lag_acting) <= 1e-14 && fabs(ctl.lag_cmd - lag_setpoint[k]) <= 1e-14);
        assert_int_equal(ddyn_mpc_plan_inputs(&ctl.mpc, u_mpc), cfg.mpc.horizon);
        {
            const double want = ctl.lag_act + dt * u_mpc[1];
            const double set = ctl.lag_cmd + dt * out.u[1];
            const double reached = ddyn_ctrl_lag_step(ctl.lag_act, set, decay);
            const double lo = cfg.mpc.rate_lo[1], hi = cfg.mpc.rate_hi[1];
            if (out.u[1] > lo + 1e-12 && out.u[1] < hi - 1e-12 && set > cfg.mpc.state_lo[1] + 1e-12 &&
                set < cfg.mpc.state_hi[1] - 1e-12) {
                assert_true(fabs(reached - want) <= 1e-12); /* exact where not clipped */
                inverted += fabs(out.u[1] - u_mpc[1]) > 1e-6;
            } else {
                clipped += 1;
            }
        }
        run_lagged_plant(k, 0, decay, &out);
        if (k == 20) {
            /* the preparation's start: the filter's step with the acting rate, the lag's next state; with
             * no reading in between, the next step starts exactly there */
            assert_int_equal(ddyn_ctrl_prepare(&ctl), DDYN_OK);
            memcpy(prepared_at, ctl.mpc.prep_x0, sizeof prepared_at);
            memset(&in, 0, sizeof in);
            ddyn_ctrl_step(&ctl, &in, &out);
            assert_memory_equal(out.x_mpc0, prepared_at, sizeof prepared_at);
            assert_true(fabs(ctl.lag_act - lag_acting) <= 1e-14);
            k += 1;
            run_lagged_plant(k, 0, decay, &out);
        }
    }
    assert_true(inverted > 10);
    /* the lagged car stays on its circle (the plant's steering is the lag's) */
    assert_true(fabs(plant[7] - lag_acting) < 1e-9);
    (void)clipped;
}

static void test_no_lag_is_the_controller_of_before(void **state)
{
    /* lag 0 (the default): the rate acting is the rate sent and the lag's state never moves (the commands
     * are bit-identical to before: the Cortex-M7 pass 1 compares them with the host's recording) */
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    double sent = 0.0;
    int k;
    (void)state;
    assert_true(cfg.lag.steering == 0.0);
    assert_true(ctl.lag_decay == 0.0);
    for (k = 0; k < 20; ++k) {
        readings(&in, k);
        ddyn_ctrl_step(&ctl, &in, &out);
        assert_true(ctl.u_acting[1] == sent || k == 0); /* the rate sent the period before */
        sent = out.u[1];
        assert_true(ctl.lag_act == plant[7] || k > 0);
        run_delayed_plant(k, 0, 0, &out);
    }
    assert_true(ctl.lag_act_next == ctl.lag_act);
}

static void test_the_filter_and_the_preparation_predict_with_the_bank(void **state)
{
    /* control.bank (issue 34): with a profile the filter predicts with the bank at its position and the
     * preparation's step adds the same lateral gravity (ddyn_model_add_bank); NULL: a flat road again */
    static double bank[TRACK_N];
    static ddyn_ctrl other;
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    double expect[DDYN_NX];
    int k, i;
    (void)state;
    for (i = 0; i < TRACK_N; ++i) bank[i] = 0.2;
    memset(&other, 0, sizeof other);
    assert_int_equal(ddyn_ctrl_set_bank(&other, bank), DDYN_ERR_ARGUMENT); /* not initialised */
    assert_int_equal(ddyn_ctrl_set_bank(&ctl, bank), DDYN_OK);
    for (k = 0; k < 5; ++k) {
        readings(&in, k);
        ddyn_ctrl_step(&ctl, &in, &out);
        assert_true(ctl.ekf.bank == 0.2); /* the table's bank where the predicted period starts */
        assert_false(out.status & DDYN_CTRL_SAFE_COMMAND);
        assert_int_equal(ddyn_ctrl_prepare(&ctl), DDYN_OK);
        assert_int_equal(ddyn_model_step(model, cfg.ekf_disc, ctl.ekf.x, ctl.u_acting, ctl.coeffs, expect, &plant_work),
                         DDYN_OK);
        ddyn_model_add_bank(0.2, model->sample_time, ctl.ekf.x, expect);
        for (i = 0; i < DDYN_NX; ++i) {
            assert_true(fabs(ctl.mpc.prep_x0[i] - expect[i]) < 1e-14 * (1.0 + fabs(expect[i])));
        }
        for (i = 0; i < ctl.mpc.cfg.horizon; ++i) {
            assert_true(fabs(ctl.mpc.stage_bank[i] - 0.2) < 1e-15); /* every stage predicts on the bank */
        }
        run(&in, &out);
    }
    assert_int_equal(ddyn_ctrl_set_bank(&ctl, NULL), DDYN_OK);
    readings(&in, 5);
    ddyn_ctrl_step(&ctl, &in, &out);
    assert_true(ctl.ekf.bank == 0.0);
}

static void test_the_filter_and_the_preparation_predict_with_the_grade(void **state)
{
    /* control.grade (issue 34): with a profile (here beside a bank) the filter predicts with the grade at its
     * position and the preparation's step adds the same longitudinal gravity (ddyn_model_add_grade) */
    static double grade[TRACK_N], bank[TRACK_N];
    static ddyn_ctrl other;
    ddyn_ctrl_output out;
    ddyn_ctrl_input in;
    double expect[DDYN_NX];
    int k, i;
    (void)state;
    for (i = 0; i < TRACK_N; ++i) {
        grade[i] = -0.08;
        bank[i] = 0.1;
    }
    memset(&other, 0, sizeof other);
    assert_int_equal(ddyn_ctrl_set_grade(&other, grade), DDYN_ERR_ARGUMENT); /* not initialised */
    assert_int_equal(ddyn_ctrl_set_grade(&ctl, grade), DDYN_OK);
    assert_int_equal(ddyn_ctrl_set_bank(&ctl, bank), DDYN_OK);
    for (k = 0; k < 5; ++k) {
        readings(&in, k);
        ddyn_ctrl_step(&ctl, &in, &out);
        assert_true(ctl.ekf.grade == -0.08 && ctl.ekf.bank == 0.1); /* where the predicted period starts */
        assert_false(out.status & DDYN_CTRL_SAFE_COMMAND);
        assert_int_equal(ddyn_ctrl_prepare(&ctl), DDYN_OK);
        assert_int_equal(ddyn_model_step(model, cfg.ekf_disc, ctl.ekf.x, ctl.u_acting, ctl.coeffs, expect, &plant_work),
                         DDYN_OK);
        ddyn_model_add_bank(0.1, model->sample_time, ctl.ekf.x, expect);
        ddyn_model_add_grade(-0.08, model->sample_time, ctl.ekf.x, expect);
        for (i = 0; i < DDYN_NX; ++i) {
            assert_true(fabs(ctl.mpc.prep_x0[i] - expect[i]) < 1e-14 * (1.0 + fabs(expect[i])));
        }
        for (i = 0; i < ctl.mpc.cfg.horizon; ++i) {
            assert_true(fabs(ctl.mpc.stage_grade[i] + 0.08) < 1e-15); /* every stage predicts on the grade */
        }
        run(&in, &out);
    }
    assert_int_equal(ddyn_ctrl_set_grade(&ctl, NULL), DDYN_OK);
    readings(&in, 5);
    ddyn_ctrl_step(&ctl, &in, &out);
    assert_true(ctl.ekf.grade == 0.0 && ctl.ekf.bank == 0.1);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test_setup(test_unusable_network_coefficients_fall_back_to_nominal, setup),
        cmocka_unit_test_setup(test_prepared_iteration_drives_like_the_full_one, setup),
        cmocka_unit_test_setup(test_a_shorter_throttle_delay_is_held_back_to_the_steerings, setup),
        cmocka_unit_test_setup(test_a_longer_throttle_delay_is_known_in_the_first_stages, setup),
        cmocka_unit_test_setup(test_indefinite_covariance_restarts_the_filter, setup),
        cmocka_unit_test_setup(test_init_names_what_is_wrong_with_the_network, setup),
        cmocka_unit_test_setup(test_every_status_has_its_own_name, setup),
        cmocka_unit_test_setup(test_bad_arguments_and_configurations, setup),
        cmocka_unit_test_setup(test_status_bits_have_distinct_names, setup),
        cmocka_unit_test_setup(test_safe_command_brakes_then_holds, setup),
        cmocka_unit_test_setup(test_history_rows_are_the_training_rows, setup),
        cmocka_unit_test_setup(test_nonfinite_readings_rejected_counted_then_sensor_fault, setup),
        cmocka_unit_test_setup(test_outlier_readings_are_gated_then_the_filter_restarts, setup),
        cmocka_unit_test_setup(test_no_readings_for_too_long_is_safe, setup),
        cmocka_unit_test_setup(test_out_of_range_history_falls_back_last_good_then_nominal, setup),
        cmocka_unit_test_setup(test_nonfinite_network_output_falls_back_to_nominal, setup),
        cmocka_unit_test_setup(test_covariance_blowup_resets_filter_and_is_safe, setup),
        cmocka_unit_test_setup(test_mpc_without_track_is_safe, setup),
        cmocka_unit_test_setup(test_healthy_closed_loop_follows_the_track, setup),
        cmocka_unit_test_setup(test_recovery_after_a_sensor_fault, setup),
        cmocka_unit_test_setup(test_filter_reacquires_a_car_that_moved_beyond_the_gate, setup),
        cmocka_unit_test_setup(test_filter_restarts_on_the_readings_after_a_blind_spell, setup),
        cmocka_unit_test_setup(test_qp_not_converged_shifts_the_plan_then_safe, setup),
        cmocka_unit_test_setup(test_fixed_coefficients_bypass_the_network, setup),
        cmocka_unit_test_setup(test_pid_throttle_follows_the_law_and_the_plan_holds_it, setup),
        cmocka_unit_test_setup(test_pid_closed_loop_reaches_and_holds_the_speed, setup),
        cmocka_unit_test_setup(test_pid_anti_windup, setup),
        cmocka_unit_test_setup(test_degraded_config_is_checked, setup),
        cmocka_unit_test_setup(test_bus_faults_enter_degraded_mode_and_recovery_has_hysteresis, setup),
        cmocka_unit_test_setup(test_old_readings_and_latency_mark_the_bus_degraded, setup),
        cmocka_unit_test_setup(test_aged_readings_are_moved_to_the_period_time, setup),
        cmocka_unit_test_setup(test_the_plan_starts_after_the_latency, setup),
        cmocka_unit_test_setup(test_a_command_not_sent_is_predicted_held, setup),
        cmocka_unit_test_setup(test_delay_line_returns_the_command_sent_n_periods_ago_and_wraps, setup),
        cmocka_unit_test_setup(test_delay_above_the_compiled_maximum_is_refused_at_init, setup),
        cmocka_unit_test_setup(test_a_steering_delay_shortens_the_horizon_by_its_periods, setup),
        cmocka_unit_test_setup(test_the_filter_predicts_with_the_command_sent_delay_ago, setup),
        cmocka_unit_test_setup(test_the_mass_scaled_coefficients_are_the_heavier_car, setup),
        cmocka_unit_test_setup(test_the_controller_uses_the_mass_scaled_coefficients_and_refuses_a_bad_offset, setup),
        cmocka_unit_test_setup(test_the_controller_evaluates_its_model_at_the_downforce_of_its_speed, setup),
        cmocka_unit_test_setup(test_the_lag_step_is_the_exact_discretisation, setup),
        cmocka_unit_test_setup(test_a_bad_lag_is_refused_at_init, setup),
        cmocka_unit_test_setup(test_the_filter_and_history_use_the_acting_steering_of_the_lag, setup),
        cmocka_unit_test_setup(test_the_first_command_inverts_the_lag, setup),
        cmocka_unit_test_setup(test_no_lag_is_the_controller_of_before, setup),
        cmocka_unit_test_setup(test_the_mpc_plans_from_the_state_after_the_pipe, setup),
        cmocka_unit_test_setup(test_the_preparation_plans_from_the_same_delayed_state, setup),
        cmocka_unit_test_setup(test_the_filter_and_the_preparation_predict_with_the_bank, setup),
        cmocka_unit_test_setup(test_the_filter_and_the_preparation_predict_with_the_grade, setup),
    };
    return cmocka_run_group_tests_name("controller", tests, NULL, NULL);
}
