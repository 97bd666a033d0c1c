/*
 * ddyn_bench: timing of the runtime's real-time functions (host tool; `ddyn bench runtime` drives it).
 *
 * usage: ddyn_bench N < histories     N calls of each function; prints one line per function:
 *        "NAME n median_us p99_us max_us"
 * Inference runs on the histories read from stdin (tau*7 numbers per line, cycled); the EKF
 * step is a predict plus the sensor updates of a 50 Hz cycle (gyro, accelerometer, wheel
 * speeds, steering; GNSS and heading every 5th call) on the 1:43 model.
 */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "bench_timing.h"
#include "ddyn_net_config.h"
#include "ddyn/ekf.h"
#include "ddyn/guard_net.h"
#include "ddyn_models.h"

#define MAX_CALLS 200000
#define MAX_HISTORIES 20000

extern const ddyn_net_tables ddyn_net_weights;

static double samples[MAX_CALLS];
static double histories[MAX_HISTORIES][DDYN_NET_TAU][DDYN_NET_NFEAT];


static void report(const char *name, int n)
{
    bench_stats s = bench_stats_of(samples, n);
    printf("%s %d %.3f %.3f %.3f\n", name, n, s.median, s.p99, s.max);
}

int main(int argc, char **argv)
{
    static ddyn_guard_net net;
    static ddyn_ekf ekf;
    static char line[1 << 14];
    static const double c[DDYN_NC] = {5.579, 1.2, 0.192, -0.083, -0.0013, 0.00043, 5.3852, 1.2691, 0.1737,
                                      -0.019, -0.00376, 0.00091, 0.287, 0.0545, 0.0518, 0.00035, 2.78e-5};
    static const double x0[DDYN_NX] = {0.0, 0.0, 0.0, 1.5, 0.0, 0.0, 0.2, 0.0};
    static const double p0[DDYN_NX] = {1e-4, 1e-4, 1e-4, 1e-3, 1e-4, 1e-2, 1e-8, 1e-8};
    static const double q[DDYN_NX] = {1e-8, 1e-8, 1e-8, 1e-6, 1e-6, 1e-4, 1e-12, 1e-12};
    int n = argc > 1 ? atoi(argv[1]) : 10000, n_hist = 0, i;
    double sink = 0.0;
    if (argc == 2 && strcmp(argv[1], "--checkpoint-hash") == 0) {
        /* the network this tool was built for: `ddyn bench` refuses to time another checkpoint's */
        printf("%s\n", DDYN_NET_CHECKPOINT_SHA256);
        return 0;
    }
    if (n < 1 || n > MAX_CALLS) {
        fprintf(stderr, "ddyn_bench: N must be in 1..%d\n", MAX_CALLS);
        return 2;
    }
    while (n_hist < MAX_HISTORIES && fgets(line, sizeof line, stdin) != NULL) {
        char *p = line, *end = NULL;
        for (i = 0; i < DDYN_NET_TAU * DDYN_NET_NFEAT; ++i, p = end) {
            histories[n_hist][i / DDYN_NET_NFEAT][i % DDYN_NET_NFEAT] = strtod(p, &end);
        }
        ++n_hist;
    }
    if (n_hist == 0 || ddyn_guard_net_init(&net, &ddyn_net_weights) != DDYN_NET_OK) {
        fprintf(stderr, "ddyn_bench: no histories on stdin, or tables refused\n");
        return 1;
    }
    for (i = 0; i < n; ++i) {
        double coeffs[DDYN_NET_NOUT], t0 = bench_now_us();
        ddyn_guard_net_infer(&net, (const double(*)[DDYN_NET_NFEAT])histories[i % n_hist], coeffs);
        samples[i] = bench_now_us() - t0;
        sink += coeffs[0];
    }
    report("guard_net_infer", n);
    ddyn_ekf_init(&ekf, &ddyn_model_orca_1_43, DDYN_DISC_EULER, x0, p0, q);
    for (i = 0; i < n; ++i) {
        static const double u[DDYN_NU] = {0.0, 0.01};
        double z1[1] = {0.1}, r1[1] = {2.5e-3}, z2[2] = {0.0, 0.0}, r2[2] = {0.04, 0.04};
        double t0 = bench_now_us();
        ddyn_ekf_predict(&ekf, u, c);
        ddyn_ekf_update(&ekf, DDYN_MEAS_YAW_RATE, z1, r1, c, NULL);
        z2[0] = ekf.x[3];
        z2[1] = ekf.x[3];
        ddyn_ekf_update(&ekf, DDYN_MEAS_WHEEL_SPEED, z2, r2, c, NULL);
        ddyn_ekf_update(&ekf, DDYN_MEAS_ACCELERATION, z2, r2, c, NULL);
        z1[0] = ekf.x[7];
        ddyn_ekf_update(&ekf, DDYN_MEAS_STEERING, z1, r1, c, NULL);
        if (i % 5 == 0) {
            z2[0] = ekf.x[0];
            z2[1] = ekf.x[1];
            ddyn_ekf_update(&ekf, DDYN_MEAS_GNSS_POSITION, z2, r2, c, NULL);
        }
        samples[i] = bench_now_us() - t0;
        if (i % 500 == 499) { /* keep the filter in its operating range over long runs */
            ddyn_ekf_init(&ekf, &ddyn_model_orca_1_43, DDYN_DISC_EULER, x0, p0, q);
        }
    }
    report("ekf_step", n);
    fprintf(stderr, "(checksum %g)\n", sink);
    return 0;
}
