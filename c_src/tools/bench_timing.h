/*
 * bench_timing.h - what the host benchmark tools share (not part of the runtime): a monotonic
 * clock and median / p99 / max of a sample array, so every tool reports the same statistics
 * (p99 = the sample at index floor(0.99 (n - 1)) of the sorted array).
 */
#ifndef DDYN_BENCH_TIMING_H
#define DDYN_BENCH_TIMING_H

#include <stdlib.h>
#include <time.h>

/* CLOCK_MONOTONIC in microseconds */
static inline double bench_now_us(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec * 1e6 + (double)t.tv_nsec * 1e-3;
}

static inline int bench_cmp_double(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

typedef struct {
    double median, p99, max;
} bench_stats;

/* sorts v (n >= 1) in place */
static inline bench_stats bench_stats_of(double *v, int n)
{
    bench_stats s;
    qsort(v, (size_t)n, sizeof v[0], bench_cmp_double);
    s.median = v[n / 2];
    s.p99 = v[(int)(0.99 * (n - 1))];
    s.max = v[n - 1];
    return s;
}

#endif
