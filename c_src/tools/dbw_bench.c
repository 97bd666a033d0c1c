/*
 * ddyn_dbw_bench: per-call timings of the drive-by-wire path (ddyn/dbw.h), each call timed on
 * CLOCK_MONOTONIC: receiving one frame (decode, checksum, range and counter checks, monitor
 * update) and producing one command frame (deadline check, range check, encode, checksum).
 * Prints "<name> <calls> <median_ns> <p99_ns> <max_ns>" per function; `ddyn can bench` runs it
 * beside the Python decoder.   usage: ddyn_dbw_bench [CALLS]   (default 100000)
 */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "bench_timing.h"
#include "ddyn/dbw.h"

#define MAX_CALLS 1000000

static double samples[MAX_CALLS]; /* ns */

static void report(const char *name, int n)
{
    bench_stats st = bench_stats_of(samples, n);
    printf("%s %d %.0f %.0f %.0f\n", name, n, st.median, st.p99, st.max);
}

int main(int argc, char **argv)
{
    int n = argc > 1 ? atoi(argv[1]) : 100000, i;
    static ddyn_dbw rx, tx;
    ddyn_dbw_config cfg;
    ddyn_dbw_signals s;
    ddyn_dbw_command desired = {0.4, 0.0, 0.1, true, DDYN_DBW_MODE_AUTONOMOUS}, sent;
    uint8_t frames[16][8], data[8];
    unsigned long long sink = 0;
    if (n < 100 || n > MAX_CALLS) {
        fprintf(stderr, "CALLS must be in [100, %d]\n", MAX_CALLS);
        return 2;
    }
    memset(&s, 0, sizeof(s));
    s.sensors.yaw_rate = 0.3;
    s.sensors.accel_x = 1.5;
    s.sensors.accel_y = -4.0;
    ddyn_dbw_default_config(&cfg, DDYN_DBW_MONITOR_CONTROLLER);
    cfg.deadline_us[DDYN_DBW_FRAME_IMU] = 0xFFFFFFFFu; /* the bench's clock is not the bus's */
    if (ddyn_dbw_init(&rx, &cfg) != 0 || ddyn_dbw_init(&tx, &cfg) != 0) {
        return 1;
    }
    for (i = 0; i < 16; ++i) { /* one frame per counter value, so every call is a good frame */
        if (ddyn_dbw_next_frame(&tx, DDYN_DBW_FRAME_IMU, &s, frames[i]) != 0) {
            return 1;
        }
    }
    for (i = 0; i < n; ++i) {
        double t0 = bench_now_us();
        ddyn_dbw_decode_result r = ddyn_dbw_on_frame(&rx, 0x120u, frames[i % 16], 8, 1000u + (uint64_t)i);
        samples[i] = (bench_now_us() - t0) * 1e3;
        sink += (unsigned long long)r;
    }
    if (rx.failures[DDYN_DBW_FAIL_COUNTER_JUMP] != 0u || sink != 0u) {
        fprintf(stderr, "bench frames were rejected\n");
        return 1;
    }
    report("dbw_on_frame", n);
    for (i = 0; i < n; ++i) {
        double t0 = bench_now_us();
        (void)ddyn_dbw_command_frame(&rx, 1000u + (uint64_t)i, &desired, &sent, data);
        samples[i] = (bench_now_us() - t0) * 1e3;
        sink += data[7];
    }
    report("dbw_command_frame", n);
    fprintf(stderr, "(checksum sink %llu)\n", sink);
    return 0;
}
