/*
 * ddyn_qp_replay: the MPC's QP solver (c_src/src/mpc_qp.c) on dumped QPs (host tool; `ddyn bench qp`,
 * train/bench/qp.py, drives it). usage: ddyn_qp_replay DUMP REPEATS MAX_ITER TOL OUT
 *
 * DUMP holds the QPs of a closed-loop lap (ddyn_mpc_lap QP_DUMP, qp_dump.h). Each QP is solved
 *   - as the runtime does (double, MAX_ITER iterations, TOL), REPEATS times: median time;
 *   - by the float32 build of the same solver (qp_f32.c), REPEATS times;
 *   - by the double solver with 50 iterations and tolerance 1e-10 (a tight own answer).
 *   - as the runtime's DAQP path does (mpc.c feedback): DAQP (mpc_qp_daqp.c, cap MAX_ITER) warm-started
 *     from the previous QP's working set shifted one stage; a QP without a working set (the first, and
 *     the one after a capped or failed solve) by the interior point instead (cap
 *     DDYN_MPC_COLD_IPM_ITERATIONS, TOL), which seeds the next working set. REPEATS times from the same
 *     start.
 *   - by DAQP cold (an empty working set for every QP; cap MAX_ITER), REPEATS times.
 * The interior point always starts cold (infeasible start). OUT gets per QP, as doubles:
 *   iterations, converged, median_us, z (2H), slack (H)      for each of the five runs in that order.
 */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "bench_timing.h"
#include "ddyn/mpc.h"
#include "qp_dump.h"
#include "qp_f32.h"

#define MAX_REPEATS 1000

static ddyn_mpc_qp problem, work;
static ddyn_mpc_qp_daqp daqp, daqp_cold;
static double times[MAX_REPEATS];

static int put(FILE *f, double it, double conv, double us, const double *z, const double *s, int m)
{
    double head[3];
    head[0] = it;
    head[1] = conv;
    head[2] = us;
    return fwrite(head, sizeof(double), 3, f) == 3 && fwrite(z, sizeof(double), (size_t)(2 * m), f) == (size_t)(2 * m) &&
           fwrite(s, sizeof(double), (size_t)m, f) == (size_t)m;
}

int main(int argc, char **argv)
{
    FILE *in, *out;
    int repeats, max_it, count = 0, r;
    double tol;
    if (argc != 6 || (repeats = atoi(argv[2])) < 1 || repeats > MAX_REPEATS || (max_it = atoi(argv[3])) < 1 ||
        max_it > DDYN_MPC_MAX_QP_ITERATIONS || !((tol = atof(argv[4])) > 0.0)) {
        fprintf(stderr, "usage: ddyn_qp_replay DUMP REPEATS(1..%d) MAX_ITER(1..%d) TOL OUT\n", MAX_REPEATS,
                DDYN_MPC_MAX_QP_ITERATIONS);
        return 2;
    }
    if ((in = fopen(argv[1], "rb")) == NULL || (out = fopen(argv[5], "wb")) == NULL) {
        fprintf(stderr, "ddyn_qp_replay: cannot open %s or %s\n", argv[1], argv[5]);
        return 2;
    }
    while (qp_dump_read(in, &problem)) {
        const int m = problem.horizon;
        double z32[DDYN_QP_NV], s32[DDYN_QP_NS];
        int it32 = 0, conv32 = 0, conv;
        bench_stats st;
        for (r = 0; r < repeats; ++r) {
            double t0;
            memcpy(&work, &problem, sizeof work);
            t0 = bench_now_us();
            conv = ddyn_mpc_qp_solve(&work, max_it, tol) == DDYN_OK;
            times[r] = bench_now_us() - t0;
        }
        st = bench_stats_of(times, repeats);
        if (!put(out, work.iterations, conv, st.median, work.z, work.slack, m)) {
            return 1;
        }
        for (r = 0; r < repeats; ++r) {
            double t0 = bench_now_us();
            conv32 = qp_f32_solve(m, problem.dt, problem.rho1, problem.rho2, problem.hess, problem.grad, problem.lb,
                                  problem.ub, problem.hard_lo, problem.hard_hi, problem.soft_row, problem.soft_lo,
                                  problem.soft_hi, max_it, tol, z32, s32, &it32);
            times[r] = bench_now_us() - t0;
        }
        st = bench_stats_of(times, repeats);
        if (!put(out, it32, conv32, st.median, z32, s32, m)) {
            return 1;
        }
        memcpy(&work, &problem, sizeof work);
        conv = ddyn_mpc_qp_solve(&work, DDYN_MPC_MAX_QP_ITERATIONS, 1e-10) == DDYN_OK;
        if (!put(out, work.iterations, conv, 0.0, work.z, work.slack, m)) {
            return 1;
        }
        {
            /* every repeat from the same warm start: the working set the previous QP left */
            int warm_id[DDYN_DAQP_WS], warm_lower[DDYN_DAQP_WS], warm_n = daqp.warm_n, warm_h = daqp.warm_h;
            memcpy(warm_id, daqp.warm_id, sizeof warm_id);
            memcpy(warm_lower, daqp.warm_lower, sizeof warm_lower);
            const int cold = warm_h != problem.horizon;
            for (r = 0; r < repeats; ++r) {
                double t0;
                ddyn_status s;
                memcpy(daqp.warm_id, warm_id, sizeof warm_id);
                memcpy(daqp.warm_lower, warm_lower, sizeof warm_lower);
                daqp.warm_n = warm_n;
                daqp.warm_h = warm_h;
                memcpy(&work, &problem, sizeof work);
                t0 = bench_now_us();
                if (cold) {
                    s = ddyn_mpc_qp_solve(&work, DDYN_MPC_COLD_IPM_ITERATIONS, tol);
                    if (s == DDYN_OK || s == DDYN_ERR_QP_NOT_CONVERGED) {
                        ddyn_mpc_qp_daqp_seed(&daqp, &work);
                    } else {
                        ddyn_mpc_qp_daqp_reset(&daqp);
                    }
                } else {
                    s = ddyn_mpc_qp_daqp_solve(&work, &daqp, max_it, 1); /* capped: the next one starts cold */
                }
                conv = s == DDYN_OK;
                times[r] = bench_now_us() - t0;
            }
        }
        st = bench_stats_of(times, repeats);
        if (!put(out, work.iterations, conv, st.median, work.z, work.slack, m)) {
            return 1;
        }
        for (r = 0; r < repeats; ++r) {
            double t0;
            memcpy(&work, &problem, sizeof work);
            ddyn_mpc_qp_daqp_reset(&daqp_cold);
            t0 = bench_now_us();
            conv = ddyn_mpc_qp_daqp_solve(&work, &daqp_cold, max_it, 0) == DDYN_OK;
            times[r] = bench_now_us() - t0;
        }
        st = bench_stats_of(times, repeats);
        if (!put(out, work.iterations, conv, st.median, work.z, work.slack, m)) {
            return 1;
        }
        ++count;
    }
    fclose(in);
    if (fclose(out) != 0) {
        return 1;
    }
    printf("qp_replay %d\n", count);
    return 0;
}
