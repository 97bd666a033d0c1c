/*
 * Drive-by-wire over a real SocketCAN interface (vcan0): a controller-side endpoint and a
 * drive-by-wire emulator, two processes exchanging frames every 10 ms. One scenario per
 * failure of the issue, injected by the emulator (or the link) mid-run; for each, the
 * controller must count it, send the safe command in the same control period, and come back
 * only through N good frames plus an explicit enable. The nominal scenario also checks the
 * kernel filters, the receive timestamps and the period timing.
 *
 * Runs where vcan exists: inside the qemu guest of scripts/vcan_guest/ (these machines' kernels
 * have no CAN), or directly on a host with vcan0. Prints one line per scenario and
 * "DDYN_VCAN_RESULT: PASS" or "DDYN_VCAN_RESULT: FAIL" last; exits 0 only on PASS.
 * usage: test_vcan [IFACE]   (default vcan0)
 */
#define _GNU_SOURCE
#include <errno.h>
#include <math.h>
#include <net/if.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include <linux/can/error.h>

#include "dbw_socketcan.h"

#define PERIOD_US 10000u
#define PERIODS 100
#define INJECT_PERIOD 25
#define STALE_GAP_PERIODS 15 /* 150 ms without IMU frames: five times its 30 ms deadline */
/* Both ends use the DBC's deadlines (ddyn_dbw_default_config: 3 cycle times). The guest runs
 * with a virtual clock driven by the instruction count (scripts/vcan_guest/run.sh), so a loaded
 * host slows the test down but does not stretch the guest's time between frames. On a real host
 * with vcan (no such clock) scheduling stalls could still exceed 30 ms, hence the retry: */
#define ATTEMPTS 2

typedef enum {
    INJ_NONE = 0,
    INJ_STALE,
    INJ_COUNTER_JUMP,
    INJ_COUNTER_REPEAT,
    INJ_CHECKSUM,
    INJ_RANGE,
    INJ_UNKNOWN,
    INJ_BAD_LENGTH,
    INJ_BUS_OFF,
    INJ_IFACE_GONE,
    INJ_COUNT
} injection;

static const char *const INJ_NAMES[INJ_COUNT] = {
    "nominal", "stale", "counter_jump", "counter_repeat", "checksum",
    "range", "unknown_frame", "bad_length", "bus_off", "iface_gone",
};
static const ddyn_dbw_failure INJ_KIND[INJ_COUNT] = {
    DDYN_DBW_FAIL_COUNT,         DDYN_DBW_FAIL_STALE, DDYN_DBW_FAIL_COUNTER_JUMP, DDYN_DBW_FAIL_COUNTER_REPEAT,
    DDYN_DBW_FAIL_CHECKSUM,      DDYN_DBW_FAIL_RANGE, DDYN_DBW_FAIL_UNKNOWN_FRAME, DDYN_DBW_FAIL_BAD_LENGTH,
    DDYN_DBW_FAIL_BUS_OFF,       DDYN_DBW_FAIL_IFACE_GONE,
};

/* what the emulator tells the controller process at the end, through a pipe */
typedef struct {
    uint32_t block_frames_sent;   /* frames inside the protocol block the controller should get */
    uint32_t commands_good;
    uint32_t commands_bad;        /* command frames the emulator's monitor rejected */
    int first_safe_period;        /* index of the first SAFE_STOP command after an AUTONOMOUS one, or -1 */
    int last_autonomous_period;   /* index of the last AUTONOMOUS command, or -1 */
    int setup_error;
} emu_report;

static const char *iface = "vcan0";
static int failures;
static const char *fail_label = "FAIL";

static void fail(const char *scenario, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    printf("%s %s: ", fail_label, scenario);
    vprintf(fmt, ap);
    printf("\n");
    va_end(ap);
    fflush(stdout);
    ++failures;
}

static void sleep_until(uint64_t t_mono_us)
{
    struct timespec ts;
    ts.tv_sec = (time_t)(t_mono_us / 1000000u);
    ts.tv_nsec = (long)((t_mono_us % 1000000u) * 1000u);
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR) {
    }
}

static int set_link_up(const char *name, int up)
{
    struct ifreq ifr;
    int r = -1, fd = socket(AF_INET, SOCK_DGRAM, 0);
    if (fd < 0) {
        return -1;
    }
    memset(&ifr, 0, sizeof(ifr));
    strncpy(ifr.ifr_name, name, sizeof(ifr.ifr_name) - 1);
    if (ioctl(fd, SIOCGIFFLAGS, &ifr) == 0) {
        if (up) {
            ifr.ifr_flags |= IFF_UP;
        } else {
            ifr.ifr_flags &= ~IFF_UP;
        }
        r = ioctl(fd, SIOCSIFFLAGS, &ifr);
    }
    close(fd);
    return r;
}

static void sim_signals(ddyn_dbw_signals *s, int period)
{
    double t = period * (PERIOD_US * 1e-6);
    memset(s, 0, sizeof(*s));
    s->feedback.steering = 0.1 * sin(t);
    s->feedback.steering_rate = 0.1 * cos(t);
    s->feedback.throttle_pedal = 0.4;
    s->feedback.mode = DDYN_DBW_MODE_AUTONOMOUS;
    s->feedback.enabled = true;
    s->feedback.wheel_speed_front = 20.0 + t;
    s->feedback.wheel_speed_rear = 20.0 + t;
    s->sensors.yaw_rate = 0.3;
    s->sensors.accel_x = 1.0;
    s->sensors.accel_y = 6.0;
    s->sensors.gnss_x = 100.0 + 20.0 * t;
    s->sensors.gnss_y = -50.0;
    s->sensors.heading = 0.5;
    s->sensors.fix_type = 4;
}

/* ---- the drive-by-wire emulator (child process) ---- */

static int emu_send(ddyn_can_socket *sock, uint32_t id, const uint8_t *data, uint8_t len, emu_report *rep)
{
    int r = ddyn_can_send(sock, id, false, data, len);
    if (r == 0 && (id & DDYN_DBW_ID_BLOCK_MASK) == DDYN_DBW_ID_BLOCK_BASE &&
        id != ddyn_dbw_frame_id(DDYN_DBW_FRAME_COMMAND)) {
        rep->block_frames_sent++;
    }
    return r;
}

static void emulator(injection inj, uint64_t t0, int out_fd)
{
    ddyn_can_socket sock;
    ddyn_dbw unit; /* monitors the commands, and owns the feedback tx counters */
    ddyn_dbw_config cfg;
    emu_report rep;
    int p, f;
    memset(&rep, 0, sizeof(rep));
    rep.first_safe_period = -1;
    rep.last_autonomous_period = -1;
    ddyn_dbw_default_config(&cfg, DDYN_DBW_MONITOR_DBW_UNIT);
    if (ddyn_dbw_init(&unit, &cfg) != 0 || ddyn_dbw_socketcan_open(&sock, iface, DDYN_DBW_ROLE_DBW_UNIT) != 0) {
        rep.setup_error = 1;
        (void)!write(out_fd, &rep, sizeof(rep));
        _exit(1);
    }
    for (p = 0; p < PERIODS; ++p) {
        uint64_t start = t0 + (uint64_t)p * PERIOD_US;
        ddyn_dbw_signals s;
        uint8_t data[8];
        sleep_until(start);
        sim_signals(&s, p);
        if (p == INJECT_PERIOD) {
            switch (inj) {
            case INJ_COUNTER_JUMP: unit.tx_counter[DDYN_DBW_FRAME_STATUS] += 2u; break;
            case INJ_COUNTER_REPEAT: unit.tx_counter[DDYN_DBW_FRAME_STEERING] += 15u; break;
            case INJ_IFACE_GONE:
                (void)set_link_up(iface, 0);
                sleep_until(start + 2u * PERIOD_US);
                (void)set_link_up(iface, 1);
                break;
            default: break;
            }
        }
        for (f = DDYN_DBW_FRAME_STEERING; f < (int)DDYN_DBW_FRAME_COUNT; ++f) {
            uint32_t id = ddyn_dbw_frame_id((ddyn_dbw_frame)f);
            uint8_t len = 8;
            if (inj == INJ_STALE && f == DDYN_DBW_FRAME_IMU && p >= INJECT_PERIOD &&
                p < INJECT_PERIOD + STALE_GAP_PERIODS) {
                continue;
            }
            if (ddyn_dbw_next_frame(&unit, (ddyn_dbw_frame)f, &s, data) != 0) {
                rep.setup_error = 2;
                continue;
            }
            if (p == INJECT_PERIOD) {
                if (inj == INJ_CHECKSUM && f == DDYN_DBW_FRAME_WHEEL_SPEEDS) {
                    data[7] ^= 0x5Au;
                } else if (inj == INJ_RANGE && f == DDYN_DBW_FRAME_GNSS_HEADING) {
                    data[0] = 0x00u; /* heading raw 32000 = 3.2 rad > 3.1416, checksum recomputed */
                    data[1] = 0x7Du;
                    data[7] = ddyn_dbw_checksum(id, data);
                } else if (inj == INJ_BAD_LENGTH && f == DDYN_DBW_FRAME_IMU) {
                    len = 6;
                }
            }
            (void)emu_send(&sock, id, data, len, &rep);
        }
        if (p == INJECT_PERIOD && inj == INJ_UNKNOWN) {
            const uint8_t z[8] = {0};
            (void)emu_send(&sock, 0x13Fu, z, 8, &rep);
        }
        if (p == INJECT_PERIOD && inj == INJ_BUS_OFF) {
            /* an error frame as a CAN controller's driver reports bus-off; vcan loops it back to
             * every socket whose error mask includes CAN_ERR_BUSOFF */
            struct can_frame ef;
            memset(&ef, 0, sizeof(ef));
            ef.can_id = CAN_ERR_FLAG | CAN_ERR_BUSOFF;
            ef.len = CAN_ERR_DLC;
            if (write(sock.fd, &ef, sizeof(ef)) != (ssize_t)sizeof(ef)) {
                rep.setup_error = 3;
            }
        }
        if (inj == INJ_NONE && p == 5) {
            /* frames the controller's filters must drop in the kernel: a foreign identifier, an
             * extended one, and a DBW_Command from some other controller */
            uint8_t cmd[8];
            ddyn_dbw_signals c;
            memset(&c, 0, sizeof(c));
            (void)ddyn_can_send(&sock, 0x200u, false, data, 8);
            (void)ddyn_can_send(&sock, 0x100u, true, data, 8);
            if (ddyn_dbw_encode(DDYN_DBW_FRAME_COMMAND, &c, 0, cmd) == 0) {
                (void)ddyn_can_send(&sock, ddyn_dbw_frame_id(DDYN_DBW_FRAME_COMMAND), false, cmd, 8);
            }
        }
        /* the controller's commands, one per controller period: the k-th command is the one of
         * the controller's period k whatever the scheduling, so "same period" is exact */
        {
            unsigned i;
            for (i = 0; i < 64u; ++i) {
                ddyn_can_rx rx;
                /* the last period waits 50 ms more: the controller's last command may be late */
                int r = ddyn_can_receive(&sock, &rx, start + PERIOD_US - 1000u + (p == PERIODS - 1 ? 50000u : 0u));
                if (r == 0) {
                    break;
                }
                if (r < 0 || rx.error) {
                    continue; /* the link loss of the iface_gone scenario, seen from this side */
                }
                if (ddyn_dbw_on_frame(&unit, rx.id, rx.data, rx.len, rx.t_mono_us) != DDYN_DBW_DECODE_OK ||
                    rx.id != ddyn_dbw_frame_id(DDYN_DBW_FRAME_COMMAND)) {
                    rep.commands_bad++;
                    continue;
                }
                /* the first safe command after autonomous driving began */
                if (unit.latest.command.mode == DDYN_DBW_MODE_SAFE_STOP && rep.last_autonomous_period >= 0 &&
                    rep.first_safe_period < 0) {
                    rep.first_safe_period = (int)rep.commands_good;
                }
                if (unit.latest.command.mode == DDYN_DBW_MODE_AUTONOMOUS) {
                    rep.last_autonomous_period = (int)rep.commands_good;
                }
                rep.commands_good++;
            }
            rep.commands_bad += unit.failures[DDYN_DBW_FAIL_COUNTER_JUMP] + unit.failures[DDYN_DBW_FAIL_COUNTER_REPEAT];
            unit.failures[DDYN_DBW_FAIL_COUNTER_JUMP] = unit.failures[DDYN_DBW_FAIL_COUNTER_REPEAT] = 0u;
        }
    }
    (void)!write(out_fd, &rep, sizeof(rep));
    ddyn_can_close(&sock);
    _exit(0);
}

/* ---- the controller (parent process) ---- */

typedef struct {
    ddyn_dbw dbw;
    ddyn_can_socket sock;
    int enables;
    int detect_period;       /* first period in which a failure was counted, or -1 */
    bool safe_at_detect;     /* the command computed in that very period was the safe command */
    int64_t stale_lateness_us; /* stale scenario: detection time - (last IMU + deadline) */
    ddyn_dbw_state final_state;
    /* timing (nominal scenario) */
    uint32_t n_lat;
    uint64_t lat_us[PERIODS * 8];
    uint32_t n_imu;
    uint64_t imu_t[PERIODS];
    bool stamps_monotone;
} ctl_run;

static int cmp_u64(const void *a, const void *b)
{
    uint64_t x = *(const uint64_t *)a, y = *(const uint64_t *)b;
    return x < y ? -1 : x > y;
}

static uint32_t total_failures(const ddyn_dbw *d)
{
    uint32_t n = 0u;
    unsigned k;
    for (k = 0; k < DDYN_DBW_FAIL_COUNT; ++k) {
        n += d->failures[k];
    }
    return n;
}

/* the nominal scenario's receive loop: like ddyn_dbw_socketcan_pump, keeping the timestamps */
static void receive_timed(ctl_run *c, uint64_t deadline)
{
    unsigned i;
    for (i = 0; i < 256u; ++i) {
        ddyn_can_rx rx;
        int r = ddyn_can_receive(&c->sock, &rx, deadline);
        if (r <= 0) {
            break;
        }
        if (rx.error) {
            continue;
        }
        if (rx.t_mono_us > rx.t_user_mono_us + 1u || rx.t_kernel_realtime_us == 0u) {
            c->stamps_monotone = false;
        }
        if (c->n_lat < sizeof(c->lat_us) / sizeof(c->lat_us[0])) {
            c->lat_us[c->n_lat++] = rx.t_user_mono_us - rx.t_mono_us;
        }
        if (rx.id == ddyn_dbw_frame_id(DDYN_DBW_FRAME_IMU) && c->n_imu < PERIODS) {
            if (c->n_imu > 0 && rx.t_mono_us <= c->imu_t[c->n_imu - 1]) {
                c->stamps_monotone = false;
            }
            c->imu_t[c->n_imu++] = rx.t_mono_us;
        }
        (void)ddyn_dbw_on_frame(&c->dbw, rx.id, rx.data, rx.len, rx.t_mono_us);
    }
}

static int controller(ctl_run *c, injection inj, uint64_t t0)
{
    ddyn_dbw_config cfg;
    int p;
    memset(c, 0, sizeof(*c));
    c->detect_period = -1;
    c->stamps_monotone = true;
    ddyn_dbw_default_config(&cfg, DDYN_DBW_MONITOR_CONTROLLER);
    if (ddyn_dbw_init(&c->dbw, &cfg) != 0) {
        return -1;
    }
    if (ddyn_dbw_socketcan_open(&c->sock, iface, DDYN_DBW_ROLE_CONTROLLER) != 0) {
        return -2;
    }
    for (p = 0; p < PERIODS; ++p) {
        uint64_t start = t0 + (uint64_t)p * PERIOD_US;
        ddyn_dbw_command desired = {0.5, 0.0, 0.05, true, DDYN_DBW_MODE_AUTONOMOUS}, sent;
        uint8_t data[8];
        if (inj == INJ_NONE) {
            receive_timed(c, start + PERIOD_US / 2u);
        } else {
            (void)ddyn_dbw_socketcan_pump(&c->sock, &c->dbw, start + PERIOD_US / 2u);
        }
        /* the operator's explicit enable, whenever the link is READY */
        if (ddyn_dbw_check(&c->dbw, ddyn_can_mono_us()) == DDYN_DBW_READY && ddyn_dbw_enable(&c->dbw) == 0) {
            c->enables++;
        }
        (void)ddyn_dbw_command_frame(&c->dbw, ddyn_can_mono_us(), &desired, &sent, data);
        if (c->detect_period < 0 && total_failures(&c->dbw) > 0u) {
            c->detect_period = p;
            c->stale_lateness_us = (int64_t)c->dbw.last_failure_us -
                                   (int64_t)(c->dbw.rx[DDYN_DBW_FRAME_IMU].last_rx_us + cfg.deadline_us[DDYN_DBW_FRAME_IMU]);
            c->safe_at_detect = sent.mode == DDYN_DBW_MODE_SAFE_STOP && sent.throttle == 0.0 &&
                                sent.brake == cfg.safe_brake && fabs(sent.steering - 0.05) < 1e-12;
        }
        (void)ddyn_dbw_socketcan_send(&c->sock, &c->dbw, DDYN_DBW_FRAME_COMMAND, data);
        /* drain until the period ends (the emulator sends at period starts) */
        if (inj == INJ_NONE) {
            receive_timed(c, start + PERIOD_US);
        } else {
            (void)ddyn_dbw_socketcan_pump(&c->sock, &c->dbw, start + PERIOD_US);
        }
    }
    c->final_state = c->dbw.state;
    return 0;
}

static void judge(injection inj, ctl_run *c, const emu_report *e)
{
    const char *name = INJ_NAMES[inj];
    const ddyn_dbw_failure kind = INJ_KIND[inj];
    unsigned k;
    int before = failures;
    if (e->setup_error) {
        fail(name, "emulator set-up error %d", e->setup_error);
        return;
    }
    for (k = 0; k < DDYN_DBW_FAIL_COUNT; ++k) {
        bool expected = k == (unsigned)kind;
        /* losing the link also starves every monitored frame: stale follows */
        bool tolerated = inj == INJ_IFACE_GONE && k == DDYN_DBW_FAIL_STALE;
        if (expected && kind == DDYN_DBW_FAIL_STALE ? c->dbw.failures[k] < 1u
            : expected && inj == INJ_IFACE_GONE    ? c->dbw.failures[k] < 1u
            : expected                             ? c->dbw.failures[k] != 1u
                                                   : (!tolerated && c->dbw.failures[k] != 0u)) {
            fail(name, "failure count %s = %u", ddyn_dbw_failure_name((ddyn_dbw_failure)k), c->dbw.failures[k]);
        }
    }
    if (c->final_state != DDYN_DBW_ACTIVE) {
        fail(name, "final state %s, expected active", ddyn_dbw_state_name(c->final_state));
    }
    if (inj == INJ_UNKNOWN) {
        /* an identifier the DBC lacks is counted, never fatal (issue 35): the car keeps driving */
        if (c->enables != 1) {
            fail(name, "%d enables, expected 1 (the link must not drop)", c->enables);
        }
        if (e->first_safe_period != -1) {
            fail(name, "a safe command at period %d for an unknown identifier", e->first_safe_period);
        }
        if (failures == before) {
            printf("ok %s: counted %u, not fatal: no safe command, autonomous throughout\n", name,
                   c->dbw.failures[kind]);
        }
        return;
    }
    if (inj == INJ_NONE) {
        uint64_t lat_med, lat_max, per[PERIODS], per_med;
        double per_mean;
        uint32_t i;
        if (c->enables != 1) {
            fail(name, "%d enables, expected 1", c->enables);
        }
        if (e->first_safe_period != -1) {
            fail(name, "a safe command at period %d without any failure", e->first_safe_period);
        }
        if (c->sock.rx_frames != e->block_frames_sent) {
            fail(name, "controller received %u frames, emulator sent %u in the block (filters?)",
                 c->sock.rx_frames, e->block_frames_sent);
        }
        if (e->commands_good != PERIODS || e->commands_bad != 0u) {
            fail(name, "emulator decoded %u good and %u bad commands of %d", e->commands_good, e->commands_bad, PERIODS);
        }
        if (!c->stamps_monotone || c->n_lat < 10u || c->n_imu < 10u) {
            fail(name, "kernel receive stamps missing, in the future or not increasing");
            return;
        }
        qsort(c->lat_us, c->n_lat, sizeof(uint64_t), cmp_u64);
        lat_med = c->lat_us[c->n_lat / 2];
        lat_max = c->lat_us[c->n_lat - 1];
        for (i = 1; i < c->n_imu; ++i) {
            per[i - 1] = c->imu_t[i] - c->imu_t[i - 1];
        }
        qsort(per, c->n_imu - 1, sizeof(uint64_t), cmp_u64);
        per_med = per[(c->n_imu - 1) / 2];
        /* the mean period is robust to an emulator that falls behind and catches up (it sleeps
         * to absolute times): bursts shorten some intervals and lengthen others */
        per_mean = (double)(c->imu_t[c->n_imu - 1] - c->imu_t[0]) / (double)(c->n_imu - 1);
        if (per_mean < 9000.0 || per_mean > 11000.0) {
            fail(name, "IMU mean period %.0f us, expected 10000 +- 1000", per_mean);
        }
        if (lat_med > 5000u) {
            fail(name, "kernel-to-user delay median %llu us > 5 ms", (unsigned long long)lat_med);
        }
        if (failures == before) {
            printf("ok %s: %u frames through the filters (foreign, extended and command frames dropped), "
                   "%u commands decoded; kernel-to-user delay median %llu us, max %llu us; IMU period mean %.0f us, "
                   "median %llu us\n",
                   name, c->sock.rx_frames, e->commands_good, (unsigned long long)lat_med,
                   (unsigned long long)lat_max, per_mean, (unsigned long long)per_med);
        }
        return;
    }
    /* the controller's and the emulator's periods are aligned to a common start, but under
     * scheduling jitter the injected frame may land in the controller's previous period */
    if (c->detect_period < INJECT_PERIOD - 1) {
        fail(name, "failure detected at period %d, before the injection at %d", c->detect_period, INJECT_PERIOD);
    }
    if (!c->safe_at_detect) {
        fail(name, "the command of the detection period %d was not the safe command", c->detect_period);
    }
    if (inj != INJ_IFACE_GONE && e->first_safe_period != c->detect_period) {
        fail(name, "the DBW unit got the first safe command in period %d, the failure was detected in %d",
             e->first_safe_period, c->detect_period);
    }
    if (inj == INJ_IFACE_GONE && e->first_safe_period < INJECT_PERIOD) {
        fail(name, "the DBW unit never got a safe command after the link came back");
    }
    /* the deadline is checked twice per period: a lapse is seen within one period of expiring */
    if (inj == INJ_STALE && (c->stale_lateness_us < 0 || c->stale_lateness_us > (int64_t)PERIOD_US)) {
        fail(name, "stale detected %lld us after the deadline expired, expected 0..%u", (long long)c->stale_lateness_us,
             PERIOD_US);
    }
    if (c->enables != 2) {
        fail(name, "%d enables, expected 2 (start, and after recovery)", c->enables);
    }
    if (e->last_autonomous_period <= e->first_safe_period) {
        fail(name, "no autonomous command after the safe one: no recovery");
    }
    if (inj != INJ_IFACE_GONE && e->commands_bad != 0u) {
        fail(name, "the DBW unit rejected %u commands", e->commands_bad);
    }
    if (failures == before) {
        printf("ok %s: counted %u, safe command in the detection period %d (the DBW unit got it as command %d), "
               "autonomous again after %u good frames + enable",
               name, c->dbw.failures[kind], c->detect_period, e->first_safe_period, c->dbw.config.recovery_good_frames);
        if (inj == INJ_STALE) {
            printf("; detected %lld us after the %u us deadline expired", (long long)c->stale_lateness_us,
                   c->dbw.config.deadline_us[DDYN_DBW_FRAME_IMU]);
        }
        printf("\n");
    }
}

static void run_scenario_once(injection inj)
{
    static ctl_run c;
    emu_report e;
    int fds[2], status = 0;
    pid_t pid;
    uint64_t t0;
    ssize_t n;
    if (pipe(fds) != 0) {
        fail(INJ_NAMES[inj], "pipe: %s", strerror(errno));
        return;
    }
    t0 = ddyn_can_mono_us() + 200000u; /* both ends start their periods together */
    pid = fork();
    if (pid < 0) {
        fail(INJ_NAMES[inj], "fork: %s", strerror(errno));
        return;
    }
    if (pid == 0) {
        close(fds[0]);
        emulator(inj, t0, fds[1]);
    }
    close(fds[1]);
    if (controller(&c, inj, t0) != 0) {
        fail(INJ_NAMES[inj], "controller set-up failed on %s: %s", iface, strerror(errno));
    }
    memset(&e, 0, sizeof(e));
    n = read(fds[0], &e, sizeof(e));
    close(fds[0]);
    waitpid(pid, &status, 0);
    ddyn_can_close(&c.sock);
    if (n != (ssize_t)sizeof(e)) {
        fail(INJ_NAMES[inj], "no report from the emulator process");
        return;
    }
    judge(inj, &c, &e);
}

static void run_scenario(injection inj)
{
    int attempt;
    for (attempt = 1; attempt <= ATTEMPTS; ++attempt) {
        int before = failures;
        fail_label = attempt < ATTEMPTS ? "attempt failed (will retry)" : "FAIL";
        run_scenario_once(inj);
        if (failures == before) {
            break;
        }
        if (attempt < ATTEMPTS) {
            failures = before; /* the retry decides */
        }
    }
    fail_label = "FAIL";
}

/* CAN FD (optional in the protocol, supported by the transport): a 64-byte FD frame reaches an
 * FD-enabled socket with its length and FD flag, and is withheld from a classic socket. The
 * guest's init sets vcan0's MTU to 72 (CANFD_MTU) so that vcan carries FD frames. */
static void check_can_fd(void)
{
    ddyn_can_socket tx, rx_fd, rx_classic;
    ddyn_can_rx r;
    uint8_t payload[64];
    int i, got;
    for (i = 0; i < 64; ++i) {
        payload[i] = (uint8_t)(i * 7 + 1);
    }
    if (ddyn_can_open(&tx, iface, NULL, 0, false, true) != 0 || ddyn_can_open(&rx_fd, iface, NULL, 0, false, true) != 0 ||
        ddyn_can_open(&rx_classic, iface, NULL, 0, false, false) != 0) {
        fail("can_fd", "cannot open FD sockets on %s: %s", iface, strerror(errno));
        return;
    }
    if (ddyn_can_send(&tx, 0x123u, false, payload, 64) != 0) {
        fail("can_fd", "sending a 64-byte FD frame failed: %s (is the MTU 72?)", strerror(errno));
    } else {
        got = ddyn_can_receive(&rx_fd, &r, ddyn_can_mono_us() + 200000u);
        if (got != 1 || !r.fd || r.len != 64 || r.id != 0x123u || memcmp(r.data, payload, 64) != 0) {
            fail("can_fd", "the FD socket did not receive the 64-byte frame intact (got %d, fd %d, len %u)", got,
                 got == 1 && r.fd, got == 1 ? r.len : 0u);
        } else if (ddyn_can_receive(&rx_classic, &r, ddyn_can_mono_us() + 50000u) != 0) {
            fail("can_fd", "a classic socket received an FD frame");
        } else {
            printf("ok can_fd: a 64-byte FD frame received intact by an FD socket, withheld from a classic one\n");
        }
    }
    ddyn_can_close(&tx);
    ddyn_can_close(&rx_fd);
    ddyn_can_close(&rx_classic);
}

int main(int argc, char **argv)
{
    int i;
    if (argc > 1) {
        iface = argv[1];
    }
    setvbuf(stdout, NULL, _IOLBF, 0);
    printf("test_vcan on %s: %d periods of %u us per scenario, failures injected at period %d\n", iface, PERIODS,
           PERIOD_US, INJECT_PERIOD);
    for (i = 0; i < (int)INJ_COUNT; ++i) {
        run_scenario((injection)i);
    }
    check_can_fd();
    printf("DDYN_VCAN_RESULT: %s (%d failed checks)\n", failures == 0 ? "PASS" : "FAIL", failures);
    return failures == 0 ? 0 : 1;
}
