/*
 * MPC contract (c_src/src/mpc.c, mpc_qp.c): configuration from the vehicle file, refusals with a
 * defined zero command, the QP solver against closed-form answers (box clipping, exact penalty),
 * the iteration cap's status and finite command, the generated prediction step's Jacobians, and a
 * short closed loop on a circular track that must stay inside it. The lap on ethzMobil against the
 * IPOPT reference is tests/python/test_mpc.py.
 */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include <cmocka.h>

#include "ddyn/mpc.h"
#include "ddyn/mpc_qp.h"
#include "ddyn_models.h"
#include "ddyn_test_vehicles.h"
#include "ddyn_mpc_limits.h"

#define PI 3.14159265358979323846
#define RING 200
#define RADIUS 1.0

static ddyn_mpc mpc;
static ddyn_mpc_qp qp;
/* the ORCA car's true coefficients, from its vehicle file (generated: ddyn_test_vehicles.h) */
static const double C[DDYN_NC] = DDYN_TEST_ORCA_1_43_TRUE_COEFFS;

/* a counter-clockwise circle of radius 1 m, 1.2 m/s reference, 0.15 m of room either side */
static void ring_mpc(int qp_iterations)
{
    static double x[RING], y[RING], v[RING], wl[RING], wr[RING];
    ddyn_mpc_config cfg;
    int i;
    for (i = 0; i < RING; ++i) {
        double a = 2.0 * PI * i / RING;
        x[i] = RADIUS * cos(a);
        y[i] = RADIUS * sin(a);
        v[i] = 1.2;
        wl[i] = 0.15;
        wr[i] = 0.15;
    }
    assert_int_equal(ddyn_mpc_default_config(&ddyn_model_orca_1_43, &cfg), DDYN_OK);
    cfg.qp_max_iterations = qp_iterations;
    assert_int_equal(ddyn_mpc_init(&mpc, &ddyn_model_orca_1_43, &cfg), DDYN_OK);
    assert_int_equal(ddyn_mpc_set_track(&mpc, RING, x, y, v, wl, wr), DDYN_OK);
    assert_int_equal(ddyn_mpc_set_coefficients(&mpc, C), DDYN_OK);
}

static void ring_start(double x0[DDYN_NX])
{
    const double s[DDYN_NX] = {RADIUS, 0.0, PI / 2.0, 1.0, 0.0, 1.0, 0.2, 0.05};
    memcpy(x0, s, sizeof s);
}

/* the ring again with the table speed v0 + dv * i at point i (0.15 m of room either side) */
static void ring_speeds(double v0, double dv)
{
    static double x[RING], y[RING], v[RING], wl[RING], wr[RING];
    int i;
    for (i = 0; i < RING; ++i) {
        double a = 2.0 * PI * i / RING;
        x[i] = RADIUS * cos(a);
        y[i] = RADIUS * sin(a);
        v[i] = v0 + dv * i;
        wl[i] = wr[i] = 0.15;
    }
    assert_int_equal(ddyn_mpc_set_track(&mpc, RING, x, y, v, wl, wr), DDYN_OK);
}

static void test_reference_speed_reads_ahead_along_the_line(void **state)
{
    /* a ring whose table speed grows with the angle: the speed `ahead` metres past the car's
     * projection is the table's there (the throttle PID's preview) */
    const double seg = 2.0 * RADIUS * sin(PI / RING); /* chord length between table points */
    double x0[DDYN_NX], speed;
    (void)state;
    ring_mpc(30);
    ring_speeds(1.0, 0.01);
    ring_start(x0); /* at table point 0 */
    assert_int_equal(ddyn_mpc_reference_speed(&mpc, x0, 0.0, &speed), DDYN_OK);
    assert_true(fabs(speed - 1.0) < 1e-9);
    assert_int_equal(ddyn_mpc_reference_speed(&mpc, x0, 10.5 * seg, &speed), DDYN_OK);
    assert_true(fabs(speed - 1.105) < 1e-9); /* half-way between points 10 and 11 */
    /* one lap and two laps further on: the same place, the same speed (it used to stop after one lap
     * of segments at point 0 with the leftover distance dropped) */
    assert_int_equal(ddyn_mpc_reference_speed(&mpc, x0, mpc.track.length + 10.5 * seg, &speed), DDYN_OK);
    assert_true(fabs(speed - 1.105) < 1e-9);
    assert_int_equal(ddyn_mpc_reference_speed(&mpc, x0, 2.0 * mpc.track.length + 10.5 * seg, &speed), DDYN_OK);
    assert_true(fabs(speed - 1.105) < 1e-9);
    assert_int_equal(ddyn_mpc_reference_speed(&mpc, x0, NAN, &speed), DDYN_ERR_NONFINITE_INPUT);
}

/* arc length (m) on the ring from the car's start (angle 0) to stage k's cost point */
static double ring_arc_to_stage(int k)
{
    double a = atan2(mpc.ref[k * 8 + 1], mpc.ref[k * 8]);
    return RADIUS * (a < 0.0 ? a + 2.0 * PI : a);
}

static void test_cost_points_run_no_faster_than_the_car_can_reach(void **state)
{
    /* a ring whose line runs at 3 m/s: a car there at its line's speed has its cost points 3 dt apart; a car
     * near standstill has them no further ahead than it can reach at full throttle (the model's dvx/dt at
     * its speed), not around the ring at the line's speed (a flying line's first lap from standstill) */
    const int h = 20;
    double x0[DDYN_NX], xs[DDYN_NX] = {0.0}, u0[DDYN_NU] = {0.0}, xdot[DDYN_NX], reach = 0.0, dt, accel;
    int k;
    (void)state;
    ring_mpc(30);
    ring_speeds(3.0, 0.0);
    assert_int_equal(mpc.cfg.horizon, h);
    dt = mpc.model->sample_time;
    ring_start(x0);
    x0[3] = 3.0; /* at the line's speed: the line alone sets the cost points */
    assert_int_equal(ddyn_mpc_prepare(&mpc, x0), DDYN_OK);
    assert_true(fabs(ring_arc_to_stage(h) - 3.0 * h * dt) < 1e-3 * 3.0 * h * dt);
    x0[3] = 0.1; /* near standstill */
    ddyn_mpc_reset(&mpc);
    assert_int_equal(ddyn_mpc_prepare(&mpc, x0), DDYN_OK);
    xs[3] = 0.1;
    xs[6] = mpc.cfg.state_hi[0];
    assert_int_equal(ddyn_model_derivatives(&ddyn_model_orca_1_43, xs, u0, C, xdot, &mpc.model_work), DDYN_OK);
    accel = xdot[3];
    assert_true(accel > 1.0); /* the car accelerates: the bound is the reachable distance, not a stop */
    for (k = 0; k < h; ++k) {
        reach += fmin(3.0, 0.1 + accel * (k + 1) * dt) * dt;
    }
    assert_true(reach < 0.8 * 3.0 * h * dt);
    assert_true(fabs(ring_arc_to_stage(h) - reach) < 1e-3 * reach);
    {
        /* on a grade the reachable distance takes gravity at x0's position: downhill further, uphill less far
         * (the level road's rate held the cost points behind a car descending a hill) */
        static double grade[RING];
        const double grades[2] = {-0.1, 0.05};
        int j, i;
        for (j = 0; j < 2; ++j) {
            double a = accel + ddyn_model_grade_accel(grades[j]), r = 0.0;
            for (i = 0; i < RING; ++i) grade[i] = grades[j];
            assert_int_equal(ddyn_mpc_set_grade(&mpc, grade), DDYN_OK);
            assert_int_equal(ddyn_mpc_prepare(&mpc, x0), DDYN_OK);
            for (k = 0; k < h; ++k) {
                r += fmin(3.0, 0.1 + a * (k + 1) * dt) * dt;
            }
            assert_true(j == 0 ? r > 1.1 * reach : r < 0.95 * reach); /* not blind: the grade moves it */
            assert_true(fabs(ring_arc_to_stage(h) - r) < 1e-3 * r);
        }
        /* a hill steeper than the car can climb at its speed: the cost points stay at its speed, not run
         * ahead at the line's (4.5 m/s here, the car at 3.4 m/s: the level road's 0.98 m/s^2 at full throttle
         * against 1.9 m/s^2 of gravity) */
        for (i = 0; i < RING; ++i) grade[i] = 0.2;
        ring_speeds(4.5, 0.0);
        assert_int_equal(ddyn_mpc_set_grade(&mpc, grade), DDYN_OK);
        x0[3] = 3.4;
        assert_int_equal(ddyn_mpc_prepare(&mpc, x0), DDYN_OK);
        assert_true(fabs(ring_arc_to_stage(h) - 3.4 * h * dt) < 1e-3 * 3.4 * h * dt);
        assert_int_equal(ddyn_mpc_set_grade(&mpc, NULL), DDYN_OK);
        assert_int_equal(ddyn_mpc_prepare(&mpc, x0), DDYN_OK); /* level: it can reach more than 3.4 m/s */
        assert_true(ring_arc_to_stage(h) > 1.05 * 3.4 * h * dt);
    }
}

static void test_prepare_then_feedback_is_the_real_time_iteration(void **state)
{
    /* The split (acados' preparation and feedback phases): prepared at the prediction of the next
     * state, moved to the measured one to first order, the command is close to a full solve at the
     * measured state, much closer than ignoring the measurement, and the car stays on the ring. */
    static ddyn_model_work work;
    static ddyn_mpc before, stale;
    double x[DDYN_NX], xp[DDYN_NX], u[DDYN_NU], u_ref[DDYN_NU], u_stale[DDYN_NU], u_full[DDYN_NU];
    double err_fb = 0.0, err_stale = 0.0;
    int k, j;
    (void)state;
    ring_mpc(30);
    ring_start(x);
    assert_int_equal(ddyn_mpc_feedback(&mpc, x, u, NULL), DDYN_ERR_NOT_READY); /* nothing prepared */
    assert_int_equal(ddyn_mpc_solve(&mpc, x, u, NULL), DDYN_OK);
    /* at the state it was prepared at, feedback is exactly the full solve */
    before = mpc;
    assert_int_equal(ddyn_mpc_prepare(&mpc, x), DDYN_OK);
    assert_int_equal(ddyn_mpc_feedback(&mpc, x, u, NULL), DDYN_OK);
    assert_int_equal(ddyn_mpc_solve(&before, x, u_full, NULL), DDYN_OK);
    assert_memory_equal(u, u_full, sizeof u);
    assert_int_equal(ddyn_mpc_feedback(&mpc, x, u, NULL), DDYN_ERR_NOT_READY); /* one feedback per preparation */
    assert_int_equal(ddyn_mpc_solve(&mpc, x, u, NULL), DDYN_OK);
    for (k = 0; k < 100; ++k) {
        /* preparation: the next state predicted with the command being sent */
        assert_int_equal(ddyn_model_step(&ddyn_model_orca_1_43, DDYN_DISC_RK4, x, u, C, xp, &work), DDYN_OK);
        before = mpc;
        assert_int_equal(ddyn_mpc_prepare(&mpc, xp), DDYN_OK);
        stale = mpc;
        /* the plant: the prediction plus a disturbance the model did not know */
        memcpy(x, xp, sizeof x);
        x[0] += 0.004 * sin(0.3 * k);
        x[1] += 0.004 * cos(0.2 * k);
        x[5] += 0.05 * sin(0.5 * k);
        assert_int_equal(ddyn_mpc_feedback(&mpc, x, u, NULL), DDYN_OK);
        assert_int_equal(ddyn_mpc_solve(&before, x, u_ref, NULL), DDYN_OK);
        assert_int_equal(ddyn_mpc_feedback(&stale, xp, u_stale, NULL), DDYN_OK);
        for (j = 0; j < DDYN_NU; ++j) {
            err_fb += fabs(u[j] - u_ref[j]);
            err_stale += fabs(u_stale[j] - u_ref[j]);
        }
        assert_true(fabs(hypot(x[0], x[1]) - RADIUS) < 0.15);
    }
    print_message("feedback vs full solve %g, ignoring the measurement %g\n", err_fb, err_stale);
    assert_true(err_fb < 0.25 * err_stale); /* the first-order move does most of the re-solve's work */
}

static void test_plan_inputs_need_no_simulation(void **state)
{
    /* the controller's shifted-plan fallback copies the plan's inputs: that copy must not depend on
     * simulating the horizon, which fails with coefficients the model cannot step with */
    static double C_BAD[DDYN_NC];
    double x[DDYN_NX], u[DDYN_NU], up[DDYN_MPC_NV], up2[DDYN_MPC_NV], xp[(DDYN_MPC_MAX_HORIZON + 1) * DDYN_NX];
    (void)state;
    ring_mpc(30);
    ring_start(x);
    assert_int_equal(ddyn_mpc_plan_inputs(&mpc, up), 0); /* no plan yet */
    assert_int_equal(ddyn_mpc_solve(&mpc, x, u, NULL), DDYN_OK);
    assert_int_equal(ddyn_mpc_plan(&mpc, NULL, up2), 20);
    memcpy(C_BAD, C, sizeof C_BAD);
    C_BAD[DDYN_NC - 1] = 0.0; /* Iz = 0: the model step divides by it */
    assert_int_equal(ddyn_mpc_set_coefficients(&mpc, C_BAD), DDYN_OK);
    assert_int_equal(ddyn_mpc_plan(&mpc, xp, NULL), 0); /* the simulation fails ... */
    assert_int_equal(ddyn_mpc_plan_inputs(&mpc, up), 20); /* ... the copy does not */
    assert_memory_equal(up, up2, 20 * DDYN_NU * sizeof(double));
    assert_true(up[0] == u[0] && up[1] == u[1]);
    assert_int_equal(ddyn_mpc_plan_inputs(&mpc, NULL), 0);
}

static void test_default_config_takes_the_vehicle_files_limits(void **state)
{
    ddyn_mpc_config cfg;
    (void)state;
    assert_int_equal(ddyn_mpc_default_config(&ddyn_model_orca_1_43, &cfg), DDYN_OK);
    /* train/vehicles/orca_1_43.json input_limits */
    assert_true(cfg.rate_lo[0] == -10.0 && cfg.rate_hi[0] == 10.0);
    assert_true(cfg.rate_lo[1] == -5.0 && cfg.rate_hi[1] == 5.0);
    assert_true(cfg.state_lo[0] == -0.1 && cfg.state_hi[0] == 1.0);
    assert_true(cfg.state_lo[1] == -0.35 && cfg.state_hi[1] == 0.35);
    assert_int_equal(cfg.horizon, 20);
    assert_int_equal(ddyn_mpc_default_config(&ddyn_model_av21, &cfg), DDYN_OK);
    assert_true(cfg.state_lo[1] == -0.25 && cfg.rate_hi[1] == 0.6);
    assert_int_equal(ddyn_mpc_init(&mpc, &ddyn_model_av21, &cfg), DDYN_OK);
}

static void test_init_refuses_bad_configs(void **state)
{
    ddyn_mpc_config cfg, bad;
    (void)state;
    assert_int_equal(ddyn_mpc_default_config(&ddyn_model_orca_1_43, &cfg), DDYN_OK);
    bad = cfg;
    bad.horizon = DDYN_MPC_MAX_HORIZON + 1;
    assert_int_equal(ddyn_mpc_init(&mpc, &ddyn_model_orca_1_43, &bad), DDYN_ERR_ARGUMENT);
    bad = cfg;
    bad.horizon = 0;
    assert_int_equal(ddyn_mpc_init(&mpc, &ddyn_model_orca_1_43, &bad), DDYN_ERR_ARGUMENT);
    bad = cfg;
    bad.r_rate[1] = 0.0; /* the condensed Hessian needs R > 0 */
    assert_int_equal(ddyn_mpc_init(&mpc, &ddyn_model_orca_1_43, &bad), DDYN_ERR_ARGUMENT);
    bad = cfg;
    bad.q_pos[0] = NAN;
    assert_int_equal(ddyn_mpc_init(&mpc, &ddyn_model_orca_1_43, &bad), DDYN_ERR_ARGUMENT);
    bad = cfg;
    bad.state_lo[0] = bad.state_hi[0];
    assert_int_equal(ddyn_mpc_init(&mpc, &ddyn_model_orca_1_43, &bad), DDYN_ERR_ARGUMENT);
    bad = cfg;
    bad.qp_max_iterations = DDYN_MPC_MAX_QP_ITERATIONS + 1;
    assert_int_equal(ddyn_mpc_init(&mpc, &ddyn_model_orca_1_43, &bad), DDYN_ERR_ARGUMENT);
    assert_int_equal(ddyn_mpc_init(NULL, &ddyn_model_orca_1_43, &cfg), DDYN_ERR_ARGUMENT);
}

static void test_refusals_give_zero_command_and_keep_the_plan(void **state)
{
    ddyn_mpc_config cfg;
    double x0[DDYN_NX], u[DDYN_NU] = {7.0, 7.0}, c_bad[DDYN_NC];
    ddyn_mpc before;
    ddyn_mpc_info info;
    (void)state;
    assert_int_equal(ddyn_mpc_default_config(&ddyn_model_orca_1_43, &cfg), DDYN_OK);
    assert_int_equal(ddyn_mpc_init(&mpc, &ddyn_model_orca_1_43, &cfg), DDYN_OK);
    ring_start(x0);
    assert_int_equal(ddyn_mpc_solve(&mpc, x0, u, &info), DDYN_ERR_NOT_READY); /* no track, no coefficients */
    assert_true(u[0] == 0.0 && u[1] == 0.0);

    ring_mpc(30);
    assert_int_equal(ddyn_mpc_solve(&mpc, x0, u, &info), DDYN_OK);
    before = mpc;
    x0[4] = NAN;
    u[0] = u[1] = 7.0;
    assert_int_equal(ddyn_mpc_solve(&mpc, x0, u, &info), DDYN_ERR_NONFINITE_INPUT);
    assert_true(u[0] == 0.0 && u[1] == 0.0);
    assert_memory_equal(before.u_plan, mpc.u_plan, sizeof mpc.u_plan);
    x0[4] = INFINITY;
    assert_int_equal(ddyn_mpc_solve(&mpc, x0, u, &info), DDYN_ERR_NONFINITE_INPUT);

    memcpy(c_bad, C, sizeof c_bad);
    c_bad[16] = NAN;
    assert_int_equal(ddyn_mpc_set_coefficients(&mpc, c_bad), DDYN_ERR_NONFINITE_INPUT);
    assert_memory_equal(mpc.c, C, sizeof C); /* the previous coefficients stay */

    /* finite coefficients that make the model non-finite (Iz = 0): a status, never a NaN command */
    c_bad[16] = 0.0;
    assert_int_equal(ddyn_mpc_set_coefficients(&mpc, c_bad), DDYN_OK);
    ring_start(x0);
    u[0] = u[1] = 7.0;
    assert_int_equal(ddyn_mpc_solve(&mpc, x0, u, &info), DDYN_ERR_NONFINITE_OUTPUT);
    assert_true(u[0] == 0.0 && u[1] == 0.0);
    assert_int_equal(ddyn_mpc_solve(NULL, x0, u, &info), DDYN_ERR_ARGUMENT);
}

static void test_track_table_is_checked(void **state)
{
    double x[4] = {0, 1, 1, 0}, y[4] = {0, 0, 1, 1}, v[4] = {1, 1, 1, 1}, w[4] = {0.1, 0.1, 0.1, 0.1};
    double v0[4] = {1, 0, 1, 1}, xn[4] = {0, 1, NAN, 0}, xd[4] = {0, 0, 1, 0};
    ddyn_mpc_config cfg;
    (void)state;
    assert_int_equal(ddyn_mpc_default_config(&ddyn_model_orca_1_43, &cfg), DDYN_OK);
    assert_int_equal(ddyn_mpc_init(&mpc, &ddyn_model_orca_1_43, &cfg), DDYN_OK);
    assert_int_equal(ddyn_mpc_set_track(&mpc, 4, x, y, v, w, w), DDYN_OK);
    assert_true(fabs(mpc.track.length - 4.0) < 1e-12);
    assert_int_equal(ddyn_mpc_set_track(&mpc, 3, x, y, v, w, w), DDYN_ERR_ARGUMENT);
    assert_int_equal(ddyn_mpc_set_track(&mpc, 4, x, y, v0, w, w), DDYN_ERR_ARGUMENT);  /* zero speed */
    assert_int_equal(ddyn_mpc_set_track(&mpc, 4, xd, xd, v, w, w), DDYN_ERR_ARGUMENT); /* repeated point */
    assert_int_equal(ddyn_mpc_set_track(&mpc, 4, xn, y, v, w, w), DDYN_ERR_NONFINITE_INPUT);
    assert_int_equal(ddyn_mpc_set_track(&mpc, DDYN_MPC_MAX_TRACK_POINTS + 1, x, y, v, w, w), DDYN_ERR_ARGUMENT);
}

static void qp_clear(int horizon)
{
    memset(&qp, 0, sizeof qp);
    qp.horizon = horizon;
    qp.dt = 0.02;
    qp.rho1 = 10.0;
    qp.rho2 = 1.0;
}

static void open_bounds(int n)
{
    int i;
    for (i = 0; i < n; ++i) {
        qp.lb[i] = -100.0;
        qp.ub[i] = 100.0;
        qp.hard_lo[i] = -100.0;
        qp.hard_hi[i] = 100.0;
    }
    for (i = 0; i < n / 2; ++i) {
        qp.soft_lo[i] = -100.0;
        qp.soft_hi[i] = 100.0;
    }
}

static void test_qp_box_solution_is_the_clipped_minimiser(void **state)
{
    /* diagonal Hessian, box only: z_i = clip(-f_i / h_i, lb_i, ub_i) */
    const int h = 10, n = 2 * h;
    int i;
    (void)state;
    qp_clear(h);
    open_bounds(n);
    for (i = 0; i < n; ++i) {
        qp.hess[i + i * DDYN_QP_NV] = 1.0 + 0.1 * i;
        qp.grad[i] = (i % 3 == 0 ? -5.0 : (i % 3 == 1 ? 4.0 : 0.3)) * qp.hess[i + i * DDYN_QP_NV];
        qp.lb[i] = -1.0;
        qp.ub[i] = 2.0;
    }
    assert_int_equal(ddyn_mpc_qp_solve(&qp, 30, 1e-9), DDYN_OK);
    for (i = 0; i < n; ++i) {
        double want = i % 3 == 0 ? 2.0 : (i % 3 == 1 ? -1.0 : -0.3);
        assert_true(fabs(qp.z[i] - want) < 1e-6);
    }
    assert_true(qp.converged && qp.iterations <= 30);
}

static void test_qp_soft_row_penalty_is_exact(void **state)
{
    /* min 1/2 (z0 - 2)^2 + 1/2 z1^2 + ... with soft row z0 <= 0.5 (+ s): the multiplier 1.5 is below
     * rho1 = 10, so the exact penalty gives s = 0 and z0 = 0.5; with rho1 = 1 the row gives way:
     * z0 - 2 + rho1 + 2 rho2 s = 0 with z0 = 0.5 + s -> s = (1.5 - rho1) / (1 + 2 rho2) */
    const int h = 1;
    (void)state;
    qp_clear(h);
    open_bounds(2);
    qp.hess[0] = 1.0;
    qp.hess[1 + DDYN_QP_NV] = 1.0;
    qp.grad[0] = -2.0;
    qp.soft_row[0] = 1.0;
    qp.soft_hi[0] = 0.5;
    qp.soft_lo[0] = -1.0;
    assert_int_equal(ddyn_mpc_qp_solve(&qp, 30, 1e-10), DDYN_OK);
    assert_true(fabs(qp.z[0] - 0.5) < 1e-6);
    assert_true(fabs(qp.slack[0]) < 1e-6);
    qp.rho1 = 1.0;
    qp.rho2 = 0.5;
    assert_int_equal(ddyn_mpc_qp_solve(&qp, 30, 1e-10), DDYN_OK);
    assert_true(fabs(qp.slack[0] - 0.25) < 1e-6);
    assert_true(fabs(qp.z[0] - 0.75) < 1e-6);
}

static void test_qp_integrator_rows_bound_the_prefix_sums(void **state)
{
    /* pull every z to +50; the throttle row caps dt * sum_{j<k} z[2j] at 0.1 for all k */
    const int h = 5, n = 2 * h;
    int i, k;
    double acc = 0.0;
    (void)state;
    qp_clear(h);
    open_bounds(n);
    for (i = 0; i < n; ++i) {
        qp.hess[i + i * DDYN_QP_NV] = 1.0;
        qp.grad[i] = -50.0;
    }
    for (k = 0; k < h; ++k) {
        qp.hard_hi[2 * k] = 0.1;
    }
    assert_int_equal(ddyn_mpc_qp_solve(&qp, 40, 1e-9), DDYN_OK);
    for (k = 0; k < h; ++k) {
        acc += qp.z[2 * k];
        assert_true(qp.dt * acc <= 0.1 + 1e-6);
        assert_true(fabs(qp.z[2 * k + 1] - 50.0) < 1e-5); /* the steering channel is free */
    }
    assert_true(fabs(qp.dt * acc - 0.1) < 1e-6);
}

/* deterministic pseudo-random numbers in [0, 1) for the dense reference test (LCG, no libc state) */
static double lcg(uint32_t *state)
{
    *state = *state * 1664525u + 1013904223u;
    return (double)(*state >> 8) / 16777216.0;
}

/* The structured Newton matrix (integrator rows by suffix sums, slacks eliminated, left-looking
 * blocked Cholesky) against the dense formula: every inequality row of C = [C_z C_s] written out,
 * K = scale H + C_z'D C_z - B M^-1 B' with M = 2 rho2 scale I + C_s'D C_s (diagonal) and
 * B = C_z'D C_s; the solve must satisfy K x = b, for horizons 20 and 7 (odd, blocks of four cut). */
static void test_qp_newton_matrix_matches_the_dense_formula(void **state)
{
    static double cz[DDYN_QP_NCON][DDYN_QP_NV], cs[DDYN_QP_NCON][DDYN_QP_NS], kref[DDYN_QP_NV][DDYN_QP_NV];
    double D[DDYN_QP_NCON], b[DDYN_QP_NV], x[DDYN_QP_NV], m[DDYN_QP_NS], scale = 0.37;
    const int horizons[2] = {DDYN_MPC_MAX_HORIZON, 7};
    uint32_t seed = 12345u;
    int hi;
    (void)state;
    for (hi = 0; hi < 2; ++hi) {
        const int h = horizons[hi], n = 2 * h, ns = h, mrows = 4 * n + 3 * ns;
        int i, j, k, q, r;
        double knorm = 0.0, xnorm = 0.0, err = 0.0;
        qp_clear(h);
        qp.rho2 = 1e5;
        for (i = 0; i < n; ++i) { /* H = R'R + I, symmetric positive definite */
            for (j = 0; j <= i; ++j) {
                double v = 0.0;
                for (k = 0; k < n; ++k) {
                    v += (lcg(&seed) - 0.5) * (lcg(&seed) - 0.5);
                }
                qp.hess[i + j * DDYN_QP_NV] = v + (i == j ? 1.0 : 0.0);
                qp.hess[j + i * DDYN_QP_NV] = qp.hess[i + j * DDYN_QP_NV];
            }
        }
        for (q = 0; q < ns; ++q) {
            for (j = 0; j < 2 * (q + 1); ++j) {
                qp.soft_row[q * DDYN_QP_NV + j] = 2.0 * lcg(&seed) - 1.0;
            }
        }
        for (r = 0; r < mrows; ++r) { /* barrier weights over twelve decades, as near convergence */
            D[r] = pow(10.0, 12.0 * lcg(&seed) - 6.0);
        }
        memset(cz, 0, sizeof cz);
        memset(cs, 0, sizeof cs);
        for (i = 0; i < n; ++i) {
            cz[i][i] = 1.0;
            cz[n + i][i] = -1.0;
        }
        for (k = 1; k <= h; ++k) {
            int ch;
            for (ch = 0; ch < 2; ++ch) {
                for (j = 0; j < k; ++j) {
                    cz[2 * n + 2 * (k - 1) + ch][2 * j + ch] = qp.dt;
                    cz[3 * n + 2 * (k - 1) + ch][2 * j + ch] = -qp.dt;
                }
            }
        }
        for (q = 0; q < ns; ++q) {
            for (j = 0; j < n; ++j) {
                cz[4 * n + q][j] = qp.soft_row[q * DDYN_QP_NV + j];
                cz[4 * n + ns + q][j] = -qp.soft_row[q * DDYN_QP_NV + j];
            }
            cs[4 * n + q][q] = -1.0;
            cs[4 * n + ns + q][q] = -1.0;
            cs[4 * n + 2 * ns + q][q] = -1.0;
        }
        for (q = 0; q < ns; ++q) {
            m[q] = 2.0 * qp.rho2 * scale;
            for (r = 0; r < mrows; ++r) {
                m[q] += cs[r][q] * D[r] * cs[r][q];
            }
        }
        for (i = 0; i < n; ++i) {
            for (j = 0; j < n; ++j) {
                double v = scale * qp.hess[i + j * DDYN_QP_NV];
                for (r = 0; r < mrows; ++r) {
                    v += cz[r][i] * D[r] * cz[r][j];
                }
                for (q = 0; q < ns; ++q) {
                    double bi = 0.0, bj = 0.0;
                    for (r = 0; r < mrows; ++r) {
                        bi += cz[r][i] * D[r] * cs[r][q];
                        bj += cz[r][j] * D[r] * cs[r][q];
                    }
                    v -= bi * bj / m[q];
                }
                kref[i][j] = v;
                knorm = fmax(knorm, fabs(v));
            }
            b[i] = 2.0 * lcg(&seed) - 1.0;
            x[i] = b[i];
        }
        assert_int_equal(ddyn_mpc_qp_newton_factor(&qp, D, scale), 0);
        ddyn_mpc_qp_newton_solve(&qp, x);
        for (i = 0; i < n; ++i) {
            xnorm = fmax(xnorm, fabs(x[i]));
        }
        for (i = 0; i < n; ++i) {
            double v = -b[i];
            for (j = 0; j < n; ++j) {
                v += kref[i][j] * x[j];
            }
            err = fmax(err, fabs(v));
        }
        assert_true(xnorm > 0.0 && isfinite(xnorm));
        assert_true(err <= 1e-9 * knorm * xnorm); /* backward error of a stable Cholesky, with margin */
    }
}

static void test_qp_refuses_nonfinite_data(void **state)
{
    (void)state;
    qp_clear(2);
    open_bounds(4);
    qp.hess[0] = 1.0;
    qp.hess[1 + DDYN_QP_NV] = 1.0;
    qp.hess[2 + 2 * DDYN_QP_NV] = 1.0;
    qp.hess[3 + 3 * DDYN_QP_NV] = 1.0;
    qp.grad[2] = NAN;
    assert_int_equal(ddyn_mpc_qp_solve(&qp, 30, 1e-9), DDYN_ERR_NONFINITE_INPUT);
    assert_true(qp.z[0] == 0.0 && qp.z[2] == 0.0);
    qp.grad[2] = 0.0;
    qp.horizon = 0;
    assert_int_equal(ddyn_mpc_qp_solve(&qp, 30, 1e-9), DDYN_ERR_ARGUMENT);
}

static void test_iteration_cap_reports_and_commands_within_bounds(void **state)
{
    double x0[DDYN_NX], u[DDYN_NU];
    ddyn_mpc_info info;
    (void)state;
    ring_mpc(1);
    mpc.cfg.qp_cold_max_iterations = 1; /* the first QP starts cold: the interior point's cap */
    ring_start(x0);
    assert_int_equal(ddyn_mpc_solve(&mpc, x0, u, &info), DDYN_ERR_QP_NOT_CONVERGED);
    assert_int_equal(info.qp_cold_start, 1);
    assert_int_equal(info.converged, 0);
    assert_int_equal(info.qp_iterations, 1);
    assert_true(isfinite(u[0]) && isfinite(u[1]));
    assert_true(u[0] >= mpc.cfg.rate_lo[0] && u[0] <= mpc.cfg.rate_hi[0]);
    assert_true(u[1] >= mpc.cfg.rate_lo[1] && u[1] <= mpc.cfg.rate_hi[1]);
    assert_true(info.kkt_residual > mpc.cfg.qp_tolerance);
}

/* ---- the DAQP path (mpc_qp_daqp.c): the same structured problems, the penalty, warm start, cap ---- */
static ddyn_mpc_qp_daqp daqp;

/* a box-only QP over h stages whose minimiser is the unconstrained one (-5, 4, 0.3 repeating) clipped to
 * [-1, 2]: the first two of every three variables end on a bound */
static void box_qp(int h)
{
    int i;
    qp_clear(h);
    open_bounds(2 * h);
    for (i = 0; i < 2 * h; ++i) {
        qp.hess[i + i * DDYN_QP_NV] = 1.0 + 0.1 * i;
        qp.grad[i] = (i % 3 == 0 ? -5.0 : (i % 3 == 1 ? 4.0 : 0.3)) * qp.hess[i + i * DDYN_QP_NV];
        qp.lb[i] = -1.0;
        qp.ub[i] = 2.0;
    }
}


static void test_daqp_solves_the_structured_qps(void **state)
{
    /* the three problems with known answers above, now through DAQP's core on the static workspace */
    int i, k, h;
    double acc = 0.0;
    (void)state;
    /* box only: the clipped minimiser */
    h = 10;
    box_qp(h);
    ddyn_mpc_qp_daqp_reset(&daqp);
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&qp, &daqp, 30, 0), DDYN_OK);
    for (i = 0; i < 2 * h; ++i) {
        assert_true(fabs(qp.z[i] - (i % 3 == 0 ? 2.0 : (i % 3 == 1 ? -1.0 : -0.3))) < 1e-9);
    }
    assert_true(qp.converged && qp.residual <= 1e-9 && daqp.cold);
    /* cold, one constraint per iteration: at least the 14 active bounds; the same QP warm-started
     * (shift 0) from that working set only checks it */
    assert_true(qp.iterations >= 14 && daqp.warm_n == 14);
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&qp, &daqp, 30, 0), DDYN_OK);
    assert_true(!daqp.cold && qp.iterations <= 1 && fabs(qp.z[0] - 2.0) < 1e-9);
    /* shifted one stage: with the same pattern at every stage (throttle at its upper, steering at its
     * lower bound), stage k's bounds move to stage k-1 and only the last stage's two are added */
    for (i = 0; i < 2 * h; ++i) {
        qp.grad[i] = (i % 2 == 0 ? -5.0 : 4.0) * qp.hess[i + i * DDYN_QP_NV];
    }
    ddyn_mpc_qp_daqp_reset(&daqp);
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&qp, &daqp, 30, 0), DDYN_OK);
    assert_true(qp.iterations >= 2 * h && daqp.warm_n == 2 * h);
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&qp, &daqp, 30, 1), DDYN_OK);
    assert_true(qp.iterations == 3 && fabs(qp.z[2 * h - 2] - 2.0) < 1e-9 && fabs(qp.z[2 * h - 1] + 1.0) < 1e-9);
    /* the soft row's penalty rho1 s + rho2 s^2, mapped onto DAQP's w s + s^2 / (2 rho): exact below
     * the price, s = (1.5 - rho1) / (1 + 2 rho2) above it */
    qp_clear(1);
    open_bounds(2);
    qp.hess[0] = 1.0;
    qp.hess[1 + DDYN_QP_NV] = 1.0;
    qp.grad[0] = -2.0;
    qp.soft_row[0] = 1.0;
    qp.soft_hi[0] = 0.5;
    qp.soft_lo[0] = -1.0;
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&qp, &daqp, 30, 0), DDYN_OK);
    assert_true(fabs(qp.z[0] - 0.5) < 1e-9 && fabs(qp.slack[0]) < 1e-9);
    qp.rho1 = 1.0;
    qp.rho2 = 0.5;
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&qp, &daqp, 30, 0), DDYN_OK);
    assert_true(fabs(qp.slack[0] - 0.25) < 1e-9 && fabs(qp.z[0] - 0.75) < 1e-9);
    qp.rho2 = 2.0; /* s = 0.5 / 5 */
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&qp, &daqp, 30, 0), DDYN_OK);
    assert_true(fabs(qp.slack[0] - 0.1) < 1e-9);
    /* the integrator rows cap the prefix sums of one channel, the other stays free */
    h = 5;
    qp_clear(h);
    open_bounds(2 * h);
    for (i = 0; i < 2 * h; ++i) {
        qp.hess[i + i * DDYN_QP_NV] = 1.0;
        qp.grad[i] = -50.0;
    }
    for (k = 0; k < h; ++k) {
        qp.hard_hi[2 * k] = 0.1;
    }
    ddyn_mpc_qp_daqp_reset(&daqp);
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&qp, &daqp, 30, 0), DDYN_OK);
    for (k = 0; k < h; ++k) {
        acc += qp.z[2 * k];
        assert_true(qp.dt * acc <= 0.1 + 1e-9);
        assert_true(fabs(qp.z[2 * k + 1] - 50.0) < 1e-9);
    }
    assert_true(fabs(qp.dt * acc - 0.1) < 1e-9);
}

static void test_daqp_refusals_and_crossing_bounds_start_cold(void **state)
{
    (void)state;
    qp_clear(2);
    open_bounds(4);
    for (int i = 0; i < 4; ++i) {
        qp.hess[i + i * DDYN_QP_NV] = 1.0;
    }
    qp.soft_lo[0] = -1.0; /* a soft row that binds: the working set is not empty */
    qp.soft_row[0] = 1.0;
    qp.grad[0] = -5.0;
    ddyn_mpc_qp_daqp_reset(&daqp);
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&qp, &daqp, 30, 0), DDYN_OK);
    qp.soft_hi[0] = 0.1;
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&qp, &daqp, 30, 0), DDYN_OK);
    assert_true(daqp.warm_n > 0);
    qp.grad[2] = NAN;
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&qp, &daqp, 30, 1), DDYN_ERR_NONFINITE_INPUT);
    assert_true(qp.z[0] == 0.0 && daqp.warm_n == 0);
    qp.grad[2] = 0.0;
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&qp, &daqp, 30, 0), DDYN_OK);
    assert_true(daqp.warm_n > 0);
    qp.hard_lo[1] = 1.0; /* crossing hard bounds: no solution, a defined answer, cold next time */
    qp.hard_hi[1] = 0.5;
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&qp, &daqp, 30, 0), DDYN_ERR_QP_NOT_CONVERGED);
    assert_true(!qp.converged && daqp.warm_n == 0 && isfinite(qp.z[0]));
    qp.hess[5] = 1.0; /* not symmetric positive definite: H = [[1, 1], [1, 1]] in the first block */
    qp.hess[1] = 1.0;
    qp.hard_lo[1] = -100.0;
    qp.hard_hi[1] = 100.0;
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&qp, &daqp, 30, 0), DDYN_ERR_ARGUMENT);
}

/* the QP's objective at its solution z, slack */
static double qp_objective(const ddyn_mpc_qp *p)
{
    const int n = 2 * p->horizon;
    double f = 0.0;
    int i, j;
    for (i = 0; i < n; ++i) {
        double hz = 0.0;
        for (j = 0; j < n; ++j) {
            hz += p->hess[i + j * DDYN_QP_NV] * p->z[j];
        }
        f += p->z[i] * (0.5 * hz + p->grad[i]);
    }
    for (i = 0; i < p->horizon; ++i) {
        f += p->rho1 * p->slack[i] + p->rho2 * p->slack[i] * p->slack[i];
    }
    return f;
}

static void test_daqp_warm_start_shifts_and_the_cap_is_defined(void **state)
{
    /* closed loop on the ring with DAQP (the default): every QP, re-solved cold from the same problem,
     * has the same answer; the shifted warm start needs fewer iterations than cold starts in total */
    static ddyn_model_work work;
    static ddyn_mpc_qp copy;
    double x[DDYN_NX], u[DDYN_NU], xn[DDYN_NX];
    ddyn_mpc_info info;
    int k, i, warm_total = 0, cold_total = 0;
    (void)state;
    ring_mpc(30);
    assert_int_equal(mpc.cfg.qp_solver, DDYN_MPC_QP_DAQP);
    ring_start(x);
    for (k = 0; k < 60; ++k) {
        assert_int_equal(ddyn_mpc_solve(&mpc, x, u, &info), DDYN_OK);
        /* only the first QP starts cold (the interior point, stopped at its tolerance 1e-6: loose in
         * the nearly free throttle direction); the others are DAQP's, warm-started */
        assert_int_equal(info.qp_cold_start, k == 0);
        if (k > 0) {
            warm_total += info.qp_iterations;
        }
        memcpy(&copy, &mpc.qp, sizeof copy);
        ddyn_mpc_qp_daqp_reset(&daqp);
        assert_int_equal(ddyn_mpc_qp_daqp_solve(&copy, &daqp, 50, 1), DDYN_OK);
        cold_total += k > 0 ? copy.iterations : 0;
        if (k == 0) { /* (the interior point stops ~1e-3 from the optimum's objective: docs/mpc.md) */
            const double f_ipm = qp_objective(&mpc.qp), f_daqp = qp_objective(&copy);
            assert_true(f_daqp <= f_ipm + 1e-9 * fabs(f_ipm) && f_ipm - f_daqp <= 1e-3 * fmax(1.0, fabs(f_daqp)));
        }
        for (i = 0; i < 2 * mpc.cfg.horizon; ++i) {
            assert_true(k == 0 || fabs(copy.z[i] - mpc.qp.z[i]) < 1e-7);
        }
        assert_int_equal(ddyn_model_step(&ddyn_model_orca_1_43, DDYN_DISC_RK4, x, u, C, xn, &work), DDYN_OK);
        memcpy(x, xn, sizeof x);
    }
    /* (the ring's QPs have few active constraints: about one iteration each either way) */
    print_message("DAQP on the ring: %d iterations warm-started, %d cold over 60 QPs\n", warm_total, cold_total);
    assert_true(warm_total <= cold_total);
    /* the cap: from a wrong working set DAQP cannot finish in 3 iterations; the answer is finite and
     * within the rate bounds, and the next period starts cold: the interior point finishes the work */
    ddyn_mpc_qp_daqp_adversarial_start(&mpc.daqp, mpc.cfg.horizon);
    mpc.cfg.qp_max_iterations = 3;
    assert_int_equal(ddyn_mpc_solve(&mpc, x, u, &info), DDYN_ERR_QP_NOT_CONVERGED);
    assert_true(info.qp_iterations == 3 && !info.converged && !info.qp_cold_start && mpc.daqp.warm_h == 0);
    assert_true(isfinite(u[0]) && isfinite(u[1]) && fabs(u[0]) <= 10.0 && fabs(u[1]) <= 5.0);
    assert_int_equal(ddyn_mpc_solve(&mpc, x, u, &info), DDYN_OK);
    assert_true(info.qp_cold_start && info.converged);
    mpc.cfg.qp_max_iterations = 50;
    /* a reset of the MPC (a fault) starts the QP cold: the interior point solves it and leaves DAQP a
     * working set for the next period */
    ddyn_mpc_reset(&mpc);
    assert_int_equal(mpc.daqp.warm_n, 0);
    assert_int_equal(ddyn_mpc_solve(&mpc, x, u, &info), DDYN_OK);
    assert_true(info.qp_cold_start && mpc.daqp.warm_h == mpc.cfg.horizon);
    assert_int_equal(ddyn_mpc_solve(&mpc, x, u, &info), DDYN_OK);
    assert_true(!info.qp_cold_start);
}

static void test_interior_point_seeds_daqp_working_set(void **state)
{
    /* box QP with 14 active bounds: DAQP from an empty working set needs at least 14 iterations; from
     * the set the interior point's solution marks active (ddyn_mpc_qp_daqp_seed) it only checks it */
    int i, h = 10;
    (void)state;
    box_qp(h);
    assert_int_equal(ddyn_mpc_qp_solve(&qp, 30, 1e-8), DDYN_OK);
    for (i = 0; i < 2 * h; ++i) {
        const int side = ddyn_mpc_qp_active_side(&qp, i);
        assert_int_equal(side, i % 3 == 0 ? 1 : (i % 3 == 1 ? -1 : 0));
    }
    for (i = 2 * h; i < 5 * h; ++i) { /* integrator and soft rows: open */
        assert_int_equal(ddyn_mpc_qp_active_side(&qp, i), 0);
    }
    assert_int_equal(ddyn_mpc_qp_active_side(&qp, 5 * h), 0); /* out of range */
    ddyn_mpc_qp_daqp_reset(&daqp);
    ddyn_mpc_qp_daqp_seed(&daqp, &qp);
    assert_true(daqp.warm_n == 14 && daqp.warm_h == h);
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&qp, &daqp, 30, 0), DDYN_OK);
    assert_true(!daqp.cold && qp.iterations <= 1 && fabs(qp.z[0] - 2.0) < 1e-9 && fabs(qp.z[1] + 1.0) < 1e-9);
}

static void test_cold_start_beyond_daqp_cap_converges_in_its_period(void **state)
{
    /* a hard first QP (the car outside the line, heading out, steering the wrong way: ~55 constraints
     * active at the optimum): DAQP from an empty working set needs far more than its cap of 30; the
     * interior point solves it in its period within its own cap, and the working set it leaves
     * (ddyn_mpc_qp_daqp_seed) is the optimum's: DAQP re-solving the same QP from it takes 1 iteration,
     * and the next period's QP, warm from it shifted, takes fewer than a cold start of that QP */
    static ddyn_model_work work;
    static ddyn_mpc_qp copy;
    static ddyn_mpc_qp_daqp seeded;
    double x[DDYN_NX], u[DDYN_NU], xn[DDYN_NX];
    ddyn_mpc_info info;
    ddyn_status st;
    (void)state;
    ring_mpc(30);
    ring_start(x);
    x[0] += 0.1;
    x[2] -= 0.5;
    x[7] = -0.3;
    assert_int_equal(ddyn_mpc_solve(&mpc, x, u, &info), DDYN_OK);
    assert_true(info.qp_cold_start && info.converged && info.qp_iterations <= mpc.cfg.qp_cold_max_iterations);
    assert_true(mpc.daqp.warm_n > 30);
    memcpy(&copy, &mpc.qp, sizeof copy);
    ddyn_mpc_qp_daqp_reset(&daqp);
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&copy, &daqp, 150, 0), DDYN_OK);
    print_message("hard first QP: DAQP cold %d iterations", copy.iterations);
    assert_true(copy.iterations > mpc.cfg.qp_max_iterations);
    memcpy(&copy, &mpc.qp, sizeof copy);
    memcpy(&seeded, &mpc.daqp, sizeof seeded);
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&copy, &seeded, 150, 0), DDYN_OK);
    print_message(", from the interior point's working set %d", copy.iterations);
    assert_true(copy.iterations <= 2);
    assert_int_equal(ddyn_model_step(&ddyn_model_orca_1_43, DDYN_DISC_RK4, x, u, C, xn, &work), DDYN_OK);
    memcpy(x, xn, sizeof x);
    st = ddyn_mpc_solve(&mpc, x, u, &info);
    assert_true((st == DDYN_OK || st == DDYN_ERR_QP_NOT_CONVERGED) && !info.qp_cold_start);
    memcpy(&copy, &mpc.qp, sizeof copy);
    ddyn_mpc_qp_daqp_reset(&daqp);
    assert_int_equal(ddyn_mpc_qp_daqp_solve(&copy, &daqp, 150, 0), DDYN_OK);
    print_message("; next period warm %d, cold %d\n", info.qp_iterations, copy.iterations);
    assert_true(info.qp_iterations < copy.iterations);
}

static void test_generated_prediction_step_jacobians_and_integrators(void **state)
{
    /* the MPC's step: A, B against central differences; throttle, steering are exact integrators
     * (the QP's prefix-sum rows rely on it) */
    /* the 1:43 car's row, found by name: the table holds every vehicle file, in name order */
    int row = 0;
    ddyn_casadi_fn step;
    double x[DDYN_NX] = {0.3, -0.2, 0.4, 1.7, 0.1, 1.2, 0.4, 0.1}, u[DDYN_NU] = {0.5, -0.8};
    double out[DDYN_NX * 11], xp[DDYN_NX], xm[DDYN_NX], scratch[DDYN_NX * 10];
    static ddyn_model_work work;
    const double *arg[4];
    double *res[3];
    const double flat[2] = {0.0, 0.0};
    int i, j;
    (void)state;
    while (row < DDYN_MPC_LIMITS_COUNT - 1 && strcmp(ddyn_mpc_limits[row].name, "orca_1_43") != 0) ++row;
    assert_string_equal(ddyn_mpc_limits[row].name, "orca_1_43");
    step = ddyn_mpc_limits[row].step;
    arg[0] = x;
    arg[1] = u;
    arg[2] = C;
    arg[3] = flat; /* the road (bank, grade): flat and level */
    res[0] = out;
    res[1] = out + DDYN_NX;
    res[2] = out + DDYN_NX * 9;
    assert_int_equal(step(arg, res, work.iw, work.w, 0), 0);
    for (j = 0; j < DDYN_NX + DDYN_NU; ++j) {
        double xx[DDYN_NX], uu[DDYN_NU], h = 1e-6;
        double *r2[3];
        memcpy(xx, x, sizeof xx);
        memcpy(uu, u, sizeof uu);
        arg[0] = xx;
        arg[1] = uu;
        r2[0] = xp;
        r2[1] = scratch;
        r2[2] = scratch + 64;
        if (j < DDYN_NX) xx[j] += h; else uu[j - DDYN_NX] += h;
        step(arg, r2, work.iw, work.w, 0);
        r2[0] = xm;
        if (j < DDYN_NX) xx[j] -= 2 * h; else uu[j - DDYN_NX] -= 2 * h;
        step(arg, r2, work.iw, work.w, 0);
        for (i = 0; i < DDYN_NX; ++i) {
            double fd = (xp[i] - xm[i]) / (2 * h);
            double an = j < DDYN_NX ? out[DDYN_NX + i + j * DDYN_NX] : out[DDYN_NX * 9 + i + (j - DDYN_NX) * DDYN_NX];
            assert_true(fabs(fd - an) < 1e-5 * (1.0 + fabs(an)));
        }
    }
    for (i = 6; i < 8; ++i) {
        for (j = 0; j < DDYN_NX; ++j) {
            assert_true(out[DDYN_NX + i + j * DDYN_NX] == (i == j ? 1.0 : 0.0));
        }
        for (j = 0; j < DDYN_NU; ++j) {
            assert_true(fabs(out[DDYN_NX * 9 + i + j * DDYN_NX] - (i - 6 == j ? 0.02 : 0.0)) < 1e-15);
        }
    }
}

/* orca_1_43's MPC step at x = {0.3, -0.2, 0.4, 1.7, 0.1, 1.2, 0.4, 0.1}, u = {0.5, -0.8}, the true coefficients,
 * from the Python model: ddyn.model.effects.derivatives (Aux.bank, no other effect) under
 * ddyn.model.integrators' single-step RK4 over the sample time, numpy float64 */
static const double BANK_CASES[3] = {0.0, 0.3, -0.2};
static const double BANK_PY_NEXT[3][DDYN_NX] = {
    {0.3306361169343469, -0.184866531731419, 0.4348376789836934, 1.7140018385223148, 0.04474829274604333,
     2.035014928766496, 0.41000000000000003, 0.084},
    {0.33045488489517694, -0.1844335327445091, 0.43493488799579993, 1.7156753687396273, 0.08631985502760987,
     2.0506102334613545, 0.41000000000000003, 0.084},
    {0.33075800631713176, -0.1851577000517705, 0.4347322556570303, 1.7128853631706895, 0.01680847870756068,
     2.0205646601087768, 0.41000000000000003, 0.084}};
/* effects.G * sin(bank) */
static const double BANK_PY_ACCEL[3] = {0.0, 2.899053227347741, -1.9489461350995507};

static void test_bank_gravity_term_matches_the_python_model(void **state)
{
    /* the generated step's bank input and the runtime's gravity term, against the Python model to 1e-12 */
    int row = 0, k, i;
    double x[DDYN_NX] = {0.3, -0.2, 0.4, 1.7, 0.1, 1.2, 0.4, 0.1}, u[DDYN_NU] = {0.5, -0.8};
    double out[DDYN_NX * 11];
    static ddyn_model_work work;
    const double *arg[4];
    double *res[3];
    (void)state;
    while (row < DDYN_MPC_LIMITS_COUNT - 1 && strcmp(ddyn_mpc_limits[row].name, "orca_1_43") != 0) ++row;
    for (k = 0; k < 3; ++k) {
        const double road[2] = {BANK_CASES[k], 0.0}; /* the generated step's road input: bank, grade */
        arg[0] = x;
        arg[1] = u;
        arg[2] = C;
        arg[3] = road;
        res[0] = out;
        res[1] = out + DDYN_NX;
        res[2] = out + DDYN_NX * 9;
        assert_int_equal(ddyn_mpc_limits[row].step(arg, res, work.iw, work.w, 0), 0);
        for (i = 0; i < DDYN_NX; ++i) {
            assert_true(fabs(out[i] - BANK_PY_NEXT[k][i]) < 1e-12);
        }
        assert_true(fabs(ddyn_model_bank_accel(BANK_CASES[k]) - BANK_PY_ACCEL[k]) < 1e-12);
    }
    {
        /* the filter's term: a constant lateral acceleration over dt, along the left normal at x's yaw */
        double xn[DDYN_NX] = {0}, a = ddyn_model_bank_accel(0.3), dt = 0.02;
        ddyn_model_add_bank(0.3, dt, x, xn);
        assert_true(fabs(xn[4] - a * dt) < 1e-15);
        assert_true(fabs(xn[0] + 0.5 * a * dt * dt * sin(x[2])) < 1e-15);
        assert_true(fabs(xn[1] - 0.5 * a * dt * dt * cos(x[2])) < 1e-15);
        assert_true(xn[2] == 0.0 && xn[3] == 0.0 && xn[5] == 0.0 && xn[6] == 0.0 && xn[7] == 0.0);
        memset(xn, 0, sizeof xn);
        ddyn_model_add_bank(0.0, dt, x, xn); /* a flat road: untouched */
        for (i = 0; i < DDYN_NX; ++i) assert_true(xn[i] == 0.0);
    }
}

/* the grade's step from the Python model (Aux.grade, and with the bank's 0.3 rad beside it), as BANK_PY_NEXT */
static const double GRADE_CASES[3][2] = {{0.0, 0.1}, {0.0, -0.15}, {0.3, 0.1}};
static const double GRADE_PY_NEXT[3][DDYN_NX] = {
    {0.3304580021143153, -0.18494587202816118, 0.4347930437881701, 1.694546402204692, 0.04490673652030404,
     2.026789687615091, 0.41000000000000003, 0.084},
    {0.3309027435026256, -0.184747789695697, 0.43490384040872315, 1.743124552972295, 0.04450307582774595,
     2.0470901042985465, 0.41000000000000003, 0.084},
    {0.330277006535652, -0.18451332760484235, 0.4348891996249318, 1.6962227999541504, 0.08637707332138933,
     2.042429791145262, 0.41000000000000003, 0.084}};

static void test_grade_gravity_term_matches_the_python_model(void **state)
{
    /* the generated step's road input (bank, grade) and the runtime's grade term, against the Python model */
    int row = 0, k, i;
    double x[DDYN_NX] = {0.3, -0.2, 0.4, 1.7, 0.1, 1.2, 0.4, 0.1}, u[DDYN_NU] = {0.5, -0.8};
    double out[DDYN_NX * 11];
    static ddyn_model_work work;
    const double *arg[4];
    double *res[3];
    (void)state;
    while (row < DDYN_MPC_LIMITS_COUNT - 1 && strcmp(ddyn_mpc_limits[row].name, "orca_1_43") != 0) ++row;
    for (k = 0; k < 3; ++k) {
        arg[0] = x;
        arg[1] = u;
        arg[2] = C;
        arg[3] = GRADE_CASES[k];
        res[0] = out;
        res[1] = out + DDYN_NX;
        res[2] = out + DDYN_NX * 9;
        assert_int_equal(ddyn_mpc_limits[row].step(arg, res, work.iw, work.w, 0), 0);
        for (i = 0; i < DDYN_NX; ++i) {
            assert_true(fabs(out[i] - GRADE_PY_NEXT[k][i]) < 1e-12);
        }
    }
    assert_true(fabs(ddyn_model_grade_accel(0.1) - (-0.9793658173053843)) < 1e-12); /* -G sin(grade) */
    {
        /* the filter's term: a constant longitudinal acceleration over dt, along x's heading */
        double xn[DDYN_NX] = {0}, a = ddyn_model_grade_accel(-0.15), dt = 0.02;
        assert_true(a > 1.4); /* downhill: the car gains speed */
        ddyn_model_add_grade(-0.15, dt, x, xn);
        assert_true(fabs(xn[3] - a * dt) < 1e-15);
        assert_true(fabs(xn[0] - 0.5 * a * dt * dt * cos(x[2])) < 1e-15);
        assert_true(fabs(xn[1] - 0.5 * a * dt * dt * sin(x[2])) < 1e-15);
        assert_true(xn[2] == 0.0 && xn[4] == 0.0 && xn[5] == 0.0 && xn[6] == 0.0 && xn[7] == 0.0);
        memset(xn, 0, sizeof xn);
        ddyn_model_add_grade(0.0, dt, x, xn); /* a level road: untouched */
        for (i = 0; i < DDYN_NX; ++i) assert_true(xn[i] == 0.0);
    }
}

static void test_grade_table_lookup_and_refusals(void **state)
{
    /* the ring with a grade falling with the angle beside a constant bank: one projection reads both, each stage
     * predicts with both at its own position; a bad grade is refused and leaves the profile */
    static double grade[RING], bank[RING];
    double x0[DDYN_NX], u[DDYN_NU], road[2];
    ddyn_mpc_info info;
    int i, hint = -1;
    (void)state;
    for (i = 0; i < RING; ++i) {
        grade[i] = -0.2 * i / RING;
        bank[i] = 0.1;
    }
    ring_mpc(30);
    assert_false(mpc.track.have_grade);
    assert_int_equal(ddyn_mpc_set_grade(&mpc, grade), DDYN_OK);
    assert_true(mpc.track.have_grade && !mpc.track.have_bank);
    assert_true(fabs(ddyn_mpc_track_grade(&mpc.track, 10, 0.25) + 0.2 * 10.25 / RING) < 1e-15);
    ddyn_mpc_road_at(&mpc, RADIUS, 0.0, &hint, road);
    assert_true(road[0] == 0.0 && fabs(road[1]) < 1e-12); /* no bank profile: flat; the grade at point 0 */
    assert_int_equal(ddyn_mpc_set_bank(&mpc, bank), DDYN_OK);
    ring_start(x0);
    assert_int_equal(ddyn_mpc_solve(&mpc, x0, u, &info), DDYN_OK);
    for (i = 0; i < mpc.cfg.horizon; ++i) {
        const double *xk = mpc.x_lin + i * DDYN_NX;
        ddyn_mpc_road_at(&mpc, xk[0], xk[1], NULL, road);
        assert_true(fabs(mpc.stage_grade[i] - road[1]) < 1e-12 && fabs(mpc.stage_bank[i] - 0.1) < 1e-12);
    }
    assert_true(mpc.stage_grade[mpc.cfg.horizon - 1] < mpc.stage_grade[0]); /* counter-clockwise: falling */
    grade[7] = 0.35;
    assert_int_equal(ddyn_mpc_set_grade(&mpc, grade), DDYN_ERR_ARGUMENT);
    grade[7] = NAN;
    assert_int_equal(ddyn_mpc_set_grade(&mpc, grade), DDYN_ERR_NONFINITE_INPUT);
    assert_true(mpc.track.have_grade && fabs(mpc.track.grade[7] + 0.2 * 7 / RING) < 1e-15);
    assert_int_equal(ddyn_mpc_set_grade(&mpc, NULL), DDYN_OK);
    assert_false(mpc.track.have_grade);
    assert_true(mpc.track.have_bank); /* the bank's profile is its own */
    assert_int_equal(ddyn_mpc_set_grade(NULL, grade), DDYN_ERR_ARGUMENT);
}

static void test_bank_table_lookup_and_refusals(void **state)
{
    /* the ring with a bank growing with the angle: the table reads linearly between its points, at the
     * projection of a position; each stage predicts with the bank at its own position; bad profiles refused */
    static double bank[RING];
    double x0[DDYN_NX], u[DDYN_NU];
    ddyn_mpc_info info;
    int i, hint = -1;
    ddyn_mpc_config cfg;
    static ddyn_mpc other;
    (void)state;
    for (i = 0; i < RING; ++i) bank[i] = 0.3 * i / RING;
    ring_mpc(30);
    assert_false(mpc.track.have_bank);
    assert_true(ddyn_mpc_bank_at(&mpc, RADIUS, 0.0, NULL) == 0.0); /* no profile: flat */
    assert_int_equal(ddyn_mpc_set_bank(&mpc, bank), DDYN_OK);
    assert_true(mpc.track.have_bank);
    assert_true(fabs(ddyn_mpc_track_bank(&mpc.track, 10, 0.25) - (0.3 * 10.25 / RING)) < 1e-15);
    assert_true(fabs(ddyn_mpc_track_bank(&mpc.track, RING - 1, 0.5) - 0.5 * 0.3 * (RING - 1) / RING) < 1e-15);
    assert_true(ddyn_mpc_track_bank(&mpc.track, RING, 0.0) == 0.0 && ddyn_mpc_track_bank(&mpc.track, 3, 1.5) == 0.0);
    {
        /* a point half-way along segment 50, 5 cm outside the ring: the bank there */
        double a0 = 2.0 * PI * 50 / RING, a1 = 2.0 * PI * 51 / RING;
        double px = 0.5 * (cos(a0) + cos(a1)) * 1.05, py = 0.5 * (sin(a0) + sin(a1)) * 1.05;
        assert_true(fabs(ddyn_mpc_bank_at(&mpc, px, py, &hint) - 0.3 * 50.5 / RING) < 1e-12);
        assert_int_equal(hint, 50);
        assert_true(fabs(ddyn_mpc_bank_at(&mpc, px, py, NULL) - 0.3 * 50.5 / RING) < 1e-12);
        assert_true(ddyn_mpc_bank_at(&mpc, NAN, py, &hint) == 0.0);
    }
    /* a solve: each stage's bank is the table's at its predicted position */
    ring_start(x0);
    assert_int_equal(ddyn_mpc_solve(&mpc, x0, u, &info), DDYN_OK);
    for (i = 0; i < mpc.cfg.horizon; ++i) {
        const double *xk = mpc.x_lin + i * DDYN_NX;
        assert_true(fabs(mpc.stage_bank[i] - ddyn_mpc_bank_at(&mpc, xk[0], xk[1], NULL)) < 1e-12);
    }
    assert_true(mpc.stage_bank[mpc.cfg.horizon - 1] > mpc.stage_bank[0]); /* counter-clockwise: growing */
    /* refusals leave the profile */
    bank[7] = 0.7854;
    assert_int_equal(ddyn_mpc_set_bank(&mpc, bank), DDYN_ERR_ARGUMENT);
    bank[7] = NAN;
    assert_int_equal(ddyn_mpc_set_bank(&mpc, bank), DDYN_ERR_NONFINITE_INPUT);
    assert_true(mpc.track.have_bank && fabs(mpc.track.bank[7] - 0.3 * 7 / RING) < 1e-15);
    assert_int_equal(ddyn_mpc_set_bank(&mpc, NULL), DDYN_OK); /* back to flat */
    assert_false(mpc.track.have_bank);
    assert_int_equal(ddyn_mpc_set_bank(NULL, bank), DDYN_ERR_ARGUMENT);
    assert_int_equal(ddyn_mpc_default_config(&ddyn_model_orca_1_43, &cfg), DDYN_OK);
    assert_int_equal(ddyn_mpc_init(&other, &ddyn_model_orca_1_43, &cfg), DDYN_OK);
    assert_int_equal(ddyn_mpc_set_bank(&other, bank), DDYN_ERR_NOT_READY); /* no track yet */
    cfg.prediction = DDYN_MPC_PRED_EULER; /* its step carries no bank */
    assert_int_equal(ddyn_mpc_init(&other, &ddyn_model_orca_1_43, &cfg), DDYN_OK);
    assert_int_equal(ddyn_mpc_set_bank(&other, bank), DDYN_ERR_ARGUMENT);
}

/* the downforce's derivative from the Python model: ddyn.model.effects.derivatives (EffectSet(downforce=k), no
 * other effect) at the state and inputs of the bank's test, numpy float64 */
static const double DOWNFORCE_CASES[3] = {0.0, 0.05, 0.3};
static const double DOWNFORCE_PY_XDOT[3][DDYN_NX] = {
    {1.5268618555740394, 0.7541172813249943, 1.2, 0.666103544295634, -2.508701605473515, 79.23100537334926, 0.5, -0.8},
    {1.5268618555740394, 0.7541172813249943, 1.2, 0.6573090405766787, -2.5811440992646713, 90.77148356596814, 0.5,
     -0.8},
    {1.5268618555740394, 0.7541172813249943, 1.2, 0.6133365219819027, -2.9433565682204508, 148.47387452906244, 0.5,
     -0.8}};

static void test_downforce_matches_the_python_model_and_each_stage_uses_its_speed(void **state)
{
    const double x[DDYN_NX] = {0.3, -0.2, 0.4, 1.7, 0.1, 1.2, 0.4, 0.1}, u[DDYN_NU] = {0.5, -0.8};
    double c_at[DDYN_NC], xdot[DDYN_NX], x0[DDYN_NX], uc[DDYN_NU], out[DDYN_NX * 11], in_place[DDYN_NC];
    static ddyn_model_work work;
    const double road[2] = {0.0, 0.0};
    const double *arg[4];
    double *res[3];
    ddyn_mpc_info info;
    int k, i, differs = 0;
    (void)state;
    for (k = 0; k < 3; ++k) {
        ddyn_model_downforce(C, DOWNFORCE_CASES[k], x[3], c_at);
        assert_int_equal(ddyn_model_derivatives(&ddyn_model_orca_1_43, x, u, c_at, xdot, &work), DDYN_OK);
        for (i = 0; i < DDYN_NX; ++i) {
            assert_true(fabs(xdot[i] - DOWNFORCE_PY_XDOT[k][i]) < 1e-12 * (1.0 + fabs(xdot[i])));
        }
    }
    ddyn_model_downforce(C, 0.0, 3.0, c_at);
    assert_memory_equal(c_at, C, sizeof c_at); /* none: bit-identical */
    memcpy(in_place, C, sizeof in_place);
    ddyn_model_downforce(in_place, 0.3, 2.0, in_place);
    assert_true(in_place[DDYN_MODEL_DF_INDEX] == C[DDYN_MODEL_DF_INDEX] * 2.2 &&
                in_place[DDYN_MODEL_DR_INDEX] == C[DDYN_MODEL_DR_INDEX] * 2.2 && in_place[0] == C[0]);
    /* the MPC: each stage of the linearisation is the generated step with the coefficients of its own speed */
    ring_mpc(30);
    assert_true(mpc.downforce == 0.0);
    assert_int_equal(ddyn_mpc_set_downforce(&mpc, 0.3), DDYN_OK);
    ring_start(x0);
    assert_int_equal(ddyn_mpc_solve(&mpc, x0, uc, &info), DDYN_OK);
    for (k = 0; k < mpc.cfg.horizon; ++k) {
        const double *xk = mpc.x_lin + k * DDYN_NX;
        ddyn_model_downforce(C, 0.3, xk[3], c_at);
        arg[0] = xk;
        arg[1] = mpc.u_lin + k * DDYN_NU;
        arg[2] = c_at;
        arg[3] = road;
        res[0] = out;
        res[1] = out + DDYN_NX;
        res[2] = out + DDYN_NX * 9;
        assert_int_equal(mpc.mpc_step(arg, res, work.iw, work.w, 0), 0);
        for (i = 0; i < DDYN_NX; ++i) {
            assert_true(out[i] == mpc.x_lin[(k + 1) * DDYN_NX + i]);
        }
        arg[2] = C; /* not blind: the plain coefficients give another stage */
        assert_int_equal(mpc.mpc_step(arg, res, work.iw, work.w, 0), 0);
        differs += fabs(out[5] - mpc.x_lin[(k + 1) * DDYN_NX + 5]) > 1e-6;
    }
    assert_int_equal(differs, mpc.cfg.horizon);
    /* refusals keep the value */
    assert_int_equal(ddyn_mpc_set_downforce(&mpc, -1e-9), DDYN_ERR_ARGUMENT);
    assert_int_equal(ddyn_mpc_set_downforce(&mpc, DDYN_MODEL_DOWNFORCE_MAX + 1e-9), DDYN_ERR_ARGUMENT);
    assert_int_equal(ddyn_mpc_set_downforce(&mpc, NAN), DDYN_ERR_ARGUMENT);
    assert_int_equal(ddyn_mpc_set_downforce(NULL, 0.1), DDYN_ERR_ARGUMENT);
    assert_true(mpc.downforce == 0.3);
    assert_int_equal(ddyn_mpc_set_downforce(&mpc, DDYN_MODEL_DOWNFORCE_MAX), DDYN_OK);
}

static void test_closed_loop_stays_on_the_ring(void **state)
{
    /* 2 s on the ring with the true coefficients: inside the room (0.15 m) all the way, every solve
     * converged, commands within the rate bounds, throttle and steering within theirs */
    static ddyn_model_work work;
    double x[DDYN_NX], u[DDYN_NU], xn[DDYN_NX], xp[(DDYN_MPC_MAX_HORIZON + 1) * DDYN_NX], last_x0[DDYN_NX];
    ddyn_mpc_info info;
    int k;
    (void)state;
    ring_mpc(30);
    ring_start(x);
    for (k = 0; k < 100; ++k) {
        memcpy(last_x0, x, sizeof x);
        assert_int_equal(ddyn_mpc_solve(&mpc, x, u, &info), DDYN_OK);
        assert_true(info.converged && info.qp_iterations >= 1 && info.qp_iterations <= 30);
        assert_true(u[0] >= -10.0 && u[0] <= 10.0 && u[1] >= -5.0 && u[1] <= 5.0);
        assert_int_equal(ddyn_model_step(&ddyn_model_orca_1_43, DDYN_DISC_RK4, x, u, C, xn, &work), DDYN_OK);
        memcpy(x, xn, sizeof x);
        assert_true(fabs(hypot(x[0], x[1]) - RADIUS) < 0.15);
        assert_true(x[6] >= -0.1 - 1e-9 && x[6] <= 1.0 + 1e-9 && fabs(x[7]) <= 0.35 + 1e-9);
    }
    assert_true(atan2(x[1], x[0]) > 0.5); /* it went round (about 2.4 m at 1.2 m/s), not stood still */
    assert_int_equal(ddyn_mpc_plan(&mpc, xp, NULL), 20);
    assert_memory_equal(xp, last_x0, sizeof last_x0); /* the plan starts at the last solve's x0 ... */
    assert_true(fabs(xp[DDYN_NX] - x[0]) < 1e-3 && fabs(xp[DDYN_NX + 1] - x[1]) < 1e-3); /* ... and predicts the plant */
    ddyn_mpc_reset(&mpc);
    assert_int_equal(ddyn_mpc_plan(&mpc, xp, NULL), 0);
}

static void test_held_throttle_plans_the_steering_alone(void **state)
{
    /* 2 s on the ring with the throttle set outside the MPC (a proportional law towards the throttle
     * that holds 1.2 m/s): the plan's throttle rates are the given one, then 0 (the throttle held over
     * the horizon); the QP's throttle block stays at zero; the steering keeps the car on the ring */
    static ddyn_model_work work;
    const double dt = ddyn_model_orca_1_43.sample_time, v = 1.2;
    const double t_hold = (C[14] + C[15] * v * v) / (C[12] - C[13] * v);
    double x[DDYN_NX], u[DDYN_NU], xn[DDYN_NX], xp[(DDYN_MPC_MAX_HORIZON + 1) * DDYN_NX], up[DDYN_MPC_NV];
    double speed, d0;
    ddyn_mpc_info info;
    int k, j;
    (void)state;
    ring_mpc(30);
    ring_start(x);
    assert_int_equal(ddyn_mpc_reference_speed(&mpc, x, 0.0, &speed), DDYN_OK);
    assert_true(speed == 1.2);
    for (k = 0; k < 100; ++k) {
        d0 = (t_hold - x[6]) / (2.0 * dt) + (k == 0 ? 30.0 : 0.0); /* the first beyond the rate bound */
        assert_int_equal(ddyn_mpc_solve_held_throttle(&mpc, x, d0, u, &info), DDYN_OK);
        assert_true(info.converged);
        assert_true(u[0] == (d0 > 10.0 ? 10.0 : (d0 < -10.0 ? -10.0 : d0))); /* clipped to the rate bounds */
        for (j = 0; j < 20; ++j) {
            assert_true(fabs(mpc.qp.z[2 * j]) < 1e-6); /* white box: the decoupled throttle block */
        }
        assert_int_equal(ddyn_mpc_plan(&mpc, xp, up), 20);
        assert_true(up[0] == u[0] && up[1] == u[1]);
        for (j = 1; j < 20; ++j) {
            assert_true(up[2 * j] == 0.0);
            assert_true(fabs(xp[(j + 1) * DDYN_NX + 6] - (x[6] + dt * u[0])) < 1e-12);
        }
        assert_int_equal(ddyn_model_step(&ddyn_model_orca_1_43, DDYN_DISC_RK4, x, u, C, xn, &work), DDYN_OK);
        memcpy(x, xn, sizeof x);
        assert_true(fabs(hypot(x[0], x[1]) - RADIUS) < 0.15);
        assert_true(fabs(x[7]) <= 0.35 + 1e-9);
    }
    assert_true(atan2(x[1], x[0]) > 0.5);
    assert_true(fabs(x[6] - t_hold) < 1e-3); /* the throttle is the one it was given */
    /* the MPC's own throttle again, from the same warm start */
    assert_int_equal(ddyn_mpc_solve(&mpc, x, u, &info), DDYN_OK);
    /* refusals */
    assert_int_equal(ddyn_mpc_solve_held_throttle(&mpc, x, NAN, u, &info), DDYN_ERR_NONFINITE_INPUT);
    assert_true(u[0] == 0.0 && u[1] == 0.0);
    assert_int_equal(ddyn_mpc_solve_held_throttle(NULL, x, 0.0, u, &info), DDYN_ERR_ARGUMENT);
    x[0] = NAN;
    assert_int_equal(ddyn_mpc_reference_speed(&mpc, x, 0.0, &speed), DDYN_ERR_NONFINITE_INPUT);
    assert_true(speed == 0.0);
    {
        ddyn_mpc_config cfg;
        assert_int_equal(ddyn_mpc_default_config(&ddyn_model_orca_1_43, &cfg), DDYN_OK);
        assert_int_equal(ddyn_mpc_init(&mpc, &ddyn_model_orca_1_43, &cfg), DDYN_OK);
        ring_start(x);
        assert_int_equal(ddyn_mpc_reference_speed(&mpc, x, 0.0, &speed), DDYN_ERR_NOT_READY);
    }
}

static void test_known_throttle_rates_fix_the_first_stages(void **state)
{
    /* issue 34, a throttle delay of 3 periods (ddyn_mpc_fix_throttle): 2 s on the ring with the plant's
     * throttle acting 3 periods after it is sent; each period the 3 rates still in the pipe are the
     * plan's first 3 throttle rates exactly, their QP columns stay at 0, the throttle sent is the plan's
     * stage 3, and the car stays on the ring. Also through prepare/feedback at a moved state, and the
     * refusals (the setting kept). n = 0 is the MPC as before. */
    static ddyn_model_work work;
    static ddyn_mpc before;
    static double sent[120];
    const double dt = ddyn_model_orca_1_43.sample_time;
    double x[DDYN_NX], u[DDYN_NU], u2[DDYN_NU], xn[DDYN_NX], xp[DDYN_NX], up[DDYN_MPC_NV], fixed[3];
    double bad[3] = {0.0, NAN, 0.0}, zmax = 0.0;
    ddyn_mpc_info info;
    int k, j;
    (void)state;
    ring_mpc(30);
    ring_start(x);
    /* n = 0: as before, bit for bit */
    before = mpc;
    assert_int_equal(ddyn_mpc_fix_throttle(&mpc, 0, NULL), DDYN_OK);
    assert_int_equal(ddyn_mpc_solve(&mpc, x, u, NULL), DDYN_OK);
    assert_int_equal(ddyn_mpc_solve(&before, x, u2, NULL), DDYN_OK);
    assert_memory_equal(u, u2, sizeof u);
    assert_memory_equal(mpc.u_plan, before.u_plan, sizeof mpc.u_plan);
    /* refusals: the previous setting kept */
    fixed[0] = fixed[1] = fixed[2] = 0.5;
    assert_int_equal(ddyn_mpc_fix_throttle(&mpc, 3, fixed), DDYN_OK);
    assert_int_equal(ddyn_mpc_fix_throttle(NULL, 1, fixed), DDYN_ERR_ARGUMENT);
    assert_int_equal(ddyn_mpc_fix_throttle(&mpc, -1, fixed), DDYN_ERR_ARGUMENT);
    assert_int_equal(ddyn_mpc_fix_throttle(&mpc, 20, fixed), DDYN_ERR_ARGUMENT); /* the whole horizon */
    assert_int_equal(ddyn_mpc_fix_throttle(&mpc, 2, NULL), DDYN_ERR_ARGUMENT);
    assert_int_equal(ddyn_mpc_fix_throttle(&mpc, 3, bad), DDYN_ERR_ARGUMENT);
    assert_int_equal(mpc.fix_n, 3);
    assert_true(mpc.fix_u[1] == 0.5);
    memset(sent, 0, sizeof sent);
    for (k = 0; k < 100; ++k) {
        double ua[DDYN_NU];
        for (j = 0; j < 3; ++j) {
            fixed[j] = k - 3 + j >= 0 ? sent[k - 3 + j] : 0.0; /* sent 3, 2, 1 periods ago */
        }
        assert_int_equal(ddyn_mpc_fix_throttle(&mpc, 3, fixed), DDYN_OK);
        assert_int_equal(ddyn_mpc_solve(&mpc, x, u, &info), DDYN_OK);
        assert_int_equal(ddyn_mpc_plan_inputs(&mpc, up), 20);
        for (j = 0; j < 3; ++j) {
            assert_true(up[2 * j] == fixed[j]);
            if (fabs(mpc.qp.z[2 * j]) > zmax) zmax = fabs(mpc.qp.z[2 * j]);
        }
        sent[k] = up[2 * 3]; /* the throttle sent now acts at stage 3 */
        assert_true(sent[k] >= -10.0 && sent[k] <= 10.0);
        ua[0] = k - 3 >= 0 ? sent[k - 3] : 0.0; /* the plant: the throttle sent 3 periods ago */
        ua[1] = u[1];
        assert_int_equal(ddyn_model_step(&ddyn_model_orca_1_43, DDYN_DISC_RK4, x, ua, C, xn, &work), DDYN_OK);
        memcpy(x, xn, sizeof x);
        assert_true(fabs(hypot(x[0], x[1]) - RADIUS) < 0.15);
    }
    assert_true(atan2(x[1], x[0]) > 0.5 || atan2(x[1], x[0]) < -0.5); /* it drove on */
    assert_true(fabs(x[3] - 1.2) < 0.15);                              /* near the reference speed */
    print_message("known throttle columns: largest QP deviation %g (the rate bounds: +-10)\n", zmax);
    assert_true(zmax < 1e-4); /* a throttle level 1e-4 * 3 dt off at most */
    /* prepared at a prediction, fed back at a moved state: the known stages stay the given ones */
    assert_int_equal(ddyn_model_step(&ddyn_model_orca_1_43, DDYN_DISC_RK4, x, u, C, xp, &work), DDYN_OK);
    assert_int_equal(ddyn_mpc_prepare(&mpc, xp), DDYN_OK);
    xp[0] += 0.003;
    xp[5] += 0.05;
    assert_int_equal(ddyn_mpc_feedback(&mpc, xp, u, &info), DDYN_OK);
    assert_int_equal(ddyn_mpc_plan_inputs(&mpc, up), 20);
    for (j = 0; j < 3; ++j) {
        assert_true(up[2 * j] == fixed[j]);
        assert_true(mpc.qp.grad[2 * j] == 0.0);
    }
    /* known rates that take the throttle below its bound (braking in the pipe), fed back at a moved state:
     * the known stages' integrator rows stay relaxed (the feedback's move once rewrote them, and the QP
     * then moved the known columns to meet the bound: the free throttle planned for another throttle) */
    fixed[0] = -1.0;
    fixed[1] = 0.0;
    fixed[2] = 0.0;
    xp[6] = -0.09; /* the known throttle: -0.11 after stage 1 (its bound -0.1), the stage-3 rate can lift it */
    assert_int_equal(ddyn_mpc_fix_throttle(&mpc, 3, fixed), DDYN_OK);
    assert_int_equal(ddyn_mpc_prepare(&mpc, xp), DDYN_OK);
    xp[0] += 0.002;
    xp[6] = -0.095;
    {
        ddyn_status fs = ddyn_mpc_feedback(&mpc, xp, u, &info);
        assert_true(fs == DDYN_OK || fs == DDYN_ERR_QP_NOT_CONVERGED);
    }
    assert_int_equal(ddyn_mpc_plan_inputs(&mpc, up), 20);
    for (j = 0; j < 3; ++j) {
        assert_true(up[2 * j] == fixed[j]);
        assert_true(mpc.qp.hard_lo[2 * j] == -1.1 * (j + 1) && mpc.qp.hard_hi[2 * j] == 1.1 * (j + 1));
        assert_true(fabs(mpc.qp.z[2 * j]) < 1e-4);
    }
    (void)dt;
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_default_config_takes_the_vehicle_files_limits),
        cmocka_unit_test(test_init_refuses_bad_configs),
        cmocka_unit_test(test_refusals_give_zero_command_and_keep_the_plan),
        cmocka_unit_test(test_track_table_is_checked),
        cmocka_unit_test(test_qp_box_solution_is_the_clipped_minimiser),
        cmocka_unit_test(test_qp_soft_row_penalty_is_exact),
        cmocka_unit_test(test_qp_integrator_rows_bound_the_prefix_sums),
        cmocka_unit_test(test_qp_newton_matrix_matches_the_dense_formula),
        cmocka_unit_test(test_qp_refuses_nonfinite_data),
        cmocka_unit_test(test_iteration_cap_reports_and_commands_within_bounds),
        cmocka_unit_test(test_generated_prediction_step_jacobians_and_integrators),
        cmocka_unit_test(test_closed_loop_stays_on_the_ring),
        cmocka_unit_test(test_daqp_solves_the_structured_qps),
        cmocka_unit_test(test_daqp_refusals_and_crossing_bounds_start_cold),
        cmocka_unit_test(test_interior_point_seeds_daqp_working_set),
        cmocka_unit_test(test_cold_start_beyond_daqp_cap_converges_in_its_period),
        cmocka_unit_test(test_daqp_warm_start_shifts_and_the_cap_is_defined),
        cmocka_unit_test(test_held_throttle_plans_the_steering_alone),
        cmocka_unit_test(test_known_throttle_rates_fix_the_first_stages),
        cmocka_unit_test(test_reference_speed_reads_ahead_along_the_line),
        cmocka_unit_test(test_cost_points_run_no_faster_than_the_car_can_reach),
        cmocka_unit_test(test_bank_gravity_term_matches_the_python_model),
        cmocka_unit_test(test_bank_table_lookup_and_refusals),
        cmocka_unit_test(test_grade_gravity_term_matches_the_python_model),
        cmocka_unit_test(test_grade_table_lookup_and_refusals),
        cmocka_unit_test(test_downforce_matches_the_python_model_and_each_stage_uses_its_speed),
        cmocka_unit_test(test_plan_inputs_need_no_simulation),
        cmocka_unit_test(test_prepare_then_feedback_is_the_real_time_iteration),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
