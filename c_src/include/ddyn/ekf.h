/*
 * ddyn/ekf.h - the car's extended Kalman filter over the single-track model.
 *
 * State: the model's 8 states (x, y, yaw, vx, vy, omega, throttle, steering).
 * Prediction: the generated discrete step and its Jacobian A (train/model/single_track.py via
 * `ddyn codegen model`) with the coefficients the guard network estimates, plus a
 * diagonal process noise. Updates: any sensor of train/model/sensors.py, each optional
 * and at its own rate (call ddyn_ekf_update when a reading arrives), with a
 * diagonal measurement noise; heading innovations are wrapped to [-pi, pi).
 * Joseph-form covariance update; all matrices fixed-size, column-major, in the
 * caller-owned ddyn_ekf; every loop bounded by compile-time sizes.
 */
#ifndef DDYN_EKF_H
#define DDYN_EKF_H

#include "ddyn/model.h"

#ifdef __cplusplus
extern "C" {
#endif

typedef struct {
    const ddyn_vehicle_model *model;
    ddyn_discretisation disc;
    double x[DDYN_NX];
    double P[DDYN_NX * DDYN_NX]; /* column-major, symmetric */
    double q[DDYN_NX];           /* process noise variance per step */
    double bank;                 /* rad: the road's bank over the next prediction (ddyn_model_add_bank;
                                    0 after init: flat); the caller sets it before ddyn_ekf_predict */
    double grade;                /* rad: the road's grade over the next prediction (ddyn_model_add_grade;
                                    0 after init: level); set like bank */
    ddyn_model_work work;
} ddyn_ekf;

ddyn_status ddyn_ekf_init(ddyn_ekf *ekf, const ddyn_vehicle_model *model, ddyn_discretisation disc,
                          const double x0[DDYN_NX], const double p0_diag[DDYN_NX], const double q_diag[DDYN_NX]);

/* Propagate over one sample time with input rates u and coefficients c. */
ddyn_status ddyn_ekf_predict(ddyn_ekf *ekf, const double u[DDYN_NU], const double c[DDYN_NC]);

/* Fuse a reading z of sensor `kind` with noise variances r_diag; nis (may be NULL) receives
 * the normalised innovation squared y' S^-1 y. On error the filter is left unchanged. */
ddyn_status ddyn_ekf_update(ddyn_ekf *ekf, ddyn_meas_kind kind, const double *z, const double *r_diag,
                            const double c[DDYN_NC], double *nis);

#ifdef __cplusplus
}
#endif

#endif /* DDYN_EKF_H */
