/*
 * ddyn/mpc.h - the raceline-tracking model predictive controller of the car (real-time iteration).
 *
 * Problem (the Deep Dynamics paper's MPC, with all 17 coefficients as run-time parameters):
 *
 *   min  sum_{k=1..H} w_k |p_k - r_k|^2_Q  +  sum_{k=0..H-1} |u_k|^2_R  +  sum_k (rho1 s_k + rho2 s_k^2)
 *   s.t. x_{k+1} = step(x_k, u_k, c)               (the generated discrete model, Euler or RK4)
 *        rate_lo <= u_k <= rate_hi                  (u = dthrottle, dsteering: the inputs ARE rates,
 *                                                     so R weights the input increments)
 *        state_lo <= (throttle, steering)_k <= state_hi   (states 6, 7, bounded as states)
 *        -width_right(r_k) - s_k <= n_k . (p_k - r_k) <= width_left(r_k) + s_k,  s_k >= 0
 *                                                   (soft track bounds: exact L1 + quadratic penalty,
 *                                                     so the QP is feasible from any state)
 *
 * p_k = (x, y) of the predicted state, r_k the raceline reference of stage k, n_k the raceline's
 * left normal there, w_k = 1 for k < H and q_terminal_scale for k = H. The references follow the
 * raceline's speed profile: r_0 is the projection of x0 onto the raceline, r_{k+1} lies
 * speed(r_k) * dt further along it (the paper's time-parameterised reference).
 *
 * Real-time iteration: each ddyn_mpc_solve does ONE Gauss-Newton SQP step around the previous
 * plan shifted by one period (the warm start): forward simulation and Jacobians of a generated
 * step (by default the MPC's own single-step RK4, else ddyn_model_step and
 * ddyn_model_step_jacobians), condensing onto the H*2 input rates, one
 * dense QP solved by a primal-dual interior-point method (Mehrotra predictor-corrector, Cholesky of
 * the condensed Hessian, soft-constraint slacks eliminated in closed form) with an iteration cap.
 *
 * Embedded rules: C99, no allocation, no recursion, no VLAs, every loop bounded by the
 * compile-time sizes below. Everything lives in the caller-owned ddyn_mpc (about 140 kB with the
 * defaults: lower DDYN_MPC_MAX_TRACK_POINTS / DDYN_MPC_MAX_HORIZON at compile time to shrink it).
 * Not thread-safe per context; contexts are independent.
 */
#ifndef DDYN_MPC_H
#define DDYN_MPC_H

#include "ddyn/model.h"
#include "ddyn/mpc_qp.h"
#include "ddyn/mpc_qp_daqp.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Compile-time capacities (override with -D...). The run-time horizon is cfg.horizon <= max. */
#ifndef DDYN_MPC_MAX_HORIZON
#define DDYN_MPC_MAX_HORIZON 20
#endif
#ifndef DDYN_MPC_MAX_TRACK_POINTS
#define DDYN_MPC_MAX_TRACK_POINTS 1024
#endif
#define DDYN_MPC_DEFAULT_HORIZON 20
#define DDYN_MPC_NV (DDYN_MPC_MAX_HORIZON * DDYN_NU)       /* QP variables: input rates */
#define DDYN_MPC_MAX_QP_ITERATIONS 50
/* default qp_cold_max_iterations: the interior point's cap for a QP that DAQP would start cold
 * (docs/m7.md: such a step at this cap stays within the Cortex-M7's 3 M-instruction target) */
#define DDYN_MPC_COLD_IPM_ITERATIONS 12

/* The prediction model's discretisation. */
typedef enum {
    DDYN_MPC_PRED_RK4_SINGLE = 0, /* default: one RK4 step per sample time, generated for the MPC with
                                     its Jacobians in one function (codegen/mpc.py): ~4x cheaper than
                                     the plant's 4-sub-step RK4, within ~0.5 mm of it over 10 steps */
    DDYN_MPC_PRED_EULER = 1,      /* the model's Euler step (cheapest; centimetres off at 50 Hz) */
    DDYN_MPC_PRED_RK4 = 2,        /* the model's RK4 step with the vehicle's sub-steps (the plant) */
    DDYN_MPC_PRED_COUNT = 3
} ddyn_mpc_prediction;

/* The QP solver (docs/mpc.md, "The QP solver against DAQP, PIQP and ProxQP"). */
typedef enum {
    DDYN_MPC_QP_DAQP = 0, /* default: DAQP's dual active-set core (mpc_qp_daqp.c), warm-started from the
                             last period's working set shifted one stage; qp_tolerance unused */
    DDYN_MPC_QP_IPM = 1,  /* the own dense interior point (mpc_qp.c), cold every period */
    DDYN_MPC_QP_COUNT = 2
} ddyn_mpc_qp_solver;

typedef struct {
    int horizon;                /* H, 1..DDYN_MPC_MAX_HORIZON (default 20) */
    ddyn_mpc_prediction prediction; /* prediction model (default DDYN_MPC_PRED_RK4_SINGLE) */
    double q_pos[2];            /* Q: weight of the x and y error to the reference, per stage */
    double q_terminal_scale;    /* the last stage's position weight is q_pos * this */
    double r_rate[DDYN_NU];     /* R: weight of dthrottle, dsteering (the input increments) */
    double rate_lo[DDYN_NU];    /* bounds of the inputs dthrottle, dsteering (vehicle input_limits) */
    double rate_hi[DDYN_NU];
    double state_lo[2];         /* bounds of the states throttle, steering (vehicle input_limits) */
    double state_hi[2];
    double slack_l1;            /* rho1: exact penalty of a track-bound violation, per metre */
    double slack_l2;            /* rho2: quadratic penalty, per square metre (> 0) */
    ddyn_mpc_qp_solver qp_solver; /* DDYN_MPC_QP_DAQP (default) or DDYN_MPC_QP_IPM */
    int qp_max_iterations;      /* QP iteration cap, 1..DDYN_MPC_MAX_QP_ITERATIONS; hitting it returns
                                   DDYN_ERR_QP_NOT_CONVERGED (the controller then shifts the last plan) */
    double qp_tolerance;        /* IPM: stop when residuals and mean complementarity are below this */
    int qp_cold_max_iterations; /* DAQP: a QP without a working set to start from (the first from a
                                   standstill, after ddyn_mpc_reset or a failed solve) is solved by the
                                   interior point with this cap, 1..DDYN_MPC_MAX_QP_ITERATIONS, and its
                                   active constraints start DAQP's next solve (docs/mpc.md) */
} ddyn_mpc_config;

/* Raceline table with the room to the track bounds (set once per track with ddyn_mpc_set_track). */
typedef struct {
    int n;                                      /* points of the closed raceline, 0 = none set */
    double length;                              /* m, closed-loop arc length */
    double s[DDYN_MPC_MAX_TRACK_POINTS];        /* arc length at each point */
    double x[DDYN_MPC_MAX_TRACK_POINTS];
    double y[DDYN_MPC_MAX_TRACK_POINTS];
    double speed[DDYN_MPC_MAX_TRACK_POINTS];    /* reference speed (m/s), > 0 */
    double width_left[DDYN_MPC_MAX_TRACK_POINTS];  /* usable room along the left normal (m) */
    double width_right[DDYN_MPC_MAX_TRACK_POINTS]; /* usable room along the right normal (m) */
    double speed_scale;  /* the reference speed is speed * speed_scale: 1 after ddyn_mpc_set_track; a
                            caller may lower it at run time (the controller's degraded-bus mode), (0, 1] */
    /* the road's bank profile (issue 34, ddyn_mpc_set_bank): the bank (rad, + tilting the road so that
     * gravity pulls to the left of the direction of travel) at each point; have_bank 0: a flat road */
    double bank[DDYN_MPC_MAX_TRACK_POINTS];
    int have_bank;
    /* the road's grade profile (issue 34, ddyn_mpc_set_grade): the grade (rad, + uphill in the direction of
     * travel) at each point; have_grade 0: a level road */
    double grade[DDYN_MPC_MAX_TRACK_POINTS];
    int have_grade;
} ddyn_mpc_track;

/* What one solve did. */
typedef struct {
    int qp_iterations;          /* QP iterations used */
    int converged;              /* 1 if the QP met qp_tolerance within qp_max_iterations */
    double kkt_residual;        /* final max(primal residual, dual residual, mean complementarity) */
    double max_slack;           /* largest track-bound slack of the plan (m): > 0 = the plan leaves the track */
    double max_bound_violation; /* largest violation of a hard bound (rates, throttle, steering) by the
                                   linearised plan before the command was clipped (0 when converged) */
    double cost;                /* QP objective at the returned plan (linearised) */
    double progress;            /* arc length of x0's projection on the raceline (m) */
    int track_index;            /* raceline segment of that projection */
    int qp_cold_start;          /* 1: DAQP had no working set, the interior point solved this QP */
} ddyn_mpc_info;

typedef struct {
    const ddyn_vehicle_model *model;
    ddyn_casadi_fn mpc_step;    /* the generated MPC step of this vehicle */
    ddyn_mpc_config cfg;
    double c[DDYN_NC];          /* coefficients the prediction uses (ddyn_mpc_set_coefficients) */
    int have_coefficients;
    double downforce;           /* s^2/m^2 (ddyn_mpc_set_downforce; 0: none) */
    ddyn_mpc_track track;
    int have_warm_start;        /* u_plan holds a plan from the previous solve (shifted) */
    int last_index;             /* raceline segment found last time: local search from here */
    /* plan: x_plan[k*8 + i] state i at stage k (k = 0..H), u_plan[k*2 + j] input j at stage k */
    double x_plan[(DDYN_MPC_MAX_HORIZON + 1) * DDYN_NX];
    double u_plan[DDYN_MPC_NV];
    /* stage references (k = 0..H): cost point (x, y), then the track-bound half-planes at the
     * projection of the predicted position: anchor (x, y), left normal (x, y), room left, right */
    double ref[(DDYN_MPC_MAX_HORIZON + 1) * 8];
    /* work memory (contents meaningless between calls) */
    double x_lin[(DDYN_MPC_MAX_HORIZON + 1) * DDYN_NX]; /* linearisation trajectory */
    double u_lin[DDYN_MPC_NV];
    double A[DDYN_MPC_MAX_HORIZON * DDYN_NX * DDYN_NX];
    double B[DDYN_MPC_MAX_HORIZON * DDYN_NX * DDYN_NU];
    double sens[2 * DDYN_MPC_MAX_HORIZON * DDYN_MPC_NV]; /* d(x, y)_k / du: stage k-1, row, column */
    /* real-time iteration split (ddyn_mpc_prepare / ddyn_mpc_feedback): the state the QP was built
     * at, d(x, y)_k / dx0 (stage k-1: row x then row y, 8 columns each), the held-throttle flag */
    double prep_x0[DDYN_NX];
    double ref_tangent[(DDYN_MPC_MAX_HORIZON + 1) * 2]; /* raceline tangent at each stage's cost point */
    double stage_bank[DDYN_MPC_MAX_HORIZON]; /* the bank each stage's prediction used (0 without a profile) */
    double stage_grade[DDYN_MPC_MAX_HORIZON]; /* the grade each stage's prediction used (0 without a profile) */
    double phi[2 * DDYN_MPC_MAX_HORIZON * DDYN_NX];
    int prepared;               /* 1 between a preparation and its feedback */
    int prep_hold;
    int prep_movable;
    int prep_index;
    int prep_cold;              /* DAQP: the prepared QP has no working set to start from */
    double prep_u0;
    /* known throttle rates of the first stages (ddyn_mpc_fix_throttle): fix_n stages, fix_u[k] */
    int fix_n;
    double fix_u[DDYN_MPC_MAX_HORIZON];
    ddyn_mpc_qp qp;
    ddyn_mpc_qp_daqp daqp;      /* DAQP's workspace and warm start (qp_solver DDYN_MPC_QP_DAQP) */
    ddyn_model_work model_work;
} ddyn_mpc;

/* Defaults for a vehicle: its input_limits (from the vehicle file, generated by `ddyn codegen model`),
 * horizon DDYN_MPC_DEFAULT_HORIZON, single-step RK4 prediction, the weights of docs/mpc.md. */
ddyn_status ddyn_mpc_default_config(const ddyn_vehicle_model *model, ddyn_mpc_config *cfg);

/* Check cfg and set up the context (no track, no coefficients, no warm start yet). */
ddyn_status ddyn_mpc_init(ddyn_mpc *mpc, const ddyn_vehicle_model *model, const ddyn_mpc_config *cfg);

/* The 17 coefficients (COEFF_NAMES order) the prediction model uses from the next solve on; call
 * every control period with the guard network's estimate. Non-finite -> DDYN_ERR_NONFINITE_INPUT
 * and the previous coefficients are kept. Nothing is regenerated: they are plain parameters. */
ddyn_status ddyn_mpc_set_coefficients(ddyn_mpc *mpc, const double c[DDYN_NC]);

/* A known downforce k (s^2/m^2, 0 <= k <= DDYN_MODEL_DOWNFORCE_MAX, issue 34): each prediction stage steps
 * the model with the coefficients of its own linearisation speed, D_f and D_r times 1 + k vx^2
 * (ddyn_model_downforce), and so does the launch bound of the references. 0 (the default): none. Out of
 * range (also NaN) -> DDYN_ERR_ARGUMENT, the previous value kept. The line's speeds are not raised: the
 * line was made for the car without it. */
ddyn_status ddyn_mpc_set_downforce(ddyn_mpc *mpc, double k);

/* The closed raceline: n points (4..DDYN_MPC_MAX_TRACK_POINTS, no repeated end point), the
 * reference speed at each (> 0) and the usable room from each point to the left and right track
 * bounds along the raceline's normal (already reduced by the car's half width and any margin; may
 * be negative where the raceline itself is too close). Clears the warm start. */
ddyn_status ddyn_mpc_set_track(ddyn_mpc *mpc, int n, const double *x, const double *y, const double *speed,
                               const double *width_left, const double *width_right);

/* The road's bank along the raceline (issue 34): bank[i] (rad, |bank| < DDYN_MPC_MAX_BANK, finite) at each
 * point of the track set last (n values, as ddyn_mpc_set_track's). Each prediction stage then steps the
 * generated model with the lateral gravity g sin(bank) (ddyn_<vehicle>_mpc_step's road input (bank, grade), the term of
 * train/model/effects.py) at the bank of its own track position: the projection of the stage's
 * predicted position on the raceline, linear between the points. bank NULL: back to a flat road. Only
 * with the single-step RK4 prediction (the generated step carries the term), else DDYN_ERR_ARGUMENT;
 * DDYN_ERR_NOT_READY without a track; a refused profile leaves the previous one. Clears the warm start. */
#define DDYN_MPC_MAX_BANK 0.7853981633974483 /* 45 degrees */
ddyn_status ddyn_mpc_set_bank(ddyn_mpc *mpc, const double *bank);

/* The road's grade along the raceline (issue 34): grade[i] (rad, + uphill in the direction of travel,
 * |grade| < DDYN_MPC_MAX_GRADE, finite) at each point, as ddyn_mpc_set_bank's bank: each prediction stage steps
 * the generated model with the longitudinal gravity -g sin(grade) (the generated step's road input, the term of
 * train/model/effects.py's grade) at its own track position. The same refusals; clears the warm start. */
#define DDYN_MPC_MAX_GRADE 0.3490658503988659 /* 20 degrees: a 36 % slope */
ddyn_status ddyn_mpc_set_grade(ddyn_mpc *mpc, const double *grade);

/* The grade profile at segment i, parameter u (as ddyn_mpc_track_bank). */
double ddyn_mpc_track_grade(const ddyn_mpc_track *t, int i, double u);

/* The road at the projection of (px, py) on the raceline, one search for both: road[0] the bank, road[1] the
 * grade (each 0 without its profile); *hint as ddyn_mpc_bank_at's. */
void ddyn_mpc_road_at(const ddyn_mpc *mpc, double px, double py, int *hint, double road[2]);

/* The bank profile at segment i (0..n-1), parameter u in [0, 1] (linear between the points; 0 without a
 * profile or out-of-range arguments). */
double ddyn_mpc_track_bank(const ddyn_mpc_track *t, int i, double u);

/* The bank at the projection of (px, py) on the raceline, searched +-DDYN_MPC_BANK_WINDOW segments around
 * *hint (every segment when *hint < 0 or hint NULL), *hint updated to the segment found; 0 without a
 * profile or for a non-finite position. Bounded: at most n segment distances. */
#define DDYN_MPC_BANK_WINDOW 40
double ddyn_mpc_bank_at(const ddyn_mpc *mpc, double px, double py, int *hint);

/* One real-time iteration from the current state x0 (8 states).
 * Returns DDYN_OK: u (2 input rates) is the first input of the new plan.
 *   DDYN_ERR_QP_NOT_CONVERGED: the QP hit its iteration cap; u is the last iterate's first input
 *     clipped to the rate bounds (finite, defined), the plan is that iterate; info says how far
 *     it was. The caller decides whether to apply it.
 *   DDYN_ERR_NONFINITE_INPUT (NaN/inf in x0 or the coefficients), DDYN_ERR_NOT_READY (no track or
 *     no coefficients), DDYN_ERR_ARGUMENT (null pointer), DDYN_ERR_NONFINITE_OUTPUT / _EVALUATION
 *     (the model failed along the prediction): u = {0, 0} (hold throttle and steering), the plan
 *     and the warm start are left as they were.
 * u is never NaN. info may be NULL. */
ddyn_status ddyn_mpc_solve(ddyn_mpc *mpc, const double x0[DDYN_NX], double u[DDYN_NU], ddyn_mpc_info *info);

/* The real-time iteration in two phases, as acados splits it: the expensive part before the
 * measurement, a short one after it.
 * ddyn_mpc_prepare(x0_pred): linearise along the shifted plan from the predicted state x0_pred
 *   (e.g. the last estimate stepped with the command just sent), the sensitivities, the track
 *   references, the QP at x0_pred, and d(x, y)_k / dx0. Returns as ddyn_mpc_solve's errors; on
 *   success the context is prepared.
 * ddyn_mpc_feedback(x0): the QP moved to the measured x0 to first order (gradient and bounds by
 *   d(x, y)_k / dx0 (x0 - x0_pred); throttle and steering exactly), solved; u and the plan as
 *   ddyn_mpc_solve. DDYN_ERR_NOT_READY when not prepared. With x0 == x0_pred it is ddyn_mpc_solve.
 * ddyn_mpc_solve(x0) = ddyn_mpc_prepare(x0) then ddyn_mpc_feedback(x0). */
ddyn_status ddyn_mpc_prepare(ddyn_mpc *mpc, const double x0_pred[DDYN_NX]);
ddyn_status ddyn_mpc_feedback(ddyn_mpc *mpc, const double x0[DDYN_NX], double u[DDYN_NU], ddyn_mpc_info *info);

/* As ddyn_mpc_solve, with the throttle held (a speed controller outside the MPC sets it): the plan's
 * throttle-rate inputs are fixed, dthrottle0 at stage 0 (clipped to the rate bounds) and 0 after,
 * so the predicted throttle is x0's + dt * dthrottle0 at every later stage, and the QP optimises
 * the steering rates alone. The throttle columns are taken out of the QP (no cost, no coupling to
 * the position costs or the track rows; their own rows relaxed) so that its steering part is
 * exactly the steering-only problem; the plan's throttle inputs are the fixed ones, and u[0] is
 * dthrottle0 (clipped). Returns and u as ddyn_mpc_solve (u = {0, 0} on the errors that return it).
 * ddyn_mpc_solve and this function may alternate; the warm start's steering carries over. */
ddyn_status ddyn_mpc_solve_held_throttle(ddyn_mpc *mpc, const double x0[DDYN_NX], double dthrottle0,
                                         double u[DDYN_NU], ddyn_mpc_info *info);

/* Known throttle rates of the first n stages (issue 34: a throttle delay longer than the steering's, whose
 * commands still in the pipe act over the MPC's first stages; ddyn/controller.h): from the next
 * preparation or solve on, stage k < n of the plan runs dthrottle[k] (clipped to the rate bounds), its
 * QP column taken out (decoupled from the cost and the track rows, its own rows relaxed, and a weight
 * DDYN_MPC_FIX_WEIGHT times the throttle-rate weight that keeps it at 0 where a later stage's
 * throttle bound pulls on it), and the plan's inputs there are the known ones: the planned throttle
 * the caller sends now is the plan's stage n. n = 0: none (the default; the MPC as before). Kept until
 * the next call; ddyn_mpc_solve_held_throttle ignores it. DDYN_ERR_ARGUMENT for n outside
 * 0..horizon - 1 or a non-finite rate (the previous setting kept). */
#define DDYN_MPC_FIX_WEIGHT 1e6
ddyn_status ddyn_mpc_fix_throttle(ddyn_mpc *mpc, int n, const double *dthrottle);
/* The raceline table's reference speed (speed_scale already in the table) at the projection of
 * x0's position: searched around the last solve's projection, as the next solve will (the whole
 * raceline before the first solve). DDYN_ERR_NOT_READY without a track, DDYN_ERR_NONFINITE_INPUT
 * for a non-finite position; *speed is then 0. Does not change the context. */
ddyn_status ddyn_mpc_reference_speed(const ddyn_mpc *mpc, const double x0[DDYN_NX], double ahead, double *speed);

/* The plan of the last successful (or not converged) solve: u_plan H*2 and x_plan (H+1)*8, the
 * states predicted by the nonlinear model from that solve's x0 (simulated here, on demand; either
 * may be NULL). Returns the horizon H, 0 if there is no plan yet or the simulation failed. */
int ddyn_mpc_plan(ddyn_mpc *mpc, double *x_plan, double *u_plan);

/* The input rates u_plan (H*2) of the last successful (or not converged) solve, copied as they are:
 * no simulation, so it costs nothing and cannot fail once a plan exists (the controller's shifted-plan
 * fallback relies on that). Returns H, or 0 if there is no plan yet. */
int ddyn_mpc_plan_inputs(const ddyn_mpc *mpc, double *u_plan);

/* Forget the warm start (e.g. after a discontinuity in the state); the next solve starts from
 * zero input rates and a global search for the raceline position. */
void ddyn_mpc_reset(ddyn_mpc *mpc);

#ifdef __cplusplus
}
#endif

#endif /* DDYN_MPC_H */
