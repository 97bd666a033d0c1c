#include "controller_setup.h"

#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int expect(FILE *in, const char *key)
{
    char word[64];
    if (fscanf(in, "%63s", word) != 1 || strcmp(word, key) != 0) {
        fprintf(stderr, "ddyn_sil_controller: setup: expected '%s'\n", key);
        return 0;
    }
    return 1;
}

static int read_n(FILE *in, double *v, int n)
{
    int i;
    for (i = 0; i < n; ++i) {
        if (fscanf(in, "%lf", &v[i]) != 1 || !isfinite(v[i])) {
            return 0;
        }
    }
    return 1;
}

/* "throttle mpc|pid  pid_gains default|KP KI KD PREVIEW" */
static int read_throttle(FILE *in, ddyn_sil_setup *s)
{
    char word[64], *end;
    if (!expect(in, "throttle") || fscanf(in, "%63s", word) != 1) {
        return 0;
    }
    if (strcmp(word, "pid") == 0) {
        s->throttle_pid = 1;
    } else if (strcmp(word, "mpc") == 0) {
        s->throttle_pid = 0;
    } else {
        fprintf(stderr, "ddyn_sil_controller: setup: throttle is 'mpc' or 'pid', not '%s'\n", word);
        return 0;
    }
    if (!expect(in, "pid_gains") || fscanf(in, "%63s", word) != 1) {
        return 0;
    }
    if (strcmp(word, "default") == 0) {
        s->pid_default = 1;
        return 1;
    }
    s->pid_default = 0;
    s->pid[0] = strtod(word, &end);
    return end != word && *end == '\0' && isfinite(s->pid[0]) && read_n(in, s->pid + 1, 3);
}

int ddyn_sil_read_setup(const char *path, ddyn_sil_setup *s)
{
    FILE *in = fopen(path, "r");
    double r[2 * DDYN_MEAS_COUNT], st[DDYN_DBW_FRAME_COUNT];
    int ok, i, k;
    if (in == NULL) {
        fprintf(stderr, "ddyn_sil_controller: cannot read setup %s: %s\n", path, strerror(errno));
        return 0;
    }
    ok = expect(in, "vehicle") && fscanf(in, "%63s", s->vehicle) == 1 && expect(in, "period") &&
         fscanf(in, "%lf", &s->period) == 1 && s->period > 0.0 && expect(in, "fixed") &&
         fscanf(in, "%d", &s->fixed) == 1 && expect(in, "nominal") && read_n(in, s->nominal, DDYN_NC) &&
         expect(in, "coeffs") && read_n(in, s->coeffs, DDYN_NC) && read_throttle(in, s) && expect(in, "x0") &&
         read_n(in, s->x0, DDYN_NX) &&
         expect(in, "r_std") && read_n(in, r, 2 * DDYN_MEAS_COUNT) && expect(in, "q") && read_n(in, s->q, DDYN_NX) &&
         expect(in, "stale") && read_n(in, st, DDYN_DBW_FRAME_COUNT) && expect(in, "max_steps") &&
         fscanf(in, "%ld", &s->max_steps) == 1 && s->max_steps > 0 && s->max_steps <= DDYN_SIL_MAX_STEPS &&
         expect(in, "idle_exit") && fscanf(in, "%lf", &s->idle_exit) == 1 && expect(in, "lockstep") &&
         fscanf(in, "%lf", &s->lockstep) == 1 && s->lockstep >= 0.0 && expect(in, "die_at_step") &&
         fscanf(in, "%ld", &s->die_at_step) == 1 && expect(in, "metrics") && fscanf(in, "%511s", s->metrics) == 1 &&
         expect(in, "log") && fscanf(in, "%511s", s->log) == 1 && expect(in, "track") &&
         fscanf(in, "%d", &s->n_track) == 1 && s->n_track >= 4 && s->n_track <= DDYN_MPC_MAX_TRACK_POINTS;
    for (i = 0; ok && i < s->n_track; ++i) {
        double row[5];
        ok = read_n(in, row, 5);
        for (k = 0; ok && k < 5; ++k) {
            s->track[k][i] = row[k];
        }
    }
    fclose(in);
    if (!ok) {
        fprintf(stderr, "ddyn_sil_controller: setup %s is malformed (see the header comment)\n", path);
        return 0;
    }
    for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
        s->r_std[k][0] = r[2 * k];
        s->r_std[k][1] = r[2 * k + 1];
    }
    for (k = 0; k < DDYN_DBW_FRAME_COUNT; ++k) {
        s->stale[k] = (int)st[k];
    }
    return 1;
}

ddyn_status ddyn_sil_node_from_setup(ddyn_sil_node *node, const ddyn_sil_setup *s, const ddyn_net_tables *tables)
{
    const ddyn_vehicle_model *model = ddyn_model_find(s->vehicle);
    ddyn_ctrl_config cfg;
    ddyn_status st;
    int i, k;
    if (model == NULL) {
        fprintf(stderr, "ddyn_sil_controller: no generated model '%s'\n", s->vehicle);
        return DDYN_ERR_ARGUMENT;
    }
    ddyn_ctrl_default_config(model, &cfg);
    memcpy(cfg.c_nominal, s->nominal, sizeof cfg.c_nominal);
    if (s->fixed) {
        cfg.coeff_source = DDYN_CTRL_SOURCE_FIXED; /* the network is never run */
        memcpy(cfg.c_fixed, s->coeffs, sizeof cfg.c_fixed);
    }
    if (s->throttle_pid) {
        cfg.throttle_mode = DDYN_CTRL_THROTTLE_PID;
        if (!s->pid_default) {
            cfg.pid.kp = s->pid[0];
            cfg.pid.ki = s->pid[1];
            cfg.pid.kd = s->pid[2];
            cfg.pid.preview = s->pid[3];
        }
    }
    for (k = 0; k < DDYN_NX; ++k) {
        if (s->q[k] > 0.0) {
            cfg.q_diag[k] = s->q[k];
        }
    }
    for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
        for (i = 0; i < DDYN_MEAS_MAX_DIM; ++i) {
            double sd = s->r_std[k][i];
            cfg.r_diag[k][i] = sd > 0.0 ? sd * sd : 1e-8;
        }
    }
    st = ddyn_sil_node_init(node, model, tables, &cfg, s->x0, s->period, s->stale);
    if (st == DDYN_OK) {
        st = ddyn_ctrl_set_track(&node->ctl, s->n_track, s->track[0], s->track[1], s->track[2], s->track[3],
                                 s->track[4]);
    }
    if (st != DDYN_OK) {
        fprintf(stderr, "ddyn_sil_controller: the controller refused the setup: %s (network built for another "
                        "export?)\n", ddyn_status_name(st));
    }
    return st;
}
