/*
 * ddyn_ekf_replay: run the car's EKF over a sensor log from stdin (host tool, for tests and tuning).
 *
 * usage: ddyn_ekf_replay VEHICLE euler|rk4 < log
 * Input lines (numbers separated by spaces):
 *   I x0[8] p0_diag[8] q_diag[8]        initialise
 *   P u[2] c[17]                        predict one sample time
 *   M kind c[17] z[dim] r_diag[dim]     update with sensor `kind` (ddyn_meas_kind number)
 *   O                                   output "x[8] P[64]" (column-major)
 * Each M line prints "nis VALUE". A malformed line or a filter error stops with a message and status 1.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "ddyn/ekf.h"

static int read_numbers(char **p, double *v, int n)
{
    int i;
    for (i = 0; i < n; ++i) {
        char *end = NULL;
        v[i] = strtod(*p, &end);
        if (end == *p) {
            return 0;
        }
        *p = end;
    }
    return 1;
}

int main(int argc, char **argv)
{
    static ddyn_ekf ekf;
    static char line[1 << 14];
    const ddyn_vehicle_model *model;
    ddyn_discretisation disc;
    long line_no = 0;
    if (argc != 3 || (model = ddyn_model_find(argv[1])) == NULL) {
        fprintf(stderr, "usage: %s VEHICLE euler|rk4 < log\n", argv[0]);
        return 2;
    }
    disc = strcmp(argv[2], "rk4") == 0 ? DDYN_DISC_RK4 : DDYN_DISC_EULER;
    while (fgets(line, sizeof line, stdin) != NULL) {
        double v[3 * DDYN_NX + DDYN_NC + 2 * DDYN_MEAS_MAX_DIM + 1];
        char *p = line + 1;
        ddyn_status s = DDYN_OK;
        ++line_no;
        if (line[0] == 'I' && read_numbers(&p, v, 3 * DDYN_NX)) {
            s = ddyn_ekf_init(&ekf, model, disc, v, v + DDYN_NX, v + 2 * DDYN_NX);
        } else if (line[0] == 'P' && read_numbers(&p, v, DDYN_NU + DDYN_NC)) {
            s = ddyn_ekf_predict(&ekf, v, v + DDYN_NU);
        } else if (line[0] == 'M' && read_numbers(&p, v, 1 + DDYN_NC)) {
            ddyn_meas_kind kind = (ddyn_meas_kind)(int)v[0];
            int dim = ddyn_meas_dim(kind);
            double nis = 0.0;
            if (dim == 0 || !read_numbers(&p, v + 1 + DDYN_NC, 2 * dim)) {
                fprintf(stderr, "ddyn_ekf_replay: line %ld: bad measurement\n", line_no);
                return 1;
            }
            s = ddyn_ekf_update(&ekf, kind, v + 1 + DDYN_NC, v + 1 + DDYN_NC + dim, v + 1, &nis);
            if (s == DDYN_OK) {
                printf("nis %.17g\n", nis);
            }
        } else if (line[0] == 'O') {
            int i;
            for (i = 0; i < DDYN_NX + DDYN_NX * DDYN_NX; ++i) {
                printf(i + 1 < DDYN_NX + DDYN_NX * DDYN_NX ? "%.17g " : "%.17g\n",
                       i < DDYN_NX ? ekf.x[i] : ekf.P[i - DDYN_NX]);
            }
        } else {
            fprintf(stderr, "ddyn_ekf_replay: line %ld: expected I, P, M or O with its numbers\n", line_no);
            return 1;
        }
        if (s != DDYN_OK) {
            fprintf(stderr, "ddyn_ekf_replay: line %ld: %s\n", line_no, ddyn_status_name(s));
            return 1;
        }
    }
    return 0;
}
