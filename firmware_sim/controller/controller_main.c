/*
 * ddyn_sil_controller: the car's controller as its own process (Linux). The c_src runtime
 * (ddyn/controller.h: EKF -> history -> guard network -> MPC) behind the drive-by-wire protocol
 * (ddyn/dbw.h frame checks, can/ddyn_dbw.dbc) on a SocketCAN interface. It talks to the plant
 * ONLY through CAN frames.
 *
 * usage: ddyn_sil_controller SETUP [--can IFACE]     (IFACE default vcan0)
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

#define MAX_STEPS DDYN_SIL_MAX_STEPS
#define PATH_LEN 512

extern const ddyn_net_tables ddyn_net_weights;

static ddyn_sil_node node; /* large: static storage, not the stack */
static double loop_us[MAX_STEPS];
static double sorted_us[MAX_STEPS];
static volatile sig_atomic_t stop_requested = 0;


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
    struct sigaction sa;
    long steps = 0, misses = 0, timer_steps = 0, send_failed = 0, status_count[DDYN_CTRL_STATUS_BITS] = {0};
    int fd, i, k;
    double last_step_wall, last_any_rx, last_gnss_wall = -1.0, safe_latency = -1.0, stale_latency = -1.0;
    int was_safe = 0, timer_mode = 0;
    FILE *log;

    if (argc < 2) {
        fprintf(stderr, "usage: %s SETUP [--can IFACE]\n", argv[0]);
        return 2;
    }
    for (i = 2; i + 1 < argc; ++i) {
        if (strcmp(argv[i], "--can") == 0) {
            iface = argv[i + 1];
        }
    }
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
        fprintf(m, "},\n  \"fixed_coefficients\": %s\n}\n", s.fixed ? "true" : "false");
        fclose(m);
    }
    printf("controller: %ld periods, loop median %.1f us, max %.1f us, %ld deadline misses, %ld safe\n", steps,
           steps ? sorted_us[steps / 2] : 0.0, steps ? sorted_us[steps - 1] : 0.0, misses, node.safe_steps);
    return 0;
}
