/*
 * controller_setup.h - the controller process's setup file (written by `ddyn sil run`, format in
 * controller_main.c's header comment) and the node built from it. Host-side (stdio).
 */
#ifndef DDYN_SIL_CONTROLLER_SETUP_H
#define DDYN_SIL_CONTROLLER_SETUP_H

#include "controller_node.h"

#ifdef __cplusplus
extern "C" {
#endif

#define DDYN_SIL_MAX_STEPS 200000
#define DDYN_SIL_PATH_LEN 512

typedef struct {
    char vehicle[64];
    double period;
    int fixed;
    double nominal[DDYN_NC], coeffs[DDYN_NC], x0[DDYN_NX], r_std[DDYN_MEAS_COUNT][2], q[DDYN_NX];
    int throttle_pid;   /* 1: throttle by PID (DDYN_CTRL_THROTTLE_PID), 0: by the MPC */
    int pid_default;    /* 1: the controller's default gains, 0: pid[] */
    double pid[4];      /* kp, ki, kd, preview (s) */
    int stale[DDYN_DBW_FRAME_COUNT];
    long max_steps;
    double idle_exit;
    double lockstep; /* 0: real time; > 0: wall seconds of total silence before a timer period */
    long die_at_step;
    char metrics[DDYN_SIL_PATH_LEN], log[DDYN_SIL_PATH_LEN];
    int n_track;
    double track[5][DDYN_MPC_MAX_TRACK_POINTS]; /* x, y, speed, room left, room right */
} ddyn_sil_setup;

/* Read a setup file; on failure prints what is wrong to stderr and returns 0. */
int ddyn_sil_read_setup(const char *path, ddyn_sil_setup *s);

/* The controller configuration of a setup (defaults of ddyn_ctrl_default_config, then the
 * setup's coefficients: fixed ones as DDYN_CTRL_SOURCE_FIXED; filter noise; throttle mode and PID
 * gains), the node initialised with it and the raceline set. Prints the reason and returns the
 * error on failure. */
ddyn_status ddyn_sil_node_from_setup(ddyn_sil_node *node, const ddyn_sil_setup *s, const ddyn_net_tables *tables);

#ifdef __cplusplus
}
#endif

#endif
