/*
 * ddyn_controller: the car's controller process, and the SIL's (Linux). The c_src runtime
 * (ddyn/controller.h: EKF -> history -> guard network -> MPC) behind the drive-by-wire protocol
 * (controller_node.h frame checks, can/ddyn_dbw.dbc) on a SocketCAN interface. It talks to the
 * car, or to the SIL's plant, ONLY through CAN frames.
 *
 * usage: ddyn_controller CONFIG.json            run (exit 0 after a clean end, 2 on a refused config)
 *        ddyn_controller --check CONFIG.json    validate, print the configuration with its defaults
 *        ddyn_controller --keys                 every configuration key, its type, range and meaning
 *        ddyn_controller --checkpoint-hash      the sha256 of the checkpoint the built-in network came from
 *
 * The configuration (controller_config.h, docs/deploy.md) names the CAN interface, the control
 * period, the raceline, the coefficients' source and the network's checkpoint hash (a network built
 * for another checkpoint is refused), MPC settings, telemetry and the real-time settings.
 *
 * Real time (controller_rt.h): mlockall, CPU affinity and SCHED_FIFO when permitted (a warning
 * otherwise), then one of two pacings:
 *   frame (default): a period runs when a GNSS_Position frame arrives (the sensors send it last in
 *     their period), or on the controller's own timer when none has come for 1.5 periods (then
 *     every period until one comes), at absolute deadlines from the last period, so the car is
 *     commanded (safely) when the sensors fall silent. Time is counted in periods: it runs
 *     unchanged in real time and in lock-step with a faster-than-real-time SIL plant
 *     (realtime.lockstep_silence > 0: the timer runs only after that much wall time without any frame).
 *   timer: a period at every absolute deadline t0 + k * period (clock_nanosleep TIMER_ABSTIME), with
 *     the frames received since the last one.
 * Each period: the readings -> ddyn_ctrl_step (with a prepared MPC, only its feedback phase) -> the
 * command frame out -> ddyn_ctrl_prepare for the next period (control.prepare, the RTI split of
 * docs/controller.md) -> wait. A period whose command leaves later than one period after its start
 * (timer: after the next deadline) is an overrun; counted, in the metrics and on stdout, and in
 * the telemetry's FAULTS bits.
 *
 * Frame authentication (docs/can.md, AUTOSAR SecOC style): with a key (can.key_file, else
 * $DDYN_DBW_KEY_FILE) every frame it reads must be followed by its sender's authenticator that
 * verifies (controller_node.h; forged, replayed and stale frames are counted in the metrics' "auth"
 * and dropped), and every command goes out with its authenticator right after it.
 *
 * With telemetry.lcm_url (a build with DDYN_WITH_LCM) it publishes the telemetry live over LCM
 * (ddyn/telemetry.h, c_src/linux/telemetry_lcm.c): every period the state estimate with its
 * covariance diagonal, the coefficients with the guard bounds, the fault bits; the MPC plan and the
 * loop timing at a fifth of the control rate. utime = period number x period, step = period number.
 *
 * Writes telemetry.metrics (JSON: loop time median/p99/max, preparation time, overruns, status
 * and frame counts, safe-state timing, the real-time settings in effect) and telemetry.log (CSV,
 * one row per period).
 */
#define _POSIX_C_SOURCE 200809L
#include <errno.h>
#include <fcntl.h>
#include <linux/can.h>
#include <linux/can/raw.h>
#include <math.h>
#include <net/if.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include "controller_config.h"
#include "controller_node.h"
#include "controller_rt.h"

#ifdef DDYN_SIL_WITH_LCM
#include "ddyn/telemetry.h"
#endif

#define MAX_STEPS DDYN_APP_MAX_STEPS /* periods whose timings are kept for the metrics */

extern const ddyn_net_tables ddyn_net_weights;

static ddyn_app_config cfg;  /* large: static storage, not the stack */
static ddyn_sil_node node;
static double loop_us[MAX_STEPS];
static double prep_us[MAX_STEPS];
static double late_us[MAX_STEPS]; /* timer pacing: wake-up after the deadline */
static double sorted_us[MAX_STEPS];
static volatile sig_atomic_t stop_requested = 0;

/* fault bits of the telemetry: the controller's status bits (0 .. DDYN_CTRL_STATUS_BITS - 1), then: */
#define APP_FAULT_STALE_FRAMES (1u << DDYN_CTRL_STATUS_BITS)       /* a monitored frame was missing: safe command */
#define APP_FAULT_SAFE_COMMAND (1u << (DDYN_CTRL_STATUS_BITS + 1)) /* the safe command went out (either cause) */
#define APP_FAULT_OVERRUN (1u << (DDYN_CTRL_STATUS_BITS + 2))      /* the command left after the period's deadline */

#ifdef DDYN_SIL_WITH_LCM

static ddyn_telemetry tm;            /* ~10 kB: static storage */
static double tm_us[MAX_STEPS];      /* wall time of each period's publish calls */
static double plan_x[(DDYN_MPC_MAX_HORIZON + 1) * DDYN_NX];
static double plan_u[DDYN_MPC_MAX_HORIZON * DDYN_NU];

/* Whether the limiter of a kind sends this step's message: the rule of telemetry_lcm.c's
 * limiter_allows (without counting), so the plan is simulated only for the steps it goes out. */
static int tm_due(const ddyn_tm_limiter *lim, int64_t step)
{
    return lim->every != 0 && (!lim->started || step < lim->last_step || step - lim->last_step >= lim->every);
}

static int tm_open(const char *url, double period)
{
    static double lo[DDYN_NC], hi[DDYN_NC];
    ddyn_telemetry_config cfg;
    int k;
    ddyn_telemetry_default_config(&cfg, 1.0 / period);
    cfg.url = url;
    if (ddyn_net_weights.lo != NULL && ddyn_net_weights.hi != NULL) {
        for (k = 0; k < DDYN_NC; ++k) {
            lo[k] = (double)ddyn_net_weights.lo[k];
            hi[k] = (double)ddyn_net_weights.hi[k];
        }
        cfg.coeff_lo = lo;
        cfg.coeff_hi = hi;
    }
    if (ddyn_telemetry_open(&tm, &cfg) != DDYN_TM_PUBLISHED) {
        fprintf(stderr, "ddyn_controller: cannot open LCM at %s\n", url);
        return 0;
    }
    return 1;
}

/* One period's telemetry; a failed publish is counted (tm.limiter[].errors), never fatal. */
static void tm_publish(long step, double period, double period_wall, double total, double prepare, int overrun,
                       const ddyn_sil_period *per)
{
    static const char *const stage_names[2] = {"feedback", "prepare"};
    ddyn_tm_state st;
    ddyn_tm_coeffs co;
    ddyn_tm_plan pl;
    ddyn_tm_timing ti;
    ddyn_tm_faults fa;
    int64_t utime = (int64_t)floor((double)step * period * 1e6 + 0.5);
    int k;

    st.utime = utime;
    st.step = step;
    for (k = 0; k < DDYN_NX; ++k) {
        st.x[k] = per->out.x_est[k];
        st.cov_diag[k] = node.ctl.ekf.P[k * DDYN_NX + k];
    }
    (void)ddyn_telemetry_publish_state(&tm, &st);

    co.utime = utime;
    co.step = step;
    memcpy(co.coeffs, per->out.coeffs, sizeof co.coeffs);
    (void)ddyn_telemetry_publish_coeffs(&tm, &co);

    memset(&pl, 0, sizeof pl);
    pl.utime = utime;
    pl.step = step;
    pl.status = (int)per->out.mpc_status;
    pl.status_name = ddyn_status_name(per->out.mpc_status);
    pl.qp_iterations = per->out.mpc_info.qp_iterations;
    pl.cost = per->out.mpc_info.cost;
    pl.horizon = 0;
    pl.states = per->out.x_est; /* no plan (yet): the estimate as the one state */
    if (tm_due(&tm.limiter[DDYN_TM_PLAN], step)) {
        int h = ddyn_mpc_plan(&node.ctl.mpc, plan_x, plan_u);
        if (h > 0 && h <= DDYN_TM_PLAN_MAX_HORIZON) {
            pl.horizon = h;
            pl.states = plan_x;
            pl.inputs = plan_u;
        }
    }
    (void)ddyn_telemetry_publish_plan(&tm, &pl);

    memset(&ti, 0, sizeof ti);
    ti.utime = utime;
    ti.step = step;
    ti.period_s = period_wall;
    ti.total_s = total;
    ti.deadline_s = period;
    ti.n_stages = 2; /* the step (the feedback phase when prepared) and the previous period's preparation */
    ti.stage_names[0] = stage_names[0];
    ti.stage_s[0] = total;
    ti.stage_names[1] = stage_names[1];
    ti.stage_s[1] = prepare;
    (void)ddyn_telemetry_publish_timing(&tm, &ti);

    fa.utime = utime;
    fa.step = step;
    fa.active = (uint32_t)per->out.status | (per->stale ? APP_FAULT_STALE_FRAMES : 0u) |
                (per->safe ? APP_FAULT_SAFE_COMMAND : 0u) | (overrun ? APP_FAULT_OVERRUN : 0u);
    (void)ddyn_telemetry_publish_faults(&tm, &fa);
}
#endif

static void on_signal(int sig)
{
    (void)sig;
    stop_requested = 1;
}

static double now_s(void)
{
    return (double)ddyn_rt_now_ns() * 1e-9;
}

/* a frame's receive time for the authentication's timeout, microseconds (the monotonic clock) */
static uint64_t rx_us(void)
{
    return (uint64_t)(ddyn_rt_now_ns() / 1000);
}

static int cmp_double(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* median, p99, max of the first n values */
static void stats(const double *v, long n, double out[3])
{
    out[0] = out[1] = out[2] = 0.0;
    if (n <= 0) {
        return;
    }
    memcpy(sorted_us, v, (size_t)n * sizeof(double));
    qsort(sorted_us, (size_t)n, sizeof(double), cmp_double);
    out[0] = sorted_us[n / 2];
    out[1] = sorted_us[(long)floor(0.99 * (double)(n - 1))];
    out[2] = sorted_us[n - 1];
}

static int open_can(const char *ifname)
{
    struct sockaddr_can addr;
    unsigned idx;
    int fd = socket(PF_CAN, SOCK_RAW, CAN_RAW), own = 0;
    if (fd < 0) {
        fprintf(stderr, "ddyn_controller: can.interface: socket(): %s\n", strerror(errno));
        return -1;
    }
    idx = if_nametoindex(ifname);
    if (idx == 0) {
        fprintf(stderr, "ddyn_controller: can.interface: no CAN interface '%s'\n", ifname);
        close(fd);
        return -1;
    }
    memset(&addr, 0, sizeof addr);
    addr.can_family = AF_CAN;
    addr.can_ifindex = (int)idx;
    if (bind(fd, (struct sockaddr *)&addr, sizeof addr) < 0) {
        fprintf(stderr, "ddyn_controller: can.interface: bind(%s): %s\n", ifname, strerror(errno));
        close(fd);
        return -1;
    }
    setsockopt(fd, SOL_CAN_RAW, CAN_RAW_RECV_OWN_MSGS, &own, sizeof own);
    return fd;
}

/* the loop's state and counts */
typedef struct {
    int fd;
    FILE *log;
    long steps, overruns, skipped, timer_steps, send_failed, status_count[DDYN_CTRL_STATUS_BITS];
    long n_late;
    int was_safe, timer_mode;
    double last_any_rx, last_gnss_wall, safe_latency, stale_latency, prev_t0, last_prep_s;
} app_loop;

/* one control period: step, command out, preparation for the next; `start` is when the period
 * began (its deadline is start + period) */
static void run_period(app_loop *L, int trigger, double start)
{
    ddyn_sil_period per;
    struct can_frame cf;
    double t0 = now_s(), t1, t2;
    int k, overrun;
    double raw[DDYN_SIL_LOG_READINGS];
    long i = L->steps < MAX_STEPS ? L->steps : MAX_STEPS - 1;
    ddyn_sil_node_period(&node, &per);
    memset(&cf, 0, sizeof cf);
    cf.can_id = per.can_id;
    cf.can_dlc = DDYN_DBW_FRAME_LEN;
    memcpy(cf.data, per.data, DDYN_DBW_FRAME_LEN);
    if (write(L->fd, &cf, sizeof cf) != (ssize_t)sizeof cf) {
        L->send_failed += 1;
    }
    if (per.has_auth) { /* its authenticator right after it (can.key_file) */
        cf.can_id = per.auth_can_id;
        memcpy(cf.data, per.auth_data, DDYN_DBW_FRAME_LEN);
        if (write(L->fd, &cf, sizeof cf) != (ssize_t)sizeof cf) {
            L->send_failed += 1;
        }
    }
    t1 = now_s(); /* the command is out */
    if (cfg.prepare) {
        (void)ddyn_ctrl_prepare(&node.ctl); /* refused in safe mode / PID throttle: the next step does it all */
    }
    t2 = now_s();
    loop_us[i] = (t1 - t0) * 1e6;
    prep_us[i] = (t2 - t1) * 1e6;
    overrun = t1 - start > cfg.period;
    L->overruns += overrun;
#ifdef DDYN_SIL_WITH_LCM
    if (cfg.lcm_url[0] != '\0') {
        /* after the command went out: the publish calls are not part of the step's time */
        tm_publish(L->steps, cfg.period, L->prev_t0 >= 0.0 ? t0 - L->prev_t0 : cfg.period, t1 - t0, L->last_prep_s,
                   overrun, &per);
        tm_us[i] = (now_s() - t2) * 1e6;
    }
#endif
    L->prev_t0 = t0;
    L->last_prep_s = t2 - t1;
    for (k = 0; k < DDYN_CTRL_STATUS_BITS; ++k) {
        L->status_count[k] += (long)((per.out.status >> k) & 1u);
    }
    /* the first entry into the safe state after driving: how long after the last position frame */
    if (per.safe && !L->was_safe && L->steps > 0 && L->safe_latency < 0.0 && L->last_gnss_wall >= 0.0) {
        L->safe_latency = t1 - L->last_gnss_wall;
    }
    L->was_safe = per.safe;
    /* the first period commanded safe because frames stopped arriving, after the first position */
    if (per.stale && L->stale_latency < 0.0 && L->last_gnss_wall >= 0.0) {
        L->stale_latency = t1 - L->last_gnss_wall;
    }
    L->timer_steps += trigger == 2 ? 1 : 0;
    L->timer_mode = trigger == 2;
    if (L->log != NULL) {
        fprintf(L->log, "%ld,%.6f,%.9f,%.2f,%.2f,%u,%d,%d,%d,%d,%.6f,%.6f", L->steps, t1, start, loop_us[i], prep_us[i],
                (unsigned)per.out.status, trigger, per.safe, per.stale, overrun, per.throttle, per.steering);
        for (k = 0; k < DDYN_NX; ++k) {
            fprintf(L->log, ",%.6g", per.out.x_est[k]);
        }
        for (k = 0; k < DDYN_NX; ++k) {
            fprintf(L->log, ",%.6g", node.ctl.ekf.P[k * DDYN_NX + k]);
        }
        ddyn_sil_log_readings(&per, raw);
        for (k = 0; k < DDYN_SIL_LOG_READINGS; ++k) {
            fprintf(L->log, ",%.6g", raw[k]);
        }
        fputc('\n', L->log);
    }
    L->steps += 1;
}

static void maybe_die(app_loop *L)
{
    if (cfg.die_at_step >= 0 && L->steps >= cfg.die_at_step) {
        if (L->log != NULL) {
            fflush(L->log);
        }
        raise(SIGKILL); /* the fault scenario: gone without a word, files left as they are */
    }
}

static int done(const app_loop *L)
{
    return stop_requested || (cfg.max_steps > 0 && L->steps >= cfg.max_steps);
}

/* pacing "frame": a period per position frame, the own timer when they stop */
static void loop_frame(app_loop *L)
{
    double last_start = now_s(); /* when the last period began: its frame's arrival, or its deadline */
    L->last_any_rx = last_start;
    while (!done(L)) {
        /* 1.5 periods of grace for the next position frame, then the nominal period on the timer:
         * absolute deadlines from the start of the last period, so that neither the step's nor the
         * preparation's time delays the timer (the safe command of a silent bus stays 2.5 periods
         * after the last position frame, plus one step) */
        double deadline = last_start + (L->timer_mode ? 1.0 : 1.5) * cfg.period;
        double now = now_s(), wait = deadline - now, start;
        int trigger = 0, runs = 0, r;
        struct pollfd p;
        p.fd = L->fd;
        p.events = POLLIN;
        p.revents = 0;
        if (poll(&p, 1, wait > 0.0 ? (int)ceil(wait * 1e3) : 0) > 0) {
            struct can_frame cf;
            if (read(L->fd, &cf, sizeof cf) == (ssize_t)sizeof cf) {
                L->last_any_rx = now_s();
                runs = ddyn_sil_node_on_frame_at(&node, cf.can_id & CAN_EFF_MASK, cf.data, cf.can_dlc, rx_us());
                if (runs > 0) {
                    trigger = 1;
                    L->last_gnss_wall = L->last_any_rx;
                }
            }
        }
        now = now_s();
        start = L->last_any_rx;
        /* no timer before the first position frame: the sensors (or the plant) may not be up yet */
        if (!trigger && L->last_gnss_wall >= 0.0 && now >= deadline &&
            (cfg.lockstep_silence <= 0.0 || now - L->last_any_rx >= cfg.lockstep_silence)) {
            trigger = 2; /* the controller's own timer */
            runs = 1;
            start = deadline;
            if (now - deadline >= cfg.period) { /* woke a period or more late: from now, not back to back */
                if (cfg.lockstep_silence <= 0.0) {
                    L->skipped += (long)floor((now - deadline) / cfg.period);
                }
                start = now;
            }
        }
        if (cfg.idle_exit > 0.0 && now - L->last_any_rx > cfg.idle_exit) {
            break; /* the bus is gone for good */
        }
        if (trigger) {
            maybe_die(L);
        }
        for (r = 0; r < runs && !done(L); ++r) {
            run_period(L, trigger, start);
            last_start = start;
        }
    }
}

/* pacing "timer": a period at every absolute deadline, with the frames received since the last */
static void loop_timer(app_loop *L)
{
    const int64_t period_ns = (int64_t)llround(cfg.period * 1e9);
    int64_t next = ddyn_rt_now_ns() + period_ns;
    int fl = fcntl(L->fd, F_GETFL, 0);
    if (fl >= 0) {
        (void)fcntl(L->fd, F_SETFL, fl | O_NONBLOCK);
    }
    L->last_any_rx = now_s();
    while (!done(L)) {
        struct can_frame cf;
        int64_t woke, finished;
        ddyn_rt_sleep_until(next, &stop_requested);
        if (stop_requested) {
            break;
        }
        woke = ddyn_rt_now_ns();
        late_us[L->n_late < MAX_STEPS ? L->n_late : MAX_STEPS - 1] = (double)(woke - next) * 1e-3;
        L->n_late += L->n_late < MAX_STEPS ? 1 : 0;
        while (read(L->fd, &cf, sizeof cf) == (ssize_t)sizeof cf) {
            L->last_any_rx = now_s();
            if (ddyn_sil_node_on_frame_at(&node, cf.can_id & CAN_EFF_MASK, cf.data, cf.can_dlc, rx_us()) > 0) {
                L->last_gnss_wall = L->last_any_rx;
            }
        }
        node.catch_up = 0; /* the clock, not the frames, sets the periods */
        if (cfg.idle_exit > 0.0 && now_s() - L->last_any_rx > cfg.idle_exit) {
            break;
        }
        maybe_die(L);
        run_period(L, 2, (double)next * 1e-9);
        finished = ddyn_rt_now_ns();
        next += period_ns;
        if (finished > next) { /* deadlines already passed are skipped, not run back to back */
            int64_t missed = (finished - next) / period_ns + 1;
            L->skipped += (long)missed;
            next += missed * period_ns;
        }
    }
}

static int write_metrics(const app_loop *L, const ddyn_rt_state *rt)
{
    static const char *const meas_names[DDYN_MEAS_COUNT] = DDYN_MEAS_NAMES;
    long n = L->steps < MAX_STEPS ? L->steps : MAX_STEPS;
    double s[3];
    int k;
    FILE *m = fopen(cfg.metrics, "w");
    if (m == NULL) {
        fprintf(stderr, "ddyn_controller: telemetry.metrics: cannot write %s\n", cfg.metrics);
        return 0;
    }
    stats(loop_us, n, s);
    fprintf(m, "{\n  \"steps\": %ld,\n  \"period\": %.6f,\n", L->steps, cfg.period);
    fprintf(m, "  \"loop_us\": {\"median\": %.3f, \"p99\": %.3f, \"max\": %.3f},\n", s[0], s[1], s[2]);
    stats(prep_us, n, s);
    fprintf(m, "  \"prepare_us\": {\"median\": %.3f, \"p99\": %.3f, \"max\": %.3f},\n", s[0], s[1], s[2]);
    stats(late_us, L->n_late, s);
    fprintf(m, "  \"overruns\": {\"periods\": %ld, \"skipped_deadlines\": %ld, "
               "\"wakeup_late_us\": {\"median\": %.3f, \"p99\": %.3f, \"max\": %.3f}},\n",
            L->overruns, L->skipped, s[0], s[1], s[2]);
    fprintf(m, "  \"deadline_misses\": %ld,\n  \"safe_steps\": %ld,\n  \"timer_steps\": %ld,\n", L->overruns,
            node.safe_steps, L->timer_steps);
    fprintf(m, "  \"first_safe_latency\": %.6f,\n  \"first_stale_latency\": %.6f,\n", L->safe_latency,
            L->stale_latency);
    fprintf(m, "  \"frames\": {\"ok\": %ld, \"lost\": %ld, \"repeated_counter\": %ld, \"late\": %ld, \"unknown_id\": %ld, "
               "\"bad_length\": %ld, \"checksum\": %ld, \"range\": %ld, \"send_failed\": %ld},\n",
            node.frames_ok, node.frames_lost, node.repeated_counter, node.late, node.unknown_id, node.bad_length,
            node.checksum, node.range, L->send_failed);
    /* frame authentication (can.key_file): frames accepted, refused (forged, replayed), dropped stale */
    fprintf(m, "  \"auth\": {\"enabled\": %s, \"accepted\": %ld, \"forged\": %ld, \"replayed\": %ld, \"stale\": %ld},\n",
            node.auth_on ? "true" : "false", node.auth_accepted, node.auth_forged, node.auth_replayed, node.auth_stale);
    fprintf(m, "  \"status_counts\": {");
    for (k = 0; k < DDYN_CTRL_STATUS_BITS; ++k) {
        fprintf(m, "%s\"%s\": %ld", k ? ", " : "", ddyn_ctrl_status_name(1u << k), L->status_count[k]);
    }
    fprintf(m, "},\n  \"sensor_rejected\": {");
    for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
        fprintf(m, "%s\"%s\": %lu", k ? ", " : "", meas_names[k], (unsigned long)node.ctl.rejected_count[k]);
    }
    fprintf(m, "},\n  \"sensor_nonfinite\": {");
    for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
        fprintf(m, "%s\"%s\": %lu", k ? ", " : "", meas_names[k], (unsigned long)node.ctl.nonfinite_count[k]);
    }
    fprintf(m, "},\n");
    fprintf(m, "  \"realtime\": {\"pacing\": \"%s\", \"prepare\": %s, \"memory_locked\": %s, \"fifo_priority\": %d, "
               "\"cpu\": %d, \"warnings\": %d},\n",
            cfg.pacing == DDYN_APP_PACING_TIMER ? "timer" : "frame", cfg.prepare ? "true" : "false",
            rt->memory_locked ? "true" : "false", rt->fifo_priority, rt->cpu, rt->warnings);
    fprintf(m, "  \"checkpoint_hash\": \"%s\",\n",
            ddyn_net_weights.checkpoint_sha256 != NULL ? ddyn_net_weights.checkpoint_sha256 : "");
#ifdef DDYN_SIL_WITH_LCM
    if (cfg.lcm_url[0] != '\0') {
        /* the publish calls of each period (outside loop_us) and the limiters' counts */
        stats(tm_us, n, s);
        fprintf(m, "  \"telemetry\": {\"url\": \"%s\", \"publish_us\": {\"median\": %.3f, \"p99\": %.3f, \"max\": %.3f}",
                cfg.lcm_url, s[0], s[1], s[2]);
        for (k = 0; k < DDYN_TM_KIND_COUNT; ++k) {
            const ddyn_tm_limiter *lim = &tm.limiter[k];
            fprintf(m, ", \"%s\": {\"published\": %llu, \"skipped\": %llu, \"errors\": %llu}",
                    ddyn_tm_kind_name((ddyn_tm_kind)k), (unsigned long long)lim->published,
                    (unsigned long long)lim->skipped, (unsigned long long)lim->errors);
        }
        fprintf(m, "},\n");
    }
#endif
    fprintf(m, "  \"fixed_coefficients\": %s\n}\n", cfg.fixed ? "true" : "false");
    fclose(m);
    return 1;
}

static int usage(const char *prog)
{
    fprintf(stderr, "usage: %s CONFIG.json | --check CONFIG.json | --keys | --checkpoint-hash\n", prog);
    return 2;
}

int main(int argc, char **argv)
{
    char err[DDYN_APP_ERROR_LEN];
    const char *path;
    struct sigaction sa;
    ddyn_rt_state rt;
    app_loop L;
    double s[3];
    int check = 0;

    if (argc == 2 && strcmp(argv[1], "--checkpoint-hash") == 0) {
        /* which network this build runs (train/bench/identity.py) */
        const char *h = ddyn_net_weights.checkpoint_sha256;
        if (h == NULL || h[0] == '\0') {
            fprintf(stderr, "ddyn_controller: the built-in network carries no checkpoint hash\n");
            return 2;
        }
        printf("%s\n", h);
        return 0;
    }
    if (argc == 2 && strcmp(argv[1], "--keys") == 0) {
        ddyn_app_config_keys(stdout);
        return 0;
    }
    if (argc == 3 && strcmp(argv[1], "--check") == 0) {
        check = 1;
        path = argv[2];
    } else if (argc == 2 && argv[1][0] != '-') {
        path = argv[1];
    } else {
        return usage(argv[0]);
    }
    if (!ddyn_app_config_read(path, &cfg, err)) {
        fprintf(stderr, "ddyn_controller: %s\n", err);
        return 2;
    }
#ifndef DDYN_SIL_WITH_LCM
    if (cfg.lcm_url[0] != '\0') {
        fprintf(stderr, "ddyn_controller: %s: telemetry.lcm_url: this build has no LCM telemetry (configured with "
                        "DDYN_WITH_LCM=OFF)\n", path);
        return 2;
    }
#endif
    if (!ddyn_app_check_network(&cfg, &ddyn_net_weights, err)) {
        fprintf(stderr, "ddyn_controller: %s: refused: %s\n", path, err);
        return 2;
    }
    if (check) {
        ddyn_app_config_print(&cfg, stdout);
        return 0;
    }
    if (ddyn_app_node_init(&node, &cfg, &ddyn_net_weights) != DDYN_OK) {
        return 2;
    }
    memset(&L, 0, sizeof L);
    L.last_gnss_wall = L.safe_latency = L.stale_latency = L.prev_t0 = -1.0;
    L.fd = open_can(cfg.can_interface);
    if (L.fd < 0) {
        return 2;
    }
#ifdef DDYN_SIL_WITH_LCM
    if (cfg.lcm_url[0] != '\0' && !tm_open(cfg.lcm_url, cfg.period)) {
        return 2;
    }
#endif
    if (cfg.log[0] != '\0') {
        L.log = fopen(cfg.log, "w");
        if (L.log == NULL) {
            fprintf(stderr, "ddyn_controller: telemetry.log: cannot write %s\n", cfg.log);
            return 2;
        }
        /* wall: when the command went out; start: when the period began (its frame, or its deadline) */
        fprintf(L.log, "step,wall,start,loop_us,prepare_us,status,trigger,safe,stale,overrun,throttle_cmd,steering_cmd,"
                       "x,y,yaw,vx,vy,omega,throttle,steering,P0,P1,P2,P3,P4,P5,P6,P7," DDYN_SIL_LOG_READINGS_HEADER "\n");
    }
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal; /* no SA_RESTART: poll() and clock_nanosleep return at once */
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    /* after every allocation of the set-up (files, sockets, LCM): locked from here on */
    rt = ddyn_rt_setup(cfg.priority, cfg.cpu, cfg.lock_memory);
    /* the "running" line says the bus is bound and the set-up done (the SIL starts its plant on it) */
    printf("ddyn_controller: running %s on %s, period %.4f s, pacing %s, prepare %s, memory %s, SCHED_FIFO %d, cpu %d, "
           "frame authentication %s\n",
           cfg.vehicle, cfg.can_interface, cfg.period, cfg.pacing == DDYN_APP_PACING_TIMER ? "timer" : "frame",
           cfg.prepare ? "on" : "off", rt.memory_locked ? "locked" : "not locked", rt.fifo_priority, rt.cpu,
           node.auth_on ? "on" : "off");
    fflush(stdout);

    if (cfg.pacing == DDYN_APP_PACING_TIMER) {
        loop_timer(&L);
    } else {
        loop_frame(&L);
    }
    if (L.log != NULL) {
        fclose(L.log);
    }
    close(L.fd);
#ifdef DDYN_SIL_WITH_LCM
    if (cfg.lcm_url[0] != '\0') {
        ddyn_telemetry_close(&tm);
    }
#endif
    if (!write_metrics(&L, &rt)) {
        return 2;
    }
    stats(loop_us, L.steps < MAX_STEPS ? L.steps : MAX_STEPS, s);
    printf("controller: %ld periods, loop median %.1f us, max %.1f us, %ld overruns, %ld skipped deadlines, "
           "%ld safe\n", L.steps, s[0], s[2], L.overruns, L.skipped, node.safe_steps);
    return 0;
}
