/*
 * ddyn_mpc_lap: the C MPC driving the simulated car in closed loop (host tool; `ddyn mpc lap` and
 * `ddyn bench runtime` drive it). The plant is the generated model step (RK4) with its own coefficients.
 *
 * usage: ddyn_mpc_lap [QP_DUMP] < setup      setup is text, keyword lines then the raceline table:
 *   vehicle NAME | disc rk4_single|euler|rk4 | horizon H | steps N | weights qx qy q_terminal r_dT r_dd l1 l2
 *   qp MAX_ITER TOL | coeffs c1..c17 (the MPC's) | plant_coeffs c1..c17 | x0 x1..x8
 *   track N, followed by N lines "x y speed room_left room_right"
 * DDYN_QP_SOLVER=ipm in the environment selects the interior-point QP solver (default daqp).
 * Prints one line per step: "k status qp_iterations converged kkt_residual max_slack solve_us
 * u0 u1 x1..x8" (x after applying u), then "done".
 * With QP_DUMP, every step's condensed QP (ddyn_mpc_qp: problem and the solver's answer) is appended
 * to that file as little-endian doubles, one record per step (c_src/tools/qp_dump.h, `ddyn bench qp`).
 */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "bench_timing.h"
#include "qp_dump.h"
#include "ddyn/mpc.h"
#include "ddyn_models.h"

#define MAX_STEPS 200000


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

static double tx[DDYN_MPC_MAX_TRACK_POINTS], ty[DDYN_MPC_MAX_TRACK_POINTS], tv[DDYN_MPC_MAX_TRACK_POINTS],
    twl[DDYN_MPC_MAX_TRACK_POINTS], twr[DDYN_MPC_MAX_TRACK_POINTS];

int main(int argc, char **argv)
{
    FILE *dump = NULL;
    static ddyn_mpc mpc;
    static ddyn_model_work work;
    char key[64], name[64] = "orca_1_43", disc[16] = "rk4";
    double w[7] = {0}, c[DDYN_NC] = {0}, pc[DDYN_NC] = {0}, x[DDYN_NX] = {0}, qtol = 0.0;
    int horizon = DDYN_MPC_DEFAULT_HORIZON, steps = 100, n_track = 0, have_w = 0, qiter = 0, k, i;
    const ddyn_vehicle_model *model;
    ddyn_mpc_config cfg;
    ddyn_status st;
    while (scanf("%63s", key) == 1) {
        int ok = 1;
        if (strcmp(key, "vehicle") == 0) {
            ok = scanf("%63s", name) == 1;
        } else if (strcmp(key, "disc") == 0) {
            ok = scanf("%15s", disc) == 1;
        } else if (strcmp(key, "horizon") == 0) {
            ok = scanf("%d", &horizon) == 1;
        } else if (strcmp(key, "steps") == 0) {
            ok = scanf("%d", &steps) == 1 && steps >= 1 && steps <= MAX_STEPS;
        } else if (strcmp(key, "weights") == 0) {
            ok = read_doubles(w, 7);
            have_w = 1;
        } else if (strcmp(key, "qp") == 0) {
            ok = scanf("%d %lf", &qiter, &qtol) == 2;
        } else if (strcmp(key, "coeffs") == 0) {
            ok = read_doubles(c, DDYN_NC);
        } else if (strcmp(key, "plant_coeffs") == 0) {
            ok = read_doubles(pc, DDYN_NC);
        } else if (strcmp(key, "x0") == 0) {
            ok = read_doubles(x, DDYN_NX);
        } else if (strcmp(key, "track") == 0) {
            ok = scanf("%d", &n_track) == 1 && n_track >= 4 && n_track <= DDYN_MPC_MAX_TRACK_POINTS;
            for (i = 0; ok && i < n_track; ++i) {
                ok = scanf("%lf %lf %lf %lf %lf", &tx[i], &ty[i], &tv[i], &twl[i], &twr[i]) == 5;
            }
        } else {
            ok = 0;
        }
        if (!ok) {
            fprintf(stderr, "ddyn_mpc_lap: bad or incomplete '%s' line\n", key);
            return 2;
        }
    }
    model = ddyn_model_find(name);
    if (model == NULL || ddyn_mpc_default_config(model, &cfg) != DDYN_OK) {
        fprintf(stderr, "ddyn_mpc_lap: unknown vehicle %s\n", name);
        return 2;
    }
    cfg.horizon = horizon;
    cfg.prediction = strcmp(disc, "euler") == 0 ? DDYN_MPC_PRED_EULER
                     : strcmp(disc, "rk4") == 0 ? DDYN_MPC_PRED_RK4 : DDYN_MPC_PRED_RK4_SINGLE;
    if (have_w) {
        cfg.q_pos[0] = w[0];
        cfg.q_pos[1] = w[1];
        cfg.q_terminal_scale = w[2];
        cfg.r_rate[0] = w[3];
        cfg.r_rate[1] = w[4];
        cfg.slack_l1 = w[5];
        cfg.slack_l2 = w[6];
    }
    if (qiter > 0) {
        cfg.qp_max_iterations = qiter;
        cfg.qp_tolerance = qtol;
    }
    if (getenv("DDYN_QP_SOLVER") != NULL) { /* ipm or daqp (the default): docs/mpc.md */
        cfg.qp_solver = strcmp(getenv("DDYN_QP_SOLVER"), "ipm") == 0 ? DDYN_MPC_QP_IPM : DDYN_MPC_QP_DAQP;
    }
    if ((st = ddyn_mpc_init(&mpc, model, &cfg)) != DDYN_OK ||
        (st = ddyn_mpc_set_track(&mpc, n_track, tx, ty, tv, twl, twr)) != DDYN_OK ||
        (st = ddyn_mpc_set_coefficients(&mpc, c)) != DDYN_OK) {
        fprintf(stderr, "ddyn_mpc_lap: setup refused: %s\n", ddyn_status_name(st));
        return 2;
    }
    if (argc > 1 && (dump = fopen(argv[1], "wb")) == NULL) {
        fprintf(stderr, "ddyn_mpc_lap: cannot write %s\n", argv[1]);
        return 2;
    }
    for (k = 0; k < steps; ++k) {
        double u[DDYN_NU], xn[DDYN_NX], t0, t1;
        ddyn_mpc_info info;
        t0 = bench_now_us();
        st = ddyn_mpc_solve(&mpc, x, u, &info);
        t1 = bench_now_us();
        if (dump != NULL && (st == DDYN_OK || st == DDYN_ERR_QP_NOT_CONVERGED) && !qp_dump_write(dump, &mpc.qp)) {
            fprintf(stderr, "ddyn_mpc_lap: writing %s failed\n", argv[1]);
            return 1;
        }
        if (ddyn_model_step(model, DDYN_DISC_RK4, x, u, pc, xn, &work) != DDYN_OK) {
            fprintf(stderr, "ddyn_mpc_lap: plant step failed at step %d\n", k);
            return 1;
        }
        memcpy(x, xn, sizeof x);
        printf("%d %d %d %d %.3e %.3e %.3f %.17g %.17g", k, (int)st, info.qp_iterations, info.converged,
               info.kkt_residual, info.max_slack, t1 - t0, u[0], u[1]);
        for (i = 0; i < DDYN_NX; ++i) {
            printf(" %.17g", x[i]);
        }
        printf("\n");
    }
    printf("done\n");
    if (dump != NULL && fclose(dump) != 0) {
        return 1;
    }
    return 0;
}
