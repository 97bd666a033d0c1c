/*
 * ddyn_controller_bench: closed-loop timing of the whole controller step (host tool;
 * train/bench/controller.py writes its input and reads its output).
 *
 * usage: ddyn_controller_bench STEPS SEED < setup
 *
 * The plant is the generated model step (RK4) with the vehicle's true coefficients; the sensors
 * are the generated sensor models of the true state plus Gaussian noise, each at its own period;
 * the controller (EKF -> history -> guard network -> MPC, c_src/src/controller.c) closes the
 * loop. Only ddyn_ctrl_step is timed. setup (whitespace-separated numbers, in this order):
 *   vehicle name
 *   17 true coefficients (the plant), 17 nominal coefficients (the controller's fallback)
 *   8 initial states, 8 process noise variances of the filter (per period)
 *   per sensor kind (ddyn_meas_kind order): period in control periods (0 = never), noise std of
 *   the simulated reading, std the filter assumes (its R: noise plus model error)
 *   n, then n raceline rows: x y speed width_left width_right
 * With DDYN_BENCH_PREPARE=1 in the environment, ddyn_ctrl_prepare runs (timed on its own, line
 * "controller_prepare") after each step, so that "controller_step" is the feedback latency: from the
 * readings to the command with the MPC's preparation done beforehand.
 * Output: "controller_step n median_us p99_us max_us", the same for "mpc_solve" (the step's MPC
 * solve repeated alone on a copy of the MPC context: the MPC's share of the step), then
 * "# key value" lines: steps with each status bit, rejected readings per sensor, laps driven,
 * largest distance of the true position from the raceline.
 */
#define _POSIX_C_SOURCE 199309L
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "bench_timing.h"
#include "ddyn_net_config.h"
#include "ddyn/controller.h"

#define MAX_STEPS 1000000

extern const ddyn_net_tables ddyn_net_weights;

static double samples[MAX_STEPS];
static double mpc_samples[MAX_STEPS];
static double prepare_samples[MAX_STEPS];
static ddyn_ctrl ctl;
static ddyn_mpc mpc_replay; /* the step's MPC solve once more, timed alone */
static double track[5][DDYN_MPC_MAX_TRACK_POINTS];


static void report(const char *name, double *v, int n)
{
    double sum = 0.0;
    int i, over = 0;
    for (i = 0; i < n; ++i) {
        sum += v[i];
        over += v[i] > 1000.0;
    }
    printf("# %s_over_1ms %d\n", name, over);
    bench_stats s = bench_stats_of(v, n);
    printf("%s %d %.3f %.3f %.3f\n", name, n, s.median, s.p99, s.max);
    printf("# %s_mean_us %.3f\n", name, sum / n);
}

/* xorshift64* and Box-Muller: reproducible noise without libc's rand state */
static uint64_t rng_state = 88172645463325252ull;
static double uniform01(void)
{
    rng_state ^= rng_state >> 12;
    rng_state ^= rng_state << 25;
    rng_state ^= rng_state >> 27;
    return ((double)((rng_state * 2685821657736338717ull) >> 11) + 0.5) / 9007199254740992.0;
}
static double gaussian(void)
{
    return sqrt(-2.0 * log(uniform01())) * cos(6.283185307179586 * uniform01());
}

static int read_doubles(double *v, int n)
{
    int i;
    for (i = 0; i < n; ++i) {
        if (scanf("%lf", &v[i]) != 1) {
            return 0;
        }
    }
    return 1;
}

/* distance from (x, y) to the closed polyline of the raceline */
static double raceline_distance(int n, double x, double y)
{
    double best = INFINITY;
    int i;
    for (i = 0; i < n; ++i) {
        int j = (i + 1) % n;
        double dx = track[0][j] - track[0][i], dy = track[1][j] - track[1][i];
        double t = ((x - track[0][i]) * dx + (y - track[1][i]) * dy) / (dx * dx + dy * dy);
        double px, py;
        t = t < 0.0 ? 0.0 : (t > 1.0 ? 1.0 : t);
        px = track[0][i] + t * dx - x;
        py = track[1][i] + t * dy - y;
        best = fmin(best, sqrt(px * px + py * py));
    }
    return best;
}

int main(int argc, char **argv)
{
    static const int dims[DDYN_MEAS_COUNT] = DDYN_MEAS_DIMS;
    char name[64];
    double c_true[DDYN_NC], c_nominal[DDYN_NC], x[DDYN_NX], q[DDYN_NX], period_noise[3 * DDYN_MEAS_COUNT];
    long bit_count[DDYN_CTRL_STATUS_BITS] = {0};
    const ddyn_vehicle_model *model;
    ddyn_ctrl_config cfg;
    ddyn_model_work work;
    int steps = argc > 1 ? atoi(argv[1]) : 10000, n_track = 0, i, k, b;
    const char *prepare_env = getenv("DDYN_BENCH_PREPARE");
    const int prepare_mode = prepare_env != NULL && strcmp(prepare_env, "1") == 0;
    double max_offset = 0.0, progress0 = 0.0, progress_prev = 0.0, distance = 0.0;
    if (argc == 2 && strcmp(argv[1], "--checkpoint-hash") == 0) {
        /* the network this tool was built for: `ddyn bench` refuses to time another checkpoint's */
        printf("%s\n", DDYN_NET_CHECKPOINT_SHA256);
        return 0;
    }
    if (argc > 2) {
        rng_state ^= (uint64_t)strtoull(argv[2], NULL, 10) * 0x9E3779B97F4A7C15ull;
    }
    if (steps < 1 || steps > MAX_STEPS) {
        fprintf(stderr, "ddyn_controller_bench: STEPS must be in 1..%d\n", MAX_STEPS);
        return 2;
    }
    if (scanf("%63s", name) != 1 || (model = ddyn_model_find(name)) == NULL || !read_doubles(c_true, DDYN_NC) ||
        !read_doubles(c_nominal, DDYN_NC) || !read_doubles(x, DDYN_NX) || !read_doubles(q, DDYN_NX) ||
        !read_doubles(period_noise, 3 * DDYN_MEAS_COUNT) || scanf("%d", &n_track) != 1 || n_track < 4 ||
        n_track > DDYN_MPC_MAX_TRACK_POINTS) {
        fprintf(stderr, "ddyn_controller_bench: malformed setup on stdin (see the tool's header comment)\n");
        return 2;
    }
    for (i = 0; i < n_track; ++i) {
        for (k = 0; k < 5; ++k) {
            if (scanf("%lf", &track[k][i]) != 1) {
                fprintf(stderr, "ddyn_controller_bench: raceline row %d malformed\n", i);
                return 2;
            }
        }
    }
    ddyn_ctrl_default_config(model, &cfg);
    memcpy(cfg.c_nominal, c_nominal, sizeof c_nominal);
    memcpy(cfg.q_diag, q, sizeof q);
    for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
        double sd = period_noise[3 * k + 2];
        for (i = 0; i < DDYN_MEAS_MAX_DIM; ++i) {
            cfg.r_diag[k][i] = sd > 0.0 ? sd * sd : 1e-8;
        }
    }
    if (ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, x) != DDYN_OK ||
        ddyn_ctrl_set_track(&ctl, n_track, track[0], track[1], track[2], track[3], track[4]) != DDYN_OK) {
        fprintf(stderr, "ddyn_controller_bench: controller refused the setup (network built for another export?)\n");
        return 1;
    }
    for (i = 0; i < steps; ++i) {
        ddyn_ctrl_input in;
        ddyn_ctrl_output out;
        double t0, x_next[DDYN_NX];
        memset(&in, 0, sizeof in);
        for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
            int period = (int)period_noise[3 * k];
            double h[DDYN_MEAS_MAX_DIM], H[DDYN_MEAS_MAX_DIM * DDYN_NX];
            if (period > 0 && i % period == 0 &&
                ddyn_model_measure(model, (ddyn_meas_kind)k, x, c_true, h, H, &work) == DDYN_OK) {
                int d;
                in.reading[k].valid = 1;
                for (d = 0; d < dims[k]; ++d) {
                    in.reading[k].z[d] = h[d] + period_noise[3 * k + 1] * gaussian();
                }
            }
        }
        memcpy(&mpc_replay, &ctl.mpc, sizeof mpc_replay); /* the MPC as the step will find it */
        mpc_replay.prepared = 0;                             /* ... timed as the whole iteration */
        t0 = bench_now_us();
        ddyn_ctrl_step(&ctl, &in, &out);
        samples[i] = bench_now_us() - t0;
        {
            /* the same solve (same warm start, coefficients, state) timed on its own: the share
             * of the step that is the MPC's */
            double u_replay[DDYN_NU];
            ddyn_mpc_set_coefficients(&mpc_replay, out.coeffs);
            t0 = bench_now_us();
            ddyn_mpc_solve(&mpc_replay, out.x_est, u_replay, NULL);
            mpc_samples[i] = bench_now_us() - t0;
        }
        if (prepare_mode) {
            t0 = bench_now_us();
            (void)ddyn_ctrl_prepare(&ctl); /* after the command is out, before the next readings */
            prepare_samples[i] = bench_now_us() - t0;
        }
        for (b = 0; b < DDYN_CTRL_STATUS_BITS; ++b) {
            bit_count[b] += (out.status >> b) & 1u;
        }
        if (i == 0) {
            progress0 = progress_prev = out.mpc_info.progress;
        } else if (out.mpc_status == DDYN_OK || out.mpc_status == DDYN_ERR_QP_NOT_CONVERGED) {
            double ds = out.mpc_info.progress - progress_prev;
            double len = ctl.mpc.track.length;
            ds -= len * floor(ds / len + 0.5); /* across the start line */
            distance += ds;
            progress_prev = out.mpc_info.progress;
        }
        if (ddyn_model_step(model, DDYN_DISC_RK4, x, out.u, c_true, x_next, &work) != DDYN_OK) {
            fprintf(stderr, "ddyn_controller_bench: plant step failed at step %d\n", i);
            return 1;
        }
        memcpy(x, x_next, sizeof x);
        max_offset = fmax(max_offset, raceline_distance(n_track, x[0], x[1]));
    }
    report("controller_step", samples, steps);
    report("mpc_solve", mpc_samples, steps);
    if (prepare_mode) {
        report("controller_prepare", prepare_samples, steps);
    }
    for (b = 0; b < DDYN_CTRL_STATUS_BITS; ++b) {
        printf("# steps_%s %ld\n", ddyn_ctrl_status_name((ddyn_ctrl_status)1u << b), bit_count[b]);
    }
    for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
        static const char *const names[DDYN_MEAS_COUNT] = DDYN_MEAS_NAMES;
        printf("# rejected_%s %lu\n", names[k], (unsigned long)ctl.rejected_count[k]);
        printf("# nonfinite_%s %lu\n", names[k], (unsigned long)ctl.nonfinite_count[k]);
    }
    printf("# laps %.3f\n", distance / ctl.mpc.track.length);
    printf("# max_raceline_offset_m %.4f\n", max_offset);
    printf("# start_progress_m %.4f\n", progress0);
    return 0;
}
