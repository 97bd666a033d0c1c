/*
 * ddyn/telemetry.h - the controller's telemetry over LCM (Linux host and SIL only).
 *
 * The controller hands plain C structs to the publish functions once per control
 * step; a rate limiter per message kind decides which of them go on the wire, so
 * the controller never has to know the rates. Counters that must not miss a step
 * (deadline misses, fault onsets, the longest step) are kept here from every call,
 * published or not.
 *
 * The wire format is the LCM types in lcmtypes/ (package ddyn_lcm), encoded with
 * the lcm-gen C code generated at build time. Messages are encoded into a fixed
 * buffer in the context; LCM itself allocates when the context is created and, for
 * some providers, when publishing. None of this is part of the embedded build:
 * CMake option DDYN_WITH_LCM (off for the Cortex-M7).
 *
 * The limiter counts control steps, not clock time: a kind published at rate R Hz
 * goes out on every N-th step, N = round(control rate / R), so jitter in the
 * controller's clock never drops or doubles a message, and SIL (simulated time)
 * and the car (monotonic clock) behave alike. docs/lcm.md.
 */
#ifndef DDYN_TELEMETRY_H
#define DDYN_TELEMETRY_H

#include <stdint.h>

#include "ddyn/model.h" /* DDYN_NX, DDYN_NU, DDYN_NC */

#ifdef __cplusplus
extern "C" {
#endif

typedef enum {
    DDYN_TM_STATE = 0,   /* channel <prefix>STATE, ddyn_lcm.state_estimate_t */
    DDYN_TM_COEFFS = 1,  /* channel <prefix>COEFFS, ddyn_lcm.guard_coeffs_t */
    DDYN_TM_PLAN = 2,    /* channel <prefix>PLAN, ddyn_lcm.mpc_plan_t */
    DDYN_TM_TIMING = 3,  /* channel <prefix>TIMING, ddyn_lcm.loop_timing_t */
    DDYN_TM_FAULTS = 4,  /* channel <prefix>FAULTS, ddyn_lcm.faults_t */
    DDYN_TM_KIND_COUNT = 5
} ddyn_tm_kind;

typedef enum {
    DDYN_TM_PUBLISHED = 0,    /* the message went to LCM */
    DDYN_TM_SKIPPED = 1,      /* the rate limiter held it back (not an error) */
    DDYN_TM_ERR_ARGUMENT = 2, /* null pointer, bad size, bad configuration */
    DDYN_TM_ERR_LCM = 3,      /* LCM could not be created or refused the message */
    DDYN_TM_ERR_ENCODE = 4    /* the message did not fit the encode buffer */
} ddyn_tm_status;

#define DDYN_TM_PLAN_MAX_HORIZON 100 /* longest MPC horizon a plan message carries */
#define DDYN_TM_MAX_STAGES 8         /* loop-timing stages per message */
#define DDYN_TM_FAULT_BITS 32
#define DDYN_TM_CHANNEL_MAX 64       /* channel name length, including the terminating zero */
#define DDYN_TM_DEFAULT_PREFIX "DDYN_"
#define DDYN_TM_DEFAULT_SAT_MARGIN 0.02 /* 2 % of the guard range */
/* largest encoded message: the plan at the longest horizon (fingerprint, header, arrays,
 * a status name of up to 63 characters), with room to spare */
#define DDYN_TM_BUFFER_SIZE (256 + 8 * DDYN_NX * (DDYN_TM_PLAN_MAX_HORIZON + 1) + 8 * DDYN_NU * DDYN_TM_PLAN_MAX_HORIZON)

/* ---- plain structs the controller fills (one per message kind) ---- */

typedef struct {
    int64_t utime;              /* controller clock at the step, microseconds */
    int64_t step;               /* control step number */
    double x[DDYN_NX];          /* x, y, yaw, vx, vy, omega, throttle, steering */
    double cov_diag[DDYN_NX];   /* diagonal of the estimate's covariance */
} ddyn_tm_state;

typedef struct {
    int64_t utime;
    int64_t step;
    double coeffs[DDYN_NC];     /* COEFF_NAMES order; the bounds are in the configuration */
} ddyn_tm_coeffs;

typedef struct {
    int64_t utime;
    int64_t step;
    int status;                 /* the MPC's status code (0: solved) */
    const char *status_name;    /* its name; NULL is sent as "" */
    int qp_iterations;
    double cost;
    int horizon;                /* N, 0 .. DDYN_TM_PLAN_MAX_HORIZON */
    const double *states;       /* (N + 1) x DDYN_NX, row-major: states[k * DDYN_NX + i] */
    const double *inputs;       /* N x DDYN_NU, row-major */
} ddyn_tm_plan;

typedef struct {
    int64_t utime;
    int64_t step;
    double period_s;            /* since the previous step started */
    double total_s;             /* this step's duration */
    double deadline_s;
    int n_stages;               /* 0 .. DDYN_TM_MAX_STAGES */
    const char *stage_names[DDYN_TM_MAX_STAGES];
    double stage_s[DDYN_TM_MAX_STAGES];
} ddyn_tm_timing;

typedef struct {
    int64_t utime;
    int64_t step;
    uint32_t active;            /* bit i: fault i active on this step (the controller's bit meanings) */
} ddyn_tm_faults;

/* ---- configuration and context ---- */

typedef struct {
    /* LCM provider URL, e.g. "udpm://239.255.76.67:7667?ttl=0", "file:///tmp/run.lcm?mode=w",
     * "memq://"; NULL: LCM's default (the LCM_DEFAULT_URL environment variable, else UDP multicast) */
    const char *url;
    /* an LCM instance to publish on instead of creating one (not destroyed by close); NULL: create */
    struct _lcm_t *lcm;
    const char *channel_prefix; /* NULL: DDYN_TM_DEFAULT_PREFIX */
    double control_rate_hz;     /* steps per second of the controller (> 0) */
    /* publish rate per kind, Hz: <= 0 never; at or above control_rate_hz every step */
    double rate_hz[DDYN_TM_KIND_COUNT];
    /* guard bounds of the coefficients (e.g. the exported network's lo/hi); NULL: no bounds
     * are sent (NaN) and nothing is flagged */
    const double *coeff_lo;
    const double *coeff_hi;
    double sat_margin;          /* fraction of (hi - lo); e.g. DDYN_TM_DEFAULT_SAT_MARGIN */
} ddyn_telemetry_config;

typedef struct {
    int64_t every;              /* publish every this many steps; 0: never */
    int64_t last_step;          /* step of the last message sent */
    int started;
    uint64_t published, skipped, errors;
} ddyn_tm_limiter;

/* Caller-owned context; all fields are private except the counters in `limiter`. */
typedef struct {
    struct _lcm_t *lcm;
    int owns_lcm;
    char channel[DDYN_TM_KIND_COUNT][DDYN_TM_CHANNEL_MAX];
    ddyn_tm_limiter limiter[DDYN_TM_KIND_COUNT];
    double coeff_lo[DDYN_NC], coeff_hi[DDYN_NC];
    int have_bounds;
    double sat_margin;
    /* kept from every call */
    int64_t deadline_misses;
    double max_total_s;         /* since the last timing message */
    uint32_t faults_prev, faults_latched;
    int64_t fault_onsets[DDYN_TM_FAULT_BITS];
    int64_t fault_active_steps[DDYN_TM_FAULT_BITS];
    uint8_t buffer[DDYN_TM_BUFFER_SIZE];
} ddyn_telemetry;

/* A configuration with the defaults: LCM's default URL, prefix DDYN_, every kind at
 * control_rate_hz except the plan and timing at a fifth of it, no coefficient bounds. */
void ddyn_telemetry_default_config(ddyn_telemetry_config *cfg, double control_rate_hz);

/* Open LCM (or take cfg->lcm) and set the limiters; DDYN_TM_PUBLISHED on success. */
ddyn_tm_status ddyn_telemetry_open(ddyn_telemetry *tm, const ddyn_telemetry_config *cfg);
void ddyn_telemetry_close(ddyn_telemetry *tm);

/* Call once per control step each; the limiter decides whether the message is sent. */
ddyn_tm_status ddyn_telemetry_publish_state(ddyn_telemetry *tm, const ddyn_tm_state *msg);
ddyn_tm_status ddyn_telemetry_publish_coeffs(ddyn_telemetry *tm, const ddyn_tm_coeffs *msg);
ddyn_tm_status ddyn_telemetry_publish_plan(ddyn_telemetry *tm, const ddyn_tm_plan *msg);
ddyn_tm_status ddyn_telemetry_publish_timing(ddyn_telemetry *tm, const ddyn_tm_timing *msg);
ddyn_tm_status ddyn_telemetry_publish_faults(ddyn_telemetry *tm, const ddyn_tm_faults *msg);

/* Saturation bit masks of coeffs against [lo, hi] (bit i: within margin * (hi - lo) of a bound). */
void ddyn_telemetry_saturation(const double coeffs[DDYN_NC], const double lo[DDYN_NC], const double hi[DDYN_NC],
                               double margin, uint32_t *saturated_lo, uint32_t *saturated_hi);

const char *ddyn_tm_status_name(ddyn_tm_status status);
const char *ddyn_tm_kind_name(ddyn_tm_kind kind); /* "STATE", "COEFFS", ... (the channel suffix) */

#ifdef __cplusplus
}
#endif

#endif /* DDYN_TELEMETRY_H */
