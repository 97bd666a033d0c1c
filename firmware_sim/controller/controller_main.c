/*
 * ddyn_sil_controller: the car's controller as its own process (Linux). The c_src runtime
 * (ddyn/controller.h: EKF -> history -> guard network -> MPC) behind the drive-by-wire protocol
 * (ddyn/dbw.h frame checks, can/ddyn_dbw.dbc) on a SocketCAN interface. It talks to the plant
 * ONLY through CAN frames.
 *
 * usage: ddyn_sil_controller SETUP [--can IFACE] [--lcm URL]     (IFACE default vcan0)
 *
 * --lcm URL: publish the telemetry live over LCM (ddyn/telemetry.h, c_src/linux/telemetry_lcm.c;
 * e.g. udpm://239.255.76.67:7667?ttl=0), as the car does: every period the state estimate with
 * its covariance diagonal, the coefficients used with the guard bounds, the fault bits; the MPC
 * plan and the loop timing at a fifth of the control rate (the module's default rate limiters,
 * which count periods). Messages carry utime = period number x period (the controller's clock:
 * it counts periods) and step = the period number of the CSV log. Only in a build with
 * DDYN_WITH_LCM (then the executable is linked dynamically: liblcm is a shared library); a build
 * without it refuses --lcm.
 *
 * One control period runs when a GNSS_Position frame arrives (the plant sends it last in a
 * period), or on the controller's own timer when none has come for 1.5 periods (then every period
 * until one comes), so the car is
 * commanded (safely) even when the sensors fall silent. The controller's time is counted in
 * periods, which makes it run unchanged in real time and in lock-step with a faster-than-real-
 * time plant.
 *
 * Frame policy and the command: controller_node.h.
 *
 * SETUP (text, keywords in this order, numbers whitespace-separated):
 *   vehicle NAME  period SEC  fixed 0|1  nominal 17  coeffs 17  throttle mpc|pid  pid_gains default|KP KI KD
 *   x0 8  r_std 12 (sensor kind order,
 *   2 components each: the noise the filter assumes)  q 8 (the filter's process noise variance per
 *   period; 0 = the controller's default)  stale 7 (periods per ddyn_dbw_frame; 0 = not monitored)  max_steps N
 *   idle_exit SEC  lockstep SEC (0: real time; > 0: the plant waits for each command, and the timer
 *   runs a period only when no frame at all has come for SEC of wall time: a slow plant is not a
 *   silent one, and an extra period runs the filter ahead of the plant)
 *   die_at_step N (fault scenario: the process kills itself with SIGKILL at
 *   period N, as if killed from outside; -1 = never)  metrics PATH  log PATH  track N  then N rows: x y speed width_left width_right
 * fixed 1: the MPC and EKF use `coeffs` throughout, the network is never run (DDYN_CTRL_SOURCE_FIXED);
 * `nominal` stays the fallback/safe-command coefficients. throttle pid: a PID on the speed error
 * sets the throttle and the MPC plans the steering (DDYN_CTRL_THROTTLE_PID), with the controller's
 * default gains or the three given.
 *
 * Writes the metrics (JSON: loop time median/p99/max, deadline misses, status counts, frame
 * counts, safe-state timing) and a per-period CSV log. Exit 0 after a clean end (SIGTERM/SIGINT,
 * idle_exit seconds without frames, or max_steps), 2 on bad setup.
 */
#define _POSIX_C_SOURCE 200809L
#include <errno.h>
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

#include "controller_node.h"
#include "controller_setup.h"

#ifdef DDYN_SIL_WITH_LCM
#include "ddyn/telemetry.h"
#endif

#define MAX_STEPS DDYN_SIL_MAX_STEPS
#define PATH_LEN 512

extern const ddyn_net_tables ddyn_net_weights;

static ddyn_sil_node node; /* large: static storage, not the stack */
static double loop_us[MAX_STEPS];
static double sorted_us[MAX_STEPS];
static volatile sig_atomic_t stop_requested = 0;

#ifdef DDYN_SIL_WITH_LCM
/* fault bits of the FAULTS message: bits 0-15 the period's DDYN_CTRL_* status bits, then these */
/* fault bits of the telemetry: the controller's status bits (0 .. DDYN_CTRL_STATUS_BITS - 1), then: */
#define SIL_FAULT_STALE_FRAMES (1u << DDYN_CTRL_STATUS_BITS)       /* a monitored frame was missing: safe command */
#define SIL_FAULT_SAFE_COMMAND (1u << (DDYN_CTRL_STATUS_BITS + 1)) /* the safe command went out (either cause) */

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
        fprintf(stderr, "ddyn_sil_controller: cannot open LCM at %s\n", url);
        return 0;
    }
    return 1;
}

/* One period's telemetry; a failed publish is counted (tm.limiter[].errors), never fatal. */
static void tm_publish(long step, double period, double period_wall, double total, const ddyn_sil_period *per)
{
    static const char *const stage_names[1] = {"controller_step"};
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
    ti.n_stages = 1;
    ti.stage_names[0] = stage_names[0];
    ti.stage_s[0] = total;
    (void)ddyn_telemetry_publish_timing(&tm, &ti);

    fa.utime = utime;
    fa.step = step;
    fa.active = (uint32_t)per->out.status | (per->stale ? SIL_FAULT_STALE_FRAMES : 0u) |
                (per->safe ? SIL_FAULT_SAFE_COMMAND : 0u);
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
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + (double)t.tv_nsec * 1e-9;
}

static int cmp_double(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static int open_can(const char *ifname)
{
    struct sockaddr_can addr;
    unsigned idx;
    int fd = socket(PF_CAN, SOCK_RAW, CAN_RAW), own = 0;
    if (fd < 0) {
        fprintf(stderr, "ddyn_sil_controller: socket(): %s\n", strerror(errno));
        return -1;
    }
    idx = if_nametoindex(ifname);
    if (idx == 0) {
        fprintf(stderr, "ddyn_sil_controller: no CAN interface '%s'\n", ifname);
        close(fd);
        return -1;
    }
    memset(&addr, 0, sizeof addr);
    addr.can_family = AF_CAN;
    addr.can_ifindex = (int)idx;
    if (bind(fd, (struct sockaddr *)&addr, sizeof addr) < 0) {
        fprintf(stderr, "ddyn_sil_controller: bind(%s): %s\n", ifname, strerror(errno));
        close(fd);
        return -1;
    }
    setsockopt(fd, SOL_CAN_RAW, CAN_RAW_RECV_OWN_MSGS, &own, sizeof own);
    return fd;
}

int main(int argc, char **argv)
{
    static ddyn_sil_setup s;
    static const char *const meas_names[DDYN_MEAS_COUNT] = DDYN_MEAS_NAMES;
    const char *iface = "vcan0";
    const char *lcm_url = NULL;
    struct sigaction sa;
    long steps = 0, misses = 0, timer_steps = 0, send_failed = 0, status_count[DDYN_CTRL_STATUS_BITS] = {0};
    int fd, i, k;
    double last_step_wall, last_any_rx, last_gnss_wall = -1.0, safe_latency = -1.0, stale_latency = -1.0;
#ifdef DDYN_SIL_WITH_LCM
    double prev_t0 = -1.0; /* wall time the previous period started (the timing message's period_s) */
#endif
    int was_safe = 0, timer_mode = 0;
    FILE *log;

    if (argc < 2) {
        fprintf(stderr, "usage: %s SETUP [--can IFACE] [--lcm URL]\n", argv[0]);
        return 2;
    }
    for (i = 2; i + 1 < argc; ++i) {
        if (strcmp(argv[i], "--can") == 0) {
            iface = argv[i + 1];
        } else if (strcmp(argv[i], "--lcm") == 0) {
            lcm_url = argv[i + 1];
        }
    }
#ifndef DDYN_SIL_WITH_LCM
    if (lcm_url != NULL) {
        fprintf(stderr, "ddyn_sil_controller: --lcm: this build has no LCM telemetry (configured with DDYN_WITH_LCM=OFF)\n");
        return 2;
    }
#endif
    if (!ddyn_sil_read_setup(argv[1], &s)) {
        return 2;
    }
    if (ddyn_sil_node_from_setup(&node, &s, &ddyn_net_weights) != DDYN_OK) {
        return 2;
    }
    fd = open_can(iface);
    if (fd < 0) {
        return 2;
    }
#ifdef DDYN_SIL_WITH_LCM
    if (lcm_url != NULL && !tm_open(lcm_url, s.period)) {
        return 2;
    }
#endif
    log = fopen(s.log, "w");
    if (log == NULL) {
        fprintf(stderr, "ddyn_sil_controller: cannot write %s\n", s.log);
        return 2;
    }
    fprintf(log, "step,wall,loop_us,status,trigger,safe,stale,throttle_cmd,steering_cmd,"
                 "x,y,yaw,vx,vy,omega,throttle,steering,P0,P1,P2,P3,P4,P5,P6,P7\n");
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal; /* no SA_RESTART: poll() returns at once */
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);

    last_step_wall = last_any_rx = now_s();
    while (!stop_requested && steps < s.max_steps) {
        /* 1.5 periods of grace for the next position frame, then the nominal period on the timer */
        double timeout = (timer_mode ? 1.0 : 1.5) * s.period;
        double now = now_s(), wait = timeout - (now - last_step_wall);
        int trigger = 0, runs = 0, r;
        struct pollfd p;
        p.fd = fd;
        p.events = POLLIN;
        p.revents = 0;
        if (poll(&p, 1, wait > 0.0 ? (int)ceil(wait * 1e3) : 0) > 0) {
            struct can_frame cf;
            if (read(fd, &cf, sizeof cf) == (ssize_t)sizeof cf) {
                last_any_rx = now_s();
                runs = ddyn_sil_node_on_frame(&node, cf.can_id & CAN_EFF_MASK, cf.data, cf.can_dlc);
                if (runs > 0) {
                    trigger = 1;
                    last_gnss_wall = last_any_rx;
                }
            }
        }
        now = now_s();
        /* no timer before the first position frame: the plant may not be up yet */
        if (!trigger && last_gnss_wall >= 0.0 && now - last_step_wall >= timeout &&
            (s.lockstep <= 0.0 || now - last_any_rx >= s.lockstep)) {
            trigger = 2; /* the controller's own timer */
            runs = 1;
        }
        if (now - last_any_rx > s.idle_exit) {
            break; /* the plant is gone for good */
        }
        if (trigger && s.die_at_step >= 0 && steps >= s.die_at_step) {
            fflush(log);
            raise(SIGKILL); /* the fault scenario: gone without a word, files left as they are */
        }
        for (r = 0; r < runs && steps < s.max_steps; ++r) {
            ddyn_sil_period per;
            struct can_frame cf;
            double t0 = now_s(), t1;
            ddyn_sil_node_period(&node, &per);
            t1 = now_s();
            memset(&cf, 0, sizeof cf);
            cf.can_id = per.can_id;
            cf.can_dlc = DDYN_DBW_FRAME_LEN;
            memcpy(cf.data, per.data, DDYN_DBW_FRAME_LEN);
            if (write(fd, &cf, sizeof cf) != (ssize_t)sizeof cf) {
                send_failed += 1;
            }
            loop_us[steps] = (t1 - t0) * 1e6;
#ifdef DDYN_SIL_WITH_LCM
            if (lcm_url != NULL) {
                /* after the command went out: the publish calls are not part of the step's time */
                double t2 = now_s();
                tm_publish(steps, s.period, prev_t0 >= 0.0 ? t0 - prev_t0 : s.period, t1 - t0, &per);
                tm_us[steps] = (now_s() - t2) * 1e6;
            }
            prev_t0 = t0;
#endif
            misses += (t1 - t0) > s.period ? 1 : 0;
            for (k = 0; k < DDYN_CTRL_STATUS_BITS; ++k) {
                status_count[k] += (long)((per.out.status >> k) & 1u);
            }
            /* the first entry into the safe state after driving: how long after the last position frame */
            if (per.safe && !was_safe && steps > 0 && safe_latency < 0.0 && last_gnss_wall >= 0.0) {
                safe_latency = t1 - last_gnss_wall;
            }
            was_safe = per.safe;
            /* the first period commanded safe because frames stopped arriving, after the first position */
            if (per.stale && stale_latency < 0.0 && last_gnss_wall >= 0.0) {
                stale_latency = t1 - last_gnss_wall;
            }
            timer_steps += trigger == 2 ? 1 : 0;
            timer_mode = trigger == 2;
            fprintf(log, "%ld,%.6f,%.2f,%u,%d,%d,%d,%.6f,%.6f", steps, t1, loop_us[steps], (unsigned)per.out.status,
                    trigger, per.safe, per.stale, per.throttle, per.steering);
            for (k = 0; k < DDYN_NX; ++k) {
                fprintf(log, ",%.6g", per.out.x_est[k]);
            }
            for (k = 0; k < DDYN_NX; ++k) {
                fprintf(log, ",%.6g", node.ctl.ekf.P[k * DDYN_NX + k]);
            }
            fputc('\n', log);
            last_step_wall = now_s();
            steps += 1;
        }
    }
    fclose(log);
    close(fd);
#ifdef DDYN_SIL_WITH_LCM
    if (lcm_url != NULL) {
        ddyn_telemetry_close(&tm);
    }
#endif

    {
        FILE *m = fopen(s.metrics, "w");
        double median = 0.0, p99 = 0.0, mx = 0.0;
        if (m == NULL) {
            fprintf(stderr, "ddyn_sil_controller: cannot write %s\n", s.metrics);
            return 2;
        }
        if (steps > 0) {
            memcpy(sorted_us, loop_us, (size_t)steps * sizeof(double));
            qsort(sorted_us, (size_t)steps, sizeof(double), cmp_double);
            median = sorted_us[steps / 2];
            p99 = sorted_us[(long)floor(0.99 * (double)(steps - 1))];
            mx = sorted_us[steps - 1];
        }
        fprintf(m, "{\n  \"steps\": %ld,\n  \"period\": %.6f,\n", steps, s.period);
        fprintf(m, "  \"loop_us\": {\"median\": %.3f, \"p99\": %.3f, \"max\": %.3f},\n", median, p99, mx);
        fprintf(m, "  \"deadline_misses\": %ld,\n  \"safe_steps\": %ld,\n  \"timer_steps\": %ld,\n", misses,
                node.safe_steps, timer_steps);
        fprintf(m, "  \"first_safe_latency\": %.6f,\n  \"first_stale_latency\": %.6f,\n", safe_latency,
                stale_latency);
        fprintf(m, "  \"frames\": {\"ok\": %ld, \"lost\": %ld, \"repeated_counter\": %ld, \"late\": %ld, \"unknown_id\": %ld, "
                   "\"bad_length\": %ld, \"checksum\": %ld, \"range\": %ld, \"send_failed\": %ld},\n",
                node.frames_ok, node.frames_lost, node.repeated_counter, node.late, node.unknown_id, node.bad_length,
                node.checksum, node.range, send_failed);
        fprintf(m, "  \"status_counts\": {");
        for (k = 0; k < DDYN_CTRL_STATUS_BITS; ++k) {
            fprintf(m, "%s\"%s\": %ld", k ? ", " : "", ddyn_ctrl_status_name(1u << k), status_count[k]);
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
#ifdef DDYN_SIL_WITH_LCM
        if (lcm_url != NULL) {
            /* the publish calls of each period (outside loop_us) and the limiters' counts */
            double tmed = 0.0, tp99 = 0.0, tmax = 0.0;
            if (steps > 0) {
                memcpy(sorted_us, tm_us, (size_t)steps * sizeof(double));
                qsort(sorted_us, (size_t)steps, sizeof(double), cmp_double);
                tmed = sorted_us[steps / 2];
                tp99 = sorted_us[(long)floor(0.99 * (double)(steps - 1))];
                tmax = sorted_us[steps - 1];
            }
            fprintf(m, "  \"telemetry\": {\"url\": \"%s\", \"publish_us\": {\"median\": %.3f, \"p99\": %.3f, \"max\": %.3f}",
                    lcm_url, tmed, tp99, tmax);
            for (k = 0; k < DDYN_TM_KIND_COUNT; ++k) {
                const ddyn_tm_limiter *lim = &tm.limiter[k];
                fprintf(m, ", \"%s\": {\"published\": %llu, \"skipped\": %llu, \"errors\": %llu}",
                        ddyn_tm_kind_name((ddyn_tm_kind)k), (unsigned long long)lim->published,
                        (unsigned long long)lim->skipped, (unsigned long long)lim->errors);
            }
            fprintf(m, "},\n");
        }
#endif
        fprintf(m, "  \"fixed_coefficients\": %s\n}\n", s.fixed ? "true" : "false");
        fclose(m);
    }
    printf("controller: %ld periods, loop median %.1f us, max %.1f us, %ld deadline misses, %ld safe\n", steps,
           steps ? sorted_us[steps / 2] : 0.0, steps ? sorted_us[steps - 1] : 0.0, misses, node.safe_steps);
    return 0;
}
