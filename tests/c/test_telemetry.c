/*
 * test_telemetry: the LCM telemetry module publishes what it is given, when its rate
 * limiter says so, and keeps its per-step counters across the steps it does not send.
 * Messages go over LCM's in-process memq:// provider to a subscriber here, which decodes
 * them with the lcm-gen C code; nothing touches the network.
 */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include <cmocka.h>
#include <lcm/lcm.h>

#include "ddyn/telemetry.h"
#include "ddyn_lcm_faults_t.h"
#include "ddyn_lcm_guard_coeffs_t.h"
#include "ddyn_lcm_loop_timing_t.h"
#include "ddyn_lcm_mpc_plan_t.h"
#include "ddyn_lcm_state_estimate_t.h"

#define MAX_RECEIVED 64

typedef struct {
    char channel[DDYN_TM_CHANNEL_MAX];
    uint8_t data[DDYN_TM_BUFFER_SIZE];
    int size;
} received_msg;

static received_msg received[MAX_RECEIVED];
static int n_received;

static void on_message(const lcm_recv_buf_t *rbuf, const char *channel, void *user)
{
    (void)user;
    assert_true(n_received < MAX_RECEIVED);
    assert_true(rbuf->data_size <= DDYN_TM_BUFFER_SIZE);
    strncpy(received[n_received].channel, channel, DDYN_TM_CHANNEL_MAX - 1);
    memcpy(received[n_received].data, rbuf->data, rbuf->data_size);
    received[n_received].size = (int)rbuf->data_size;
    ++n_received;
}

typedef struct {
    lcm_t *lcm;
    ddyn_telemetry tm;
} fixture;

static fixture fx;

/* deliver everything queued on the memq provider */
static void drain(void)
{
    int guard;
    for (guard = 0; guard < 10 * MAX_RECEIVED; ++guard) {
        if (lcm_handle_timeout(fx.lcm, 0) <= 0) {
            return;
        }
    }
    fail_msg("memq never ran dry");
}

static void open_with(ddyn_telemetry_config *cfg)
{
    n_received = 0;
    fx.lcm = lcm_create("memq://");
    assert_non_null(fx.lcm);
    lcm_subscribe(fx.lcm, "DDYN_.*", on_message, NULL);
    cfg->lcm = fx.lcm;
    assert_int_equal(ddyn_telemetry_open(&fx.tm, cfg), DDYN_TM_PUBLISHED);
}

static int teardown(void **state)
{
    (void)state;
    ddyn_telemetry_close(&fx.tm);
    if (fx.lcm != NULL) {
        lcm_destroy(fx.lcm);
        fx.lcm = NULL;
    }
    return 0;
}

static void test_state_round_trip(void **state)
{
    ddyn_telemetry_config cfg;
    ddyn_tm_state s;
    ddyn_lcm_state_estimate_t m;
    int i;
    (void)state;
    ddyn_telemetry_default_config(&cfg, 50.0);
    open_with(&cfg);
    s.utime = 1234567;
    s.step = 42;
    for (i = 0; i < DDYN_NX; ++i) {
        s.x[i] = 0.1 * (i + 1) - 0.35;
        s.cov_diag[i] = 1e-3 * (i + 1);
    }
    assert_int_equal(ddyn_telemetry_publish_state(&fx.tm, &s), DDYN_TM_PUBLISHED);
    drain();
    assert_int_equal(n_received, 1);
    assert_string_equal(received[0].channel, "DDYN_STATE");
    assert_int_equal(ddyn_lcm_state_estimate_t_decode(received[0].data, 0, received[0].size, &m), received[0].size);
    assert_int_equal(m.utime, 1234567);
    assert_int_equal(m.step, 42);
    assert_true(m.x == s.x[0] && m.y == s.x[1] && m.yaw == s.x[2] && m.vx == s.x[3]);
    assert_true(m.vy == s.x[4] && m.omega == s.x[5] && m.throttle == s.x[6] && m.steering == s.x[7]);
    assert_memory_equal(m.cov_diag, s.cov_diag, sizeof m.cov_diag);
    ddyn_lcm_state_estimate_t_decode_cleanup(&m);
}

static void test_rate_limiter_decimates_by_steps(void **state)
{
    ddyn_telemetry_config cfg;
    ddyn_tm_coeffs c;
    ddyn_tm_state s;
    ddyn_tm_faults f;
    int step, sent_coeffs = 0;
    (void)state;
    ddyn_telemetry_default_config(&cfg, 50.0);
    cfg.rate_hz[DDYN_TM_COEFFS] = 10.0; /* every 5th step */
    cfg.rate_hz[DDYN_TM_STATE] = 1e6;   /* above the control rate: every step */
    cfg.rate_hz[DDYN_TM_FAULTS] = 0.0;  /* never */
    open_with(&cfg);
    memset(&c, 0, sizeof c);
    memset(&s, 0, sizeof s);
    memset(&f, 0, sizeof f);
    for (step = 100; step < 120; ++step) {
        ddyn_tm_status st;
        /* the clock jitters; the limiter counts steps and does not care */
        c.utime = s.utime = f.utime = (int64_t)step * 20000 + ((step % 3) - 1) * 900;
        c.step = s.step = f.step = step;
        st = ddyn_telemetry_publish_coeffs(&fx.tm, &c);
        assert_int_equal(st, (step - 100) % 5 == 0 ? DDYN_TM_PUBLISHED : DDYN_TM_SKIPPED);
        sent_coeffs += st == DDYN_TM_PUBLISHED;
        assert_int_equal(ddyn_telemetry_publish_state(&fx.tm, &s), DDYN_TM_PUBLISHED);
        assert_int_equal(ddyn_telemetry_publish_faults(&fx.tm, &f), DDYN_TM_SKIPPED);
    }
    assert_int_equal(sent_coeffs, 4);
    assert_int_equal(fx.tm.limiter[DDYN_TM_COEFFS].published, 4);
    assert_int_equal(fx.tm.limiter[DDYN_TM_COEFFS].skipped, 16);
    assert_int_equal(fx.tm.limiter[DDYN_TM_STATE].published, 20);
    assert_int_equal(fx.tm.limiter[DDYN_TM_FAULTS].published, 0);
    /* a step number that goes backwards (controller restarted) is sent at once */
    c.step = 3;
    assert_int_equal(ddyn_telemetry_publish_coeffs(&fx.tm, &c), DDYN_TM_PUBLISHED);
    c.step = 4;
    assert_int_equal(ddyn_telemetry_publish_coeffs(&fx.tm, &c), DDYN_TM_SKIPPED);
    drain();
    assert_int_equal(n_received, 4 + 20 + 1);
}

static void test_coefficients_and_saturation_flags(void **state)
{
    static const double lo_base = 1.0, hi_base = 3.0; /* range 2: the 2 % band is 0.04 */
    double lo[DDYN_NC], hi[DDYN_NC];
    ddyn_telemetry_config cfg;
    ddyn_tm_coeffs c;
    ddyn_lcm_guard_coeffs_t m;
    int i;
    (void)state;
    for (i = 0; i < DDYN_NC; ++i) {
        lo[i] = lo_base + i;
        hi[i] = hi_base + i;
        c.coeffs[i] = 0.5 * (lo[i] + hi[i]);
    }
    c.coeffs[0] = lo[0] + 0.03;  /* inside the lower band */
    c.coeffs[1] = lo[1] + 0.05;  /* just outside it */
    c.coeffs[5] = hi[5] - 0.001; /* inside the upper band */
    c.coeffs[16] = hi[16];       /* pinned at the bound */
    c.coeffs[9] = NAN;           /* sent as it is, never flagged */
    c.utime = 7;
    c.step = 1;
    ddyn_telemetry_default_config(&cfg, 25.0);
    cfg.coeff_lo = lo;
    cfg.coeff_hi = hi;
    open_with(&cfg);
    assert_int_equal(ddyn_telemetry_publish_coeffs(&fx.tm, &c), DDYN_TM_PUBLISHED);
    drain();
    assert_int_equal(n_received, 1);
    assert_string_equal(received[0].channel, "DDYN_COEFFS");
    assert_true(ddyn_lcm_guard_coeffs_t_decode(received[0].data, 0, received[0].size, &m) > 0);
    assert_int_equal(m.saturated_lo, 1 << 0);
    assert_int_equal(m.saturated_hi, (1 << 5) | (1 << 16));
    assert_true(m.margin == DDYN_TM_DEFAULT_SAT_MARGIN);
    assert_memory_equal(m.lo, lo, sizeof lo);
    assert_memory_equal(m.hi, hi, sizeof hi);
    assert_true(isnan(m.coeffs[9]));
    for (i = 0; i < DDYN_NC; ++i) {
        if (i != 9) {
            assert_true(m.coeffs[i] == c.coeffs[i]);
        }
    }
    ddyn_lcm_guard_coeffs_t_decode_cleanup(&m);
}

static void test_plan_round_trip_and_horizon_limit(void **state)
{
    enum { N = 3 };
    double states[(N + 1) * DDYN_NX], inputs[N * DDYN_NU];
    ddyn_telemetry_config cfg;
    ddyn_tm_plan p;
    ddyn_lcm_mpc_plan_t m;
    int k, i;
    (void)state;
    for (k = 0; k < (N + 1) * DDYN_NX; ++k) {
        states[k] = 0.25 * k;
    }
    for (k = 0; k < N * DDYN_NU; ++k) {
        inputs[k] = -0.5 * k;
    }
    ddyn_telemetry_default_config(&cfg, 50.0);
    cfg.rate_hz[DDYN_TM_PLAN] = 50.0;
    open_with(&cfg);
    p.utime = 99;
    p.step = 5;
    p.status = 2;
    p.status_name = "max_iterations";
    p.qp_iterations = 17;
    p.cost = 12.5;
    p.horizon = N;
    p.states = states;
    p.inputs = inputs;
    assert_int_equal(ddyn_telemetry_publish_plan(&fx.tm, &p), DDYN_TM_PUBLISHED);
    drain();
    assert_int_equal(n_received, 1);
    assert_true(ddyn_lcm_mpc_plan_t_decode(received[0].data, 0, received[0].size, &m) > 0);
    assert_string_equal(m.status_name, "max_iterations");
    assert_int_equal(m.status, 2);
    assert_int_equal(m.qp_iterations, 17);
    assert_true(m.cost == 12.5);
    assert_int_equal(m.horizon, N);
    assert_int_equal(m.n_states, N + 1);
    for (k = 0; k <= N; ++k) {
        for (i = 0; i < DDYN_NX; ++i) {
            assert_true(m.states[k][i] == states[k * DDYN_NX + i]);
        }
    }
    for (k = 0; k < N; ++k) {
        for (i = 0; i < DDYN_NU; ++i) {
            assert_true(m.inputs[k][i] == inputs[k * DDYN_NU + i]);
        }
    }
    ddyn_lcm_mpc_plan_t_decode_cleanup(&m);
    p.horizon = DDYN_TM_PLAN_MAX_HORIZON + 1;
    p.step = 6;
    assert_int_equal(ddyn_telemetry_publish_plan(&fx.tm, &p), DDYN_TM_ERR_ARGUMENT);
}

static void test_plan_at_longest_horizon_fits_the_buffer(void **state)
{
    static double states[(DDYN_TM_PLAN_MAX_HORIZON + 1) * DDYN_NX], inputs[DDYN_TM_PLAN_MAX_HORIZON * DDYN_NU];
    static const char name[] = "a_status_name_of_sixty_three_characters_xxxxxxxxxxxxxxxxxxxxxxx";
    static char too_long[400];
    ddyn_telemetry_config cfg;
    ddyn_tm_plan p;
    (void)state;
    assert_int_equal(sizeof name - 1, 63);
    ddyn_telemetry_default_config(&cfg, 50.0);
    open_with(&cfg);
    memset(&p, 0, sizeof p);
    p.status_name = name;
    p.horizon = DDYN_TM_PLAN_MAX_HORIZON;
    p.states = states;
    p.inputs = inputs;
    assert_int_equal(ddyn_telemetry_publish_plan(&fx.tm, &p), DDYN_TM_PUBLISHED);
    drain();
    assert_int_equal(n_received, 1);
    /* a name far beyond any status name does not fit: refused, counted, nothing sent */
    memset(too_long, 'x', sizeof too_long - 1);
    p.status_name = too_long;
    p.step = 1000;
    assert_int_equal(ddyn_telemetry_publish_plan(&fx.tm, &p), DDYN_TM_ERR_ENCODE);
    assert_int_equal(fx.tm.limiter[DDYN_TM_PLAN].errors, 1);
    drain();
    assert_int_equal(n_received, 1);
}

static void test_timing_counts_every_step(void **state)
{
    ddyn_telemetry_config cfg;
    ddyn_tm_timing t;
    ddyn_lcm_loop_timing_t m;
    int step;
    (void)state;
    ddyn_telemetry_default_config(&cfg, 50.0);
    cfg.rate_hz[DDYN_TM_TIMING] = 5.0; /* every 10th step */
    open_with(&cfg);
    memset(&t, 0, sizeof t);
    t.deadline_s = 0.02;
    t.period_s = 0.02;
    t.n_stages = 3;
    t.stage_names[0] = "ekf";
    t.stage_names[1] = "guard_net";
    t.stage_names[2] = "mpc";
    for (step = 0; step <= 10; ++step) {
        t.step = step;
        t.utime = step * 20000;
        /* steps 3 and 7 miss the deadline; neither is published */
        t.total_s = (step == 3) ? 0.031 : (step == 7) ? 0.025 : 0.01;
        t.stage_s[0] = 0.001;
        t.stage_s[1] = 0.002;
        t.stage_s[2] = t.total_s - 0.003;
        assert_int_equal(ddyn_telemetry_publish_timing(&fx.tm, &t),
                         (step % 10 == 0) ? DDYN_TM_PUBLISHED : DDYN_TM_SKIPPED);
    }
    drain();
    assert_int_equal(n_received, 2);
    assert_true(ddyn_lcm_loop_timing_t_decode(received[1].data, 0, received[1].size, &m) > 0);
    assert_int_equal(m.step, 10);
    assert_int_equal(m.deadline_missed, 0);
    assert_int_equal(m.deadline_misses, 2);
    assert_true(m.max_total_s == 0.031);
    assert_int_equal(m.n_stages, 3);
    assert_string_equal(m.stage_names[1], "guard_net");
    assert_true(m.stage_s[2] == 0.01 - 0.003);
    ddyn_lcm_loop_timing_t_decode_cleanup(&m);
}

static void test_fault_onsets_and_active_steps(void **state)
{
    static const uint32_t flags[8] = {0u, 1u, 1u, 0u, 1u | 4u, 4u, 0x80000000u, 0u};
    ddyn_telemetry_config cfg;
    ddyn_tm_faults f;
    ddyn_lcm_faults_t m;
    int step;
    (void)state;
    ddyn_telemetry_default_config(&cfg, 50.0);
    cfg.rate_hz[DDYN_TM_FAULTS] = 50.0 / 8.0; /* only step 0 and the step after the last */
    open_with(&cfg);
    for (step = 0; step <= 8; ++step) {
        f.step = step;
        f.utime = step;
        f.active = step < 8 ? flags[step] : 2u;
        (void)ddyn_telemetry_publish_faults(&fx.tm, &f);
    }
    drain();
    assert_int_equal(n_received, 2);
    assert_true(ddyn_lcm_faults_t_decode(received[1].data, 0, received[1].size, &m) > 0);
    assert_int_equal(m.active, 2);
    assert_int_equal((uint32_t)m.latched, 1u | 2u | 4u | 0x80000000u);
    assert_int_equal(m.onsets[0], 2);        /* steps 1 and 4 */
    assert_int_equal(m.active_steps[0], 3);  /* steps 1, 2, 4 */
    assert_int_equal(m.onsets[2], 1);
    assert_int_equal(m.active_steps[2], 2);
    assert_int_equal(m.onsets[31], 1);
    assert_int_equal(m.onsets[1], 1);
    ddyn_lcm_faults_t_decode_cleanup(&m);
}

static void test_bad_configuration_is_refused(void **state)
{
    ddyn_telemetry_config cfg;
    ddyn_telemetry tm;
    double lo[DDYN_NC] = {0};
    (void)state;
    ddyn_telemetry_default_config(&cfg, 0.0);
    assert_int_equal(ddyn_telemetry_open(&tm, &cfg), DDYN_TM_ERR_ARGUMENT);
    ddyn_telemetry_default_config(&cfg, 50.0);
    cfg.coeff_lo = lo; /* bounds need both sides */
    assert_int_equal(ddyn_telemetry_open(&tm, &cfg), DDYN_TM_ERR_ARGUMENT);
    ddyn_telemetry_default_config(&cfg, 50.0);
    cfg.channel_prefix = "A_PREFIX_FAR_TOO_LONG_FOR_A_CHANNEL_NAME_OF_SIXTY_FOUR_CHARACTERS_";
    assert_int_equal(ddyn_telemetry_open(&tm, &cfg), DDYN_TM_ERR_ARGUMENT);
    ddyn_telemetry_default_config(&cfg, 50.0);
    cfg.url = "nosuchprovider://";
    assert_int_equal(ddyn_telemetry_open(&tm, &cfg), DDYN_TM_ERR_LCM);
    assert_int_equal(ddyn_telemetry_publish_state(NULL, NULL), DDYN_TM_ERR_ARGUMENT);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test_teardown(test_state_round_trip, teardown),
        cmocka_unit_test_teardown(test_rate_limiter_decimates_by_steps, teardown),
        cmocka_unit_test_teardown(test_coefficients_and_saturation_flags, teardown),
        cmocka_unit_test_teardown(test_plan_round_trip_and_horizon_limit, teardown),
        cmocka_unit_test_teardown(test_plan_at_longest_horizon_fits_the_buffer, teardown),
        cmocka_unit_test_teardown(test_timing_counts_every_step, teardown),
        cmocka_unit_test_teardown(test_fault_onsets_and_active_steps, teardown),
        cmocka_unit_test(test_bad_configuration_is_refused),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
