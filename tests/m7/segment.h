/*
 * tests/m7/segment.h - a recorded closed-loop segment of the controller (host build), compiled into
 * the Cortex-M7 firmware as const tables. The data (generated/controller_segment.c) is written by
 * ddyn_controller_bench's RECORD.c argument; regenerate it with scripts/m7_record.sh.
 */
#ifndef DDYN_M7_SEGMENT_H
#define DDYN_M7_SEGMENT_H

#include "ddyn/mpc.h"

typedef struct {
    unsigned valid;                                   /* bit k: a reading of sensor kind k this period */
    double z[DDYN_MEAS_COUNT * DDYN_MEAS_MAX_DIM];    /* kind k at [k * DDYN_MEAS_MAX_DIM] */
    double u[DDYN_NU];                                /* the host build's command */
    unsigned long status;                             /* the host build's status bits */
    int qp_iterations;                                /* the host build's QP iterations */
    double u_plan[DDYN_MPC_NV];                       /* the host's MPC plan after the step (next warm start) */
    int last_index;                                   /* the host's MPC raceline segment after the step */
} m7_seg_period;

extern const char m7_seg_vehicle[];
extern const double m7_seg_c_nominal[DDYN_NC];
extern const double m7_seg_x0[DDYN_NX];
extern const double m7_seg_q_diag[DDYN_NX];
extern const double m7_seg_r_std[DDYN_MEAS_COUNT]; /* std the filter assumes, per sensor kind */
extern const int m7_seg_track_n;
extern const double m7_seg_track[][5];            /* x y speed width_left width_right */
extern const int m7_seg_steps;
extern const m7_seg_period m7_seg_periods[];

#endif /* DDYN_M7_SEGMENT_H */
