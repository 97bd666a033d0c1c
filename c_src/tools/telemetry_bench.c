/*
 * ddyn_telemetry_bench: what a telemetry call costs the control loop, per message kind.
 *
 * usage: ddyn_telemetry_bench [-u URL] [-n CALLS]
 *   URL default "file:///dev/null?mode=w" (encode + the file provider's write); try
 *   "udpm://239.255.76.67:7667?ttl=0" for the network path.
 * For each kind it times CALLS calls that publish (rate = control rate) and CALLS calls the
 * rate limiter holds back (rate 0, the cost a decimated step pays), and prints median, p99
 * and max of each in microseconds with the ratio of the medians. The plan is the largest
 * message: horizon 40 (a 1.6 s horizon at 25 Hz).
 */
#define _POSIX_C_SOURCE 199309L /* clock_gettime */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "bench_timing.h"
#include "ddyn/telemetry.h"

#define MAX_CALLS 200000
#define PLAN_HORIZON 40


static double states[(PLAN_HORIZON + 1) * DDYN_NX], inputs[PLAN_HORIZON * DDYN_NU];
static double samples[MAX_CALLS];

static ddyn_tm_status call(ddyn_telemetry *tm, ddyn_tm_kind kind, int64_t step)
{
    ddyn_tm_state s;
    ddyn_tm_coeffs c;
    ddyn_tm_plan p;
    ddyn_tm_timing t;
    ddyn_tm_faults f;
    int i;
    switch (kind) {
    case DDYN_TM_STATE:
        s.utime = step * 20000;
        s.step = step;
        for (i = 0; i < DDYN_NX; ++i) {
            s.x[i] = 0.1 * i + 1e-6 * (double)step;
            s.cov_diag[i] = 1e-3;
        }
        return ddyn_telemetry_publish_state(tm, &s);
    case DDYN_TM_COEFFS:
        c.utime = step * 20000;
        c.step = step;
        for (i = 0; i < DDYN_NC; ++i) {
            c.coeffs[i] = 0.5 + 1e-6 * (double)step;
        }
        return ddyn_telemetry_publish_coeffs(tm, &c);
    case DDYN_TM_PLAN:
        memset(&p, 0, sizeof p);
        p.utime = step * 20000;
        p.step = step;
        p.status_name = "solved";
        p.horizon = PLAN_HORIZON;
        p.states = states;
        p.inputs = inputs;
        return ddyn_telemetry_publish_plan(tm, &p);
    case DDYN_TM_TIMING:
        memset(&t, 0, sizeof t);
        t.utime = step * 20000;
        t.step = step;
        t.deadline_s = 0.02;
        t.total_s = 0.005;
        t.n_stages = 4;
        t.stage_names[0] = "ekf";
        t.stage_names[1] = "guard_net";
        t.stage_names[2] = "mpc";
        t.stage_names[3] = "can_tx";
        return ddyn_telemetry_publish_timing(tm, &t);
    case DDYN_TM_FAULTS:
        f.utime = step * 20000;
        f.step = step;
        f.active = (uint32_t)(step & 3);
        return ddyn_telemetry_publish_faults(tm, &f);
    case DDYN_TM_KIND_COUNT:
        break;
    }
    return DDYN_TM_ERR_ARGUMENT;
}

/* median, p99, max of n timed calls of one kind at one rate; 0 on a publish error */
static int measure(const char *url, ddyn_tm_kind kind, double rate, int n, double out[3])
{
    static double lo[DDYN_NC], hi[DDYN_NC];
    static ddyn_telemetry tm;
    ddyn_telemetry_config cfg;
    bench_stats st;
    int i;
    for (i = 0; i < DDYN_NC; ++i) {
        lo[i] = 0.0;
        hi[i] = 1.0;
    }
    ddyn_telemetry_default_config(&cfg, 50.0);
    cfg.url = url;
    cfg.rate_hz[kind] = rate;
    cfg.coeff_lo = lo;
    cfg.coeff_hi = hi;
    if (ddyn_telemetry_open(&tm, &cfg) != DDYN_TM_PUBLISHED) {
        fprintf(stderr, "ddyn_telemetry_bench: cannot open LCM at %s\n", url);
        return 0;
    }
    for (i = 0; i < n; ++i) {
        double t0 = bench_now_us();
        ddyn_tm_status s = call(&tm, kind, i);
        samples[i] = bench_now_us() - t0;
        if (s != DDYN_TM_PUBLISHED && s != DDYN_TM_SKIPPED) {
            fprintf(stderr, "ddyn_telemetry_bench: %s: %s\n", ddyn_tm_kind_name(kind), ddyn_tm_status_name(s));
            ddyn_telemetry_close(&tm);
            return 0;
        }
    }
    ddyn_telemetry_close(&tm);
    st = bench_stats_of(samples, n);
    out[0] = st.median;
    out[1] = st.p99;
    out[2] = st.max;
    return 1;
}

int main(int argc, char **argv)
{
    const char *url = "file:///dev/null?mode=w";
    int n = 20000, i, k;
    for (i = 1; i < argc; ++i) {
        if (strcmp(argv[i], "-u") == 0 && i + 1 < argc) {
            url = argv[++i];
        } else if (strcmp(argv[i], "-n") == 0 && i + 1 < argc) {
            n = atoi(argv[++i]);
        } else {
            fprintf(stderr, "usage: %s [-u URL] [-n CALLS]\n", argv[0]);
            return 2;
        }
    }
    if (n < 100 || n > MAX_CALLS) {
        fprintf(stderr, "ddyn_telemetry_bench: CALLS must be within 100 .. %d\n", MAX_CALLS);
        return 2;
    }
    for (k = 0; k < (PLAN_HORIZON + 1) * DDYN_NX; ++k) {
        states[k] = 0.01 * k;
    }
    printf("telemetry call cost, %d calls per row, LCM %s (microseconds)\n", n, url);
    printf("%-7s %10s %10s %10s | %10s %10s %10s | %s\n", "kind", "pub med", "pub p99", "pub max", "skip med",
           "skip p99", "skip max", "median ratio pub/skip");
    for (k = 0; k < DDYN_TM_KIND_COUNT; ++k) {
        double pub[3], skip[3];
        if (!measure(url, (ddyn_tm_kind)k, 50.0, n, pub) || !measure(url, (ddyn_tm_kind)k, 0.0, n, skip)) {
            return 1;
        }
        printf("%-7s %10.3f %10.3f %10.3f | %10.3f %10.3f %10.3f | %.1f\n", ddyn_tm_kind_name((ddyn_tm_kind)k),
               pub[0], pub[1], pub[2], skip[0], skip[1], skip[2], skip[0] > 0 ? pub[0] / skip[0] : INFINITY);
    }
    return 0;
}
