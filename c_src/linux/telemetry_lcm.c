/*
 * telemetry_lcm.c - the controller's telemetry over LCM (ddyn/telemetry.h).
 *
 * Each publish function first updates what must count every step (deadline
 * misses, the longest step, fault onsets), then asks the kind's limiter, then
 * copies the plain struct into the lcm-gen struct, encodes it into the context's
 * fixed buffer and hands the bytes to lcm_publish. The lcm-gen structs hold
 * non-const pointers; they point at the caller's data only for the duration of
 * the encode, which does not write through them.
 */
#include "ddyn/telemetry.h"

#include <math.h>
#include <stdio.h>
#include <string.h>

#include <lcm/lcm.h>

#include "ddyn_lcm_faults_t.h"
#include "ddyn_lcm_guard_coeffs_t.h"
#include "ddyn_lcm_loop_timing_t.h"
#include "ddyn_lcm_mpc_plan_t.h"
#include "ddyn_lcm_state_estimate_t.h"

static const char *const kind_names[DDYN_TM_KIND_COUNT] = {"STATE", "COEFFS", "PLAN", "TIMING", "FAULTS"};

/* the message fields have fixed sizes: the telemetry API's must agree */
typedef char ddyn_tm_check_nx[(sizeof(((ddyn_lcm_state_estimate_t *)0)->cov_diag) == DDYN_NX * sizeof(double)) ? 1 : -1];
typedef char ddyn_tm_check_nc[(sizeof(((ddyn_lcm_guard_coeffs_t *)0)->coeffs) == DDYN_NC * sizeof(double)) ? 1 : -1];
typedef char ddyn_tm_check_bits[(sizeof(((ddyn_lcm_faults_t *)0)->onsets) == DDYN_TM_FAULT_BITS * sizeof(int64_t)) ? 1 : -1];

const char *ddyn_tm_kind_name(ddyn_tm_kind kind)
{
    return (kind >= 0 && kind < DDYN_TM_KIND_COUNT) ? kind_names[kind] : "UNKNOWN";
}

const char *ddyn_tm_status_name(ddyn_tm_status status)
{
    switch (status) {
    case DDYN_TM_PUBLISHED: return "published";
    case DDYN_TM_SKIPPED: return "skipped by the rate limiter";
    case DDYN_TM_ERR_ARGUMENT: return "bad argument";
    case DDYN_TM_ERR_LCM: return "LCM error";
    case DDYN_TM_ERR_ENCODE: return "message does not fit the encode buffer";
    }
    return "unknown status";
}

void ddyn_telemetry_default_config(ddyn_telemetry_config *cfg, double control_rate_hz)
{
    int k;
    memset(cfg, 0, sizeof *cfg);
    cfg->control_rate_hz = control_rate_hz;
    for (k = 0; k < DDYN_TM_KIND_COUNT; ++k) {
        cfg->rate_hz[k] = control_rate_hz;
    }
    /* the plan is the largest message and timing is read by people: a fifth is plenty */
    cfg->rate_hz[DDYN_TM_PLAN] = control_rate_hz / 5.0;
    cfg->rate_hz[DDYN_TM_TIMING] = control_rate_hz / 5.0;
    cfg->sat_margin = DDYN_TM_DEFAULT_SAT_MARGIN;
}

/* steps between messages for a rate: 0 never, else round(control / rate), at least 1 */
static int64_t decimation(double control_rate_hz, double rate_hz)
{
    double n;
    if (!(rate_hz > 0.0)) {
        return 0;
    }
    n = floor(control_rate_hz / rate_hz + 0.5);
    if (n < 1.0) {
        return 1;
    }
    return n > 1e9 ? (int64_t)1000000000 : (int64_t)n;
}

ddyn_tm_status ddyn_telemetry_open(ddyn_telemetry *tm, const ddyn_telemetry_config *cfg)
{
    const char *prefix;
    int k;
    if (tm == NULL || cfg == NULL || !(cfg->control_rate_hz > 0.0) || !isfinite(cfg->control_rate_hz)) {
        return DDYN_TM_ERR_ARGUMENT;
    }
    if ((cfg->coeff_lo == NULL) != (cfg->coeff_hi == NULL) || !(cfg->sat_margin >= 0.0 && cfg->sat_margin < 0.5)) {
        return DDYN_TM_ERR_ARGUMENT;
    }
    prefix = cfg->channel_prefix != NULL ? cfg->channel_prefix : DDYN_TM_DEFAULT_PREFIX;
    memset(tm, 0, sizeof *tm);
    for (k = 0; k < DDYN_TM_KIND_COUNT; ++k) {
        int n = snprintf(tm->channel[k], sizeof tm->channel[k], "%s%s", prefix, kind_names[k]);
        if (n < 0 || (size_t)n >= sizeof tm->channel[k]) {
            return DDYN_TM_ERR_ARGUMENT;
        }
        tm->limiter[k].every = decimation(cfg->control_rate_hz, cfg->rate_hz[k]);
    }
    tm->have_bounds = cfg->coeff_lo != NULL;
    for (k = 0; k < DDYN_NC; ++k) {
        tm->coeff_lo[k] = tm->have_bounds ? cfg->coeff_lo[k] : NAN;
        tm->coeff_hi[k] = tm->have_bounds ? cfg->coeff_hi[k] : NAN;
    }
    tm->sat_margin = cfg->sat_margin;
    if (cfg->lcm != NULL) {
        tm->lcm = cfg->lcm;
        tm->owns_lcm = 0;
    } else {
        tm->lcm = lcm_create(cfg->url);
        tm->owns_lcm = 1;
        if (tm->lcm == NULL) {
            return DDYN_TM_ERR_LCM;
        }
    }
    return DDYN_TM_PUBLISHED;
}

void ddyn_telemetry_close(ddyn_telemetry *tm)
{
    if (tm != NULL && tm->lcm != NULL && tm->owns_lcm) {
        lcm_destroy(tm->lcm);
    }
    if (tm != NULL) {
        tm->lcm = NULL;
    }
}

/* Whether this step's message of the kind goes out: the first one does, then every
 * `every` steps; a step number that goes backwards (a restart) starts over. */
static int limiter_allows(ddyn_tm_limiter *lim, int64_t step)
{
    if (lim->every == 0) {
        ++lim->skipped;
        return 0;
    }
    if (!lim->started || step < lim->last_step || step - lim->last_step >= lim->every) {
        lim->started = 1;
        lim->last_step = step;
        return 1;
    }
    ++lim->skipped;
    return 0;
}

static ddyn_tm_status send(ddyn_telemetry *tm, ddyn_tm_kind kind, int encoded)
{
    if (encoded < 0) {
        ++tm->limiter[kind].errors;
        return DDYN_TM_ERR_ENCODE;
    }
    if (lcm_publish(tm->lcm, tm->channel[kind], tm->buffer, (unsigned int)encoded) != 0) {
        ++tm->limiter[kind].errors;
        return DDYN_TM_ERR_LCM;
    }
    ++tm->limiter[kind].published;
    return DDYN_TM_PUBLISHED;
}

ddyn_tm_status ddyn_telemetry_publish_state(ddyn_telemetry *tm, const ddyn_tm_state *msg)
{
    ddyn_lcm_state_estimate_t m;
    if (tm == NULL || msg == NULL || tm->lcm == NULL) {
        return DDYN_TM_ERR_ARGUMENT;
    }
    if (!limiter_allows(&tm->limiter[DDYN_TM_STATE], msg->step)) {
        return DDYN_TM_SKIPPED;
    }
    m.utime = msg->utime;
    m.step = msg->step;
    m.x = msg->x[0];
    m.y = msg->x[1];
    m.yaw = msg->x[2];
    m.vx = msg->x[3];
    m.vy = msg->x[4];
    m.omega = msg->x[5];
    m.throttle = msg->x[6];
    m.steering = msg->x[7];
    memcpy(m.cov_diag, msg->cov_diag, sizeof m.cov_diag);
    return send(tm, DDYN_TM_STATE, ddyn_lcm_state_estimate_t_encode(tm->buffer, 0, (int)sizeof tm->buffer, &m));
}

void ddyn_telemetry_saturation(const double coeffs[DDYN_NC], const double lo[DDYN_NC], const double hi[DDYN_NC],
                               double margin, uint32_t *saturated_lo, uint32_t *saturated_hi)
{
    int i;
    *saturated_lo = 0u;
    *saturated_hi = 0u;
    for (i = 0; i < DDYN_NC; ++i) {
        double band = margin * (hi[i] - lo[i]);
        /* a NaN coefficient or bound compares false: never flagged (the NaN itself is sent) */
        if (coeffs[i] <= lo[i] + band) {
            *saturated_lo |= 1u << i;
        }
        if (coeffs[i] >= hi[i] - band) {
            *saturated_hi |= 1u << i;
        }
    }
}

ddyn_tm_status ddyn_telemetry_publish_coeffs(ddyn_telemetry *tm, const ddyn_tm_coeffs *msg)
{
    ddyn_lcm_guard_coeffs_t m;
    uint32_t sat_lo = 0u, sat_hi = 0u;
    if (tm == NULL || msg == NULL || tm->lcm == NULL) {
        return DDYN_TM_ERR_ARGUMENT;
    }
    if (!limiter_allows(&tm->limiter[DDYN_TM_COEFFS], msg->step)) {
        return DDYN_TM_SKIPPED;
    }
    if (tm->have_bounds) {
        ddyn_telemetry_saturation(msg->coeffs, tm->coeff_lo, tm->coeff_hi, tm->sat_margin, &sat_lo, &sat_hi);
    }
    m.utime = msg->utime;
    m.step = msg->step;
    memcpy(m.coeffs, msg->coeffs, sizeof m.coeffs);
    memcpy(m.lo, tm->coeff_lo, sizeof m.lo);
    memcpy(m.hi, tm->coeff_hi, sizeof m.hi);
    m.margin = tm->sat_margin;
    m.saturated_lo = (int32_t)sat_lo;
    m.saturated_hi = (int32_t)sat_hi;
    return send(tm, DDYN_TM_COEFFS, ddyn_lcm_guard_coeffs_t_encode(tm->buffer, 0, (int)sizeof tm->buffer, &m));
}

ddyn_tm_status ddyn_telemetry_publish_plan(ddyn_telemetry *tm, const ddyn_tm_plan *msg)
{
    ddyn_lcm_mpc_plan_t m;
    double *state_rows[DDYN_TM_PLAN_MAX_HORIZON + 1];
    double *input_rows[DDYN_TM_PLAN_MAX_HORIZON];
    int k;
    if (tm == NULL || msg == NULL || tm->lcm == NULL || msg->horizon < 0 || msg->horizon > DDYN_TM_PLAN_MAX_HORIZON
        || msg->states == NULL || (msg->horizon > 0 && msg->inputs == NULL)) {
        return DDYN_TM_ERR_ARGUMENT;
    }
    if (!limiter_allows(&tm->limiter[DDYN_TM_PLAN], msg->step)) {
        return DDYN_TM_SKIPPED;
    }
    for (k = 0; k <= msg->horizon; ++k) {
        state_rows[k] = (double *)(msg->states + (size_t)k * DDYN_NX);
    }
    for (k = 0; k < msg->horizon; ++k) {
        input_rows[k] = (double *)(msg->inputs + (size_t)k * DDYN_NU);
    }
    m.utime = msg->utime;
    m.step = msg->step;
    m.status = (int32_t)msg->status;
    m.status_name = (char *)(msg->status_name != NULL ? msg->status_name : "");
    m.qp_iterations = (int32_t)msg->qp_iterations;
    m.cost = msg->cost;
    m.horizon = (int32_t)msg->horizon;
    m.n_states = (int32_t)msg->horizon + 1;
    m.states = state_rows;
    m.inputs = input_rows;
    return send(tm, DDYN_TM_PLAN, ddyn_lcm_mpc_plan_t_encode(tm->buffer, 0, (int)sizeof tm->buffer, &m));
}

ddyn_tm_status ddyn_telemetry_publish_timing(ddyn_telemetry *tm, const ddyn_tm_timing *msg)
{
    ddyn_lcm_loop_timing_t m;
    char *names[DDYN_TM_MAX_STAGES];
    double stage_s[DDYN_TM_MAX_STAGES];
    int missed, k;
    if (tm == NULL || msg == NULL || tm->lcm == NULL || msg->n_stages < 0 || msg->n_stages > DDYN_TM_MAX_STAGES) {
        return DDYN_TM_ERR_ARGUMENT;
    }
    /* counted on every step, so a decimated stream still reports every miss and the worst step */
    missed = msg->total_s > msg->deadline_s;
    tm->deadline_misses += missed;
    if (msg->total_s > tm->max_total_s || isnan(msg->total_s)) {
        tm->max_total_s = msg->total_s;
    }
    if (!limiter_allows(&tm->limiter[DDYN_TM_TIMING], msg->step)) {
        return DDYN_TM_SKIPPED;
    }
    for (k = 0; k < msg->n_stages; ++k) {
        names[k] = (char *)(msg->stage_names[k] != NULL ? msg->stage_names[k] : "");
        stage_s[k] = msg->stage_s[k];
    }
    m.utime = msg->utime;
    m.step = msg->step;
    m.period_s = msg->period_s;
    m.total_s = msg->total_s;
    m.deadline_s = msg->deadline_s;
    m.deadline_missed = (int8_t)missed;
    m.deadline_misses = tm->deadline_misses;
    m.max_total_s = tm->max_total_s;
    m.n_stages = (int32_t)msg->n_stages;
    m.stage_names = names;
    m.stage_s = stage_s;
    tm->max_total_s = 0.0;
    return send(tm, DDYN_TM_TIMING, ddyn_lcm_loop_timing_t_encode(tm->buffer, 0, (int)sizeof tm->buffer, &m));
}

ddyn_tm_status ddyn_telemetry_publish_faults(ddyn_telemetry *tm, const ddyn_tm_faults *msg)
{
    ddyn_lcm_faults_t m;
    int i;
    if (tm == NULL || msg == NULL || tm->lcm == NULL) {
        return DDYN_TM_ERR_ARGUMENT;
    }
    for (i = 0; i < DDYN_TM_FAULT_BITS; ++i) {
        uint32_t bit = 1u << i;
        if (msg->active & bit) {
            ++tm->fault_active_steps[i];
            tm->fault_onsets[i] += (tm->faults_prev & bit) == 0u;
        }
    }
    tm->faults_prev = msg->active;
    tm->faults_latched |= msg->active;
    if (!limiter_allows(&tm->limiter[DDYN_TM_FAULTS], msg->step)) {
        return DDYN_TM_SKIPPED;
    }
    m.utime = msg->utime;
    m.step = msg->step;
    m.active = (int32_t)msg->active;
    m.latched = (int32_t)tm->faults_latched;
    memcpy(m.onsets, tm->fault_onsets, sizeof m.onsets);
    memcpy(m.active_steps, tm->fault_active_steps, sizeof m.active_steps);
    return send(tm, DDYN_TM_FAULTS, ddyn_lcm_faults_t_encode(tm->buffer, 0, (int)sizeof tm->buffer, &m));
}
