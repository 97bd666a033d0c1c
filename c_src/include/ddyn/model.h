/*
 * ddyn/model.h - the vehicle model on the car: one discrete step and its Jacobians.
 *
 * The equations are not written here: they are generated from the one Python
 * definition (train/model/single_track.py) by `ddyn codegen model` into c_src/generated/. This
 * module wraps the generated functions behind a small API with input checks and
 * caller-owned, fixed-size work memory (no allocation, C99).
 *
 * Layout: state x[8] = x, y, yaw, vx, vy, omega, throttle, steering;
 * input u[2] = dthrottle, dsteering; coefficients c[17] = Bf Cf Df Ef Gf Kf
 * Br Cr Dr Er Gr Kr Cm1 Cm2 Cr0 Cd Iz. Jacobians are dense column-major:
 * A[8*8] = dx+/dx, B[8*2] = dx+/du, P[8*17] = dx+/dc (element (i, j) at [j*8 + i]).
 */
#ifndef DDYN_MODEL_H
#define DDYN_MODEL_H

#ifdef __cplusplus
extern "C" {
#endif

#define DDYN_NX 8
#define DDYN_NU 2
#define DDYN_NC 17

#include "ddyn_model_dims.h" /* generated: work sizes, sensor kinds (ddyn_meas_kind) and their dimensions */

#include "ddyn/status.h" /* ddyn_status: the one error type of the runtime */

typedef enum { DDYN_DISC_EULER = 0, DDYN_DISC_RK4 = 1, DDYN_DISC_COUNT = 2 } ddyn_discretisation;

/* The CasADi calling convention: f(arg, res, iw, w, mem). */
typedef int (*ddyn_casadi_fn)(const double **arg, double **res, int *iw, double *w, int mem);

/* A generated vehicle model (instances are in the generated ddyn_models.c). */
typedef struct {
    const char *name;
    double sample_time;             /* s */
    int rk4_substeps;
    double known[4];                /* mass (kg), lf (m), lr (m), v_min (m/s) */
    const char *vehicle_sha256;     /* hash of the vehicle file it was generated from */
    ddyn_casadi_fn step[DDYN_DISC_COUNT];
    ddyn_casadi_fn step_jac[DDYN_DISC_COUNT];
    ddyn_casadi_fn deriv;
    ddyn_casadi_fn meas[DDYN_MEAS_COUNT]; /* (x, c) -> (h, H), H dense column-major */
} ddyn_vehicle_model;

/* Work memory for any generated model function; owned by the caller, reusable. */
typedef struct {
    double w[DDYN_MODEL_MAX_SZ_W];
    int iw[DDYN_MODEL_MAX_SZ_IW];
} ddyn_model_work;

/* The generated model of the named vehicle, or NULL. */
const ddyn_vehicle_model *ddyn_model_find(const char *name);

/* x_next = step(x, u, c) over one sample time. On error x_next is left unchanged. */
ddyn_status ddyn_model_step(const ddyn_vehicle_model *model, ddyn_discretisation disc,
                            const double x[DDYN_NX], const double u[DDYN_NU], const double c[DDYN_NC],
                            double x_next[DDYN_NX], ddyn_model_work *work);

/* Jacobians of the step (any of A, B, P may be NULL when not wanted). */
ddyn_status ddyn_model_step_jacobians(const ddyn_vehicle_model *model, ddyn_discretisation disc,
                                      const double x[DDYN_NX], const double u[DDYN_NU],
                                      const double c[DDYN_NC], double A[DDYN_NX * DDYN_NX],
                                      double B[DDYN_NX * DDYN_NU], double P[DDYN_NX * DDYN_NC],
                                      ddyn_model_work *work);

/* The road's bank (issue 34): its lateral gravity g sin(bank) (m/s^2, + to the left: dvy), the term of
 * train/model/effects.py (bank_angle, G = DDYN_GRAVITY). The MPC's generated step carries it as an input
 * (ddyn_mpc_set_bank); the vehicle's own steps (the filter's, the controller's pipe) have none, and
 * ddyn_model_add_bank adds the term held over a step of dt to their x_next: dvy = a dt, the position
 * a dt^2 / 2 along the car's left normal at x's yaw (a constant acceleration integrated exactly; its
 * coupling through the tyres' slip within the step is left to the filter's updates). */
#define DDYN_GRAVITY 9.81
double ddyn_model_bank_accel(double bank);
void ddyn_model_add_bank(double bank, double dt, const double x[DDYN_NX], double x_next[DDYN_NX]);
/* The road's grade (issue 34): its longitudinal gravity -g sin(grade) (m/s^2, + uphill: dvx), the term of
 * train/model/effects.py (grade); added to a vehicle step's x_next as the bank's is (dvx = a dt, the position
 * a dt^2 / 2 along x's heading). */
double ddyn_model_grade_accel(double grade);
void ddyn_model_add_grade(double grade, double dt, const double x[DDYN_NX], double x_next[DDYN_NX]);

/* Downforce (issue 34): the tyres' peak forces D_f, D_r (coefficients 2 and 8) scaled by 1 + k vx^2, the
 * term of train/model/effects.py (downforce, k in s^2/m^2) and of the SIL plant. The generated model has
 * no such term: the runtime evaluates it with the coefficients of the state's own speed, out = c with
 * those two scaled at vx (the filter's, the pipe's and each MPC stage's own state; the Jacobians then
 * lack d(scale)/dvx, a second-order term of the linearisation). k = 0 copies c bit-identically. */
#define DDYN_MODEL_DF_INDEX 2
#define DDYN_MODEL_DR_INDEX 8
#define DDYN_MODEL_DOWNFORCE_MAX 0.5 /* s^2/m^2: doubles the tyre load at 1.4 m/s (a 1:43 car's range) */
void ddyn_model_downforce(const double c[DDYN_NC], double k, double vx, double out[DDYN_NC]);
/* The coefficients to evaluate the model with at speed vx: c itself without a downforce (k = 0, no copy), else
 * ddyn_model_downforce's into buf. */
const double *ddyn_model_coeffs_at(const double c[DDYN_NC], double k, double vx, double buf[DDYN_NC]);

/* Continuous-time derivative xdot = f(x, u, c). */
/* 1 when v[0..n) holds no NaN or inf: the NaN/inf guard every runtime module uses on its inputs.
 * Under -ffast-math (-ffinite-math-only) the compiler may assume no NaN or inf exists and fold
 * isfinite() to 1: every such check of the runtime would vanish without a word. Refuse to build. */
#if defined(__FAST_MATH__) || (defined(__FINITE_MATH_ONLY__) && __FINITE_MATH_ONLY__)
#error "ddyn: the runtime's NaN/inf checks need IEEE semantics; do not build it with -ffast-math or -ffinite-math-only"
#endif
int ddyn_all_finite(const double *v, int n);

ddyn_status ddyn_model_derivatives(const ddyn_vehicle_model *model, const double x[DDYN_NX],
                                   const double u[DDYN_NU], const double c[DDYN_NC], double xdot[DDYN_NX],
                                   ddyn_model_work *work);

/* Sensor model: h[dim] = what sensor `kind` reads in state x, H[dim * 8] = dh/dx (column-major). */
ddyn_status ddyn_model_measure(const ddyn_vehicle_model *model, ddyn_meas_kind kind, const double x[DDYN_NX],
                               const double c[DDYN_NC], double h[DDYN_MEAS_MAX_DIM],
                               double H[DDYN_MEAS_MAX_DIM * DDYN_NX], ddyn_model_work *work);

/* Number of components of a sensor kind (0 for an unknown kind). */
int ddyn_meas_dim(ddyn_meas_kind kind);


#ifdef __cplusplus
}
#endif

#endif /* DDYN_MODEL_H */
