/*
 * tests/m7/m7_controller.c - the controller step on an emulated Cortex-M7 (qemu-system-arm -M mps2-an500
 * -icount shift=0), replaying a recorded closed-loop segment (segment.h, generated/controller_segment.c).
 *
 * Pass 1 replays the segment's readings period by period through ddyn_ctrl_step (EKF, history, guard
 * network, MPC) from the recorded set-up and compares every command with the host build's: every
 * period within M7_U_TOL, at least M7_TIGHT_PERCENT % within M7_U_TIGHT (absolute, per component),
 * the same status bits in every period. After each period the host's applied command and MPC plan
 * are fed back (see the loop). Pass 2 replays the first M7_CAP_STEPS periods again with the
 * QP tolerance set to 1e-300, so that every QP runs to the iteration cap (qp_max_iterations): the
 * worst case with the cap reached. Instructions per step are counted with SysTick: under -icount
 * shift=0 qemu's virtual clock advances 1 ns per guest instruction, and the board's SysTick counts
 * the 25 MHz system clock of that virtual time, so one tick is 40 instructions (calibrated at start
 * on a loop of known length; the firmware fails when the factor is not 40, e.g. without -icount).
 * The stack is painted before pass 1 and scanned after both passes (high-water mark).
 *
 * Pass 3 counts the real-time iteration split: the segment's readings again, with ddyn_ctrl_prepare
 * after every step (the MPC's preparation after the command has left), so that each following step
 * is the feedback phase alone (docs/controller.md); instructions of both (not compared with the host).
 *
 * Frame authentication (docs/m7.md): after each step of passes 1, 2 and 4, counted apart, one 20 ms period's
 * SecOC work of the controller (auth_period: 10 authenticators verified, 1 encoded, the fixed test key); the
 * worst cases are enforced on the step plus its period's work. Pass 5 counts that work with an attacker's
 * frame held beside every genuine one (two MACs per verify; reported, not enforced).
 *
 * Prints "m7: key value" lines; exits 0 when the commands agree, the worst case of passes 1, 2 and 4 with
 * the authentication is at most M7_BOUND_INSN instructions (the target M7_MAX_INSN, 3 M: met since the QP runs on DAQP)
 * and the stack did not overflow, else 1 (qemu exits with that code).
 * With DAQP (the default solver; it has no tolerance to tighten) pass 2 starts every QP from a wrong
 * working set (ddyn_mpc_qp_daqp_adversarial_start), which it takes apart one constraint per iteration.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "ddyn/controller.h"
#include "ddyn/dbw.h"
#include "ddyn_dbw_test_key.h" /* the fixed TEST key made at configure time (cmake/dbw_test_key.cmake) */
#include "m7_board.h"
#include "segment.h"

#ifndef M7_MAX_INSN
#define M7_MAX_INSN 3000000ul /* target: 5 ms at 600 MHz at one instruction per cycle, a quarter of a 50 Hz period */
#endif
#ifndef M7_BOUND_INSN
/* what the test enforces: the target itself. With the DAQP QP (cap 30) the worst case measured
 * 1.77 M instructions on the segment and 2.39 M with every QP at the cap (docs/m7.md) */
#define M7_BOUND_INSN M7_MAX_INSN
#endif
#ifndef M7_U_TOL
#define M7_U_TOL 1e-3 /* absolute, per command component (dthrottle 1/s, dsteering rad/s), every period */
#endif
#ifndef M7_U_TIGHT
#define M7_U_TIGHT 1e-6 /* ... and at least M7_TIGHT_PERCENT % of the periods within this */
#endif
#ifndef M7_TIGHT_PERCENT
#define M7_TIGHT_PERCENT 95
#endif
#ifndef M7_CAP_STEPS
#define M7_CAP_STEPS 300
#endif
#ifndef M7_MASS_OFFSET
#define M7_MASS_OFFSET 0.2 /* pass 6's known mass offset (ddyn/controller.h) */
#endif
#ifndef M7_DOWNFORCE
#define M7_DOWNFORCE 0.03 /* pass 6's known downforce, s^2/m^2: every model evaluation scales the tyre peaks at its
                             own speed (ddyn_model_downforce; 1.27 times the load at 3 m/s) */
#endif
#ifndef M7_DELAY_STEPS
#define M7_DELAY_STEPS 300 /* pass 6 (cold path with the delays at the maximum) replays this many, per variant */
#define M7_LAG_S 0.1       /* pass 6's steering lag (s): the lag runs in the filter's period, through the whole
                              pipe and inverts the first command (ddyn/controller.h "steering lag") */
#define M7_BANK_RAD 0.35   /* pass 6's road bank (issue 34): a profile along the raceline swinging +-0.35 rad (20
                              degrees, the banked oval's turns) twice a lap; the MPC looks up each stage's bank, the
                              filter and every step through the pipe theirs (ddyn_ctrl_set_bank) */
#define M7_GRADE_RAD 0.05  /* pass 6's road grade (issue 34): +-0.05 rad, three hills a lap, looked up with the bank in
                              one projection per stage (ddyn_ctrl_set_grade) */
#endif
#ifndef M7_COLD_STEPS
#define M7_COLD_STEPS 5000 /* pass 4 replays min(this, the segment's periods) */
#endif
#ifndef M7_MAX_STEPS
#define M7_MAX_STEPS 5000 /* pass 1 replays min(this, the segment's periods) */
#endif
#define INSN_PER_TICK 40u /* 1 ns per instruction (-icount shift=0) / 25 MHz SysTick clock */
#define STACK_PAINT 0xA5A5A5A5u

extern const ddyn_net_tables ddyn_net_weights;
extern uint32_t __stack_bottom, __stack_top;

static ddyn_ctrl ctl;
static uint32_t insn[5000], sorted[5000];
static double track_col[7][DDYN_MPC_MAX_TRACK_POINTS]; /* the columns, the bank and the grade (pass 6) */

/* ---- console output without stdio (semihosting SYS_WRITE0) ---- */
static char line[160];
static int line_len;

static void put_str(const char *s)
{
    while (*s && line_len < (int)sizeof line - 1) {
        line[line_len++] = *s++;
    }
}
static void put_ulong(unsigned long v)
{
    char buf[24];
    int n = 0;
    do {
        buf[n++] = (char)('0' + v % 10u);
        v /= 10u;
    } while (v && n < (int)sizeof buf);
    while (n > 0 && line_len < (int)sizeof line - 1) {
        line[line_len++] = buf[--n];
    }
}
/* %.3e-like: enough to state a difference or a tolerance */
static void put_sci(double v)
{
    int e = 0;
    unsigned long m;
    if (!isfinite(v)) {
        put_str("nan");
        return;
    }
    if (v < 0.0) {
        put_str("-");
        v = -v;
    }
    if (v == 0.0) {
        put_str("0");
        return;
    }
    while (v >= 10.0 && e < 400) {
        v /= 10.0;
        ++e;
    }
    while (v < 1.0 && e > -400) {
        v *= 10.0;
        --e;
    }
    m = (unsigned long)(v * 1000.0 + 0.5);
    if (m >= 10000u) {
        m /= 10u;
        ++e;
    }
    put_ulong(m / 1000u);
    put_str(".");
    line[line_len++] = (char)('0' + (m / 100u) % 10u);
    line[line_len++] = (char)('0' + (m / 10u) % 10u);
    line[line_len++] = (char)('0' + m % 10u);
    put_str(e < 0 ? "e-" : "e+");
    put_ulong((unsigned long)(e < 0 ? -e : e));
}
static void flush(void)
{
    line[line_len++] = '\n';
    line[line_len] = '\0';
    m7_puts(line);
    line_len = 0;
}
static void kv(const char *key, unsigned long v)
{
    put_str("m7: ");
    put_str(key);
    put_str(" ");
    put_ulong(v);
    flush();
}

#ifdef M7_PROFILE
/* Profiling build (scripts/m7_profile.sh): SysTick interrupts every M7_PROFILE ticks (40 M7_PROFILE
 * instructions) during pass 1 (with M7_PROFILE_COLD: during pass 4's steps, the cold path, instead) and the
 * handler counts the interrupted PC in 16-byte buckets; the instruction counts of such a build include
 * the handler and are not the figures. */
#define PROFILE_BUCKETS (0x100000u >> 4) /* the first MB of code */
static uint32_t profile_hist[PROFILE_BUCKETS];
static volatile int profiling;
void m7_profile_sample(const uint32_t *frame);
void m7_profile_sample(const uint32_t *frame)
{
    uint32_t pc = frame[6]; /* exception frame: r0-r3, r12, lr, pc, xpsr */
    if (profiling && pc < 0x100000u) {
        profile_hist[pc >> 4] += 1u;
    }
}
__attribute__((naked)) void m7_systick(void);
void m7_systick(void)
{
    __asm__ volatile("mrs r0, msp\n\tb m7_profile_sample");
}
static void profile_dump(void);
#endif

/* ---- SysTick: 24-bit down-counter on the processor clock ---- */
#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)

static uint32_t ticks_since(uint32_t start)
{
    return (start - SYST_CVR) & 0xFFFFFFu;
}

/* 1 + 2n instructions (subs, bne per round) */
static uint32_t count_loop(uint32_t n)
{
    uint32_t t0 = SYST_CVR;
    __asm__ volatile("1: subs %0, %0, #1\n\tbne 1b" : "+r"(n)::"cc");
    return ticks_since(t0);
}

static uint32_t median_of(const uint32_t *v, int n)
{
    int i, j;
    memcpy(sorted, v, (size_t)n * sizeof *v);
    for (i = 1; i < n; ++i) { /* insertion sort: n is a few thousand at most */
        uint32_t x = sorted[i];
        for (j = i; j > 0 && sorted[j - 1] > x; --j) {
            sorted[j] = sorted[j - 1];
        }
        sorted[j] = x;
    }
    return n % 2 ? sorted[n / 2] : (sorted[n / 2 - 1] + sorted[n / 2]) / 2u;
}

/* max_delay: both actuation delays at the compiled maximum (DDYN_CTRL_MAX_DELAY_STEPS periods), the
 * steering lag (M7_LAG_S) and the road's bank (M7_BANK_RAD), pass 6 */
static int controller_init(double qp_tolerance, int max_delay)
{
    const ddyn_vehicle_model *model = ddyn_model_find(m7_seg_vehicle);
    ddyn_ctrl_config cfg;
    int i, k;
    if (model == NULL || ddyn_ctrl_default_config(model, &cfg) != DDYN_OK) {
        return 0;
    }
    memcpy(cfg.c_nominal, m7_seg_c_nominal, sizeof cfg.c_nominal);
    memcpy(cfg.q_diag, m7_seg_q_diag, sizeof cfg.q_diag);
    for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
        double sd = m7_seg_r_std[k];
        for (i = 0; i < DDYN_MEAS_MAX_DIM; ++i) {
            cfg.r_diag[k][i] = sd > 0.0 ? sd * sd : 1e-8;
        }
    }
    if (qp_tolerance > 0.0) {
        cfg.mpc.qp_tolerance = qp_tolerance;
    }
    if (max_delay) {
        /* 1: both delays at the maximum (the pipe's most model steps; the MPC's horizon is then shortened
         * by as many stages, ddyn/controller.h); 2: the throttle's alone (the full horizon with its most
         * known stages) */
        cfg.delay.steering = max_delay == 1 ? DDYN_CTRL_MAX_DELAY_STEPS * model->sample_time : 0.0;
        cfg.delay.throttle = DDYN_CTRL_MAX_DELAY_STEPS * model->sample_time;
        cfg.lag.steering = M7_LAG_S;
        cfg.mass_offset = M7_MASS_OFFSET; /* its coefficients scaled every period, the line's speeds scaled */
        cfg.downforce = M7_DOWNFORCE;
    }
#ifdef M7_QP_CAP /* exploring other caps (docs/m7.md); pass 1 then no longer matches the recording */
    cfg.mpc.qp_max_iterations = M7_QP_CAP;
#endif
    for (i = 0; i < m7_seg_track_n; ++i) {
        for (k = 0; k < 5; ++k) {
            track_col[k][i] = m7_seg_track[i][k];
        }
    }
    for (i = 0; i < m7_seg_track_n; ++i) {
        track_col[5][i] = M7_BANK_RAD * sin(4.0 * 3.14159265358979323846 * i / m7_seg_track_n);
        track_col[6][i] = M7_GRADE_RAD * sin(6.0 * 3.14159265358979323846 * i / m7_seg_track_n);
    }
    return ddyn_ctrl_init(&ctl, model, &ddyn_net_weights, &cfg, m7_seg_x0) == DDYN_OK &&
           ddyn_ctrl_set_track(&ctl, m7_seg_track_n, track_col[0], track_col[1], track_col[2], track_col[3],
                               track_col[4]) == DDYN_OK &&
           (!max_delay || (ddyn_ctrl_set_bank(&ctl, track_col[5]) == DDYN_OK &&
                           ddyn_ctrl_set_grade(&ctl, track_col[6]) == DDYN_OK));
}

static void input_of(const m7_seg_period *p, ddyn_ctrl_input *in)
{
    int k;
    memset(in, 0, sizeof *in);
    for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
        in->reading[k].valid = (p->valid >> k) & 1u;
        memcpy(in->reading[k].z, &p->z[k * DDYN_MEAS_MAX_DIM], sizeof in->reading[k].z);
    }
}

/* ---- frame authentication: one control period's work on the controller (docs/can.md, docs/m7.md) ----
 * The controller verifies an authenticator per protected frame it acts on and signs its command. In one
 * 20 ms period of the segment (50 Hz) the DBC's cycle times (can/ddyn_dbw.dbc: DBW_Steering, DBW_Status,
 * DBW_WheelSpeeds and IMU every 10 ms, GNSS_Position and GNSS_Heading every 20 ms) bring 10 protected
 * frames, each followed by its own authenticator (SecOC_DBW 0x113 or SecOC_Sensors 0x121): 10 holds,
 * 10 verifies (one keyed-BLAKE2b MAC each, two with an injected frame held beside the genuine one), one
 * expire at the period's end, and one authenticator (SecOC_Controller) signed for DBW_Command. Every MAC
 * of the controller's goes on from its key state prepared once at ddyn_dbw_auth_init (one compression, not
 * two). The senders' side (the frames and their authenticators, with the key: two compressions each) is made
 * outside the counted region. */
#define AUTH_RX_PER_PERIOD 10
#define AUTH_PERIOD_US 20000u
static const ddyn_dbw_frame auth_rx_frames[AUTH_RX_PER_PERIOD] = {
    DDYN_DBW_FRAME_STEERING, DDYN_DBW_FRAME_STATUS, DDYN_DBW_FRAME_WHEEL_SPEEDS, DDYN_DBW_FRAME_IMU,
    DDYN_DBW_FRAME_GNSS_POSITION, DDYN_DBW_FRAME_GNSS_HEADING,                            /* at 0 ms */
    DDYN_DBW_FRAME_STEERING, DDYN_DBW_FRAME_STATUS, DDYN_DBW_FRAME_WHEEL_SPEEDS, DDYN_DBW_FRAME_IMU}; /* 10 ms */
static ddyn_dbw_auth auth_rx;                          /* the controller's receiver state */
static uint64_t auth_tx_fresh[DDYN_DBW_FRAME_COUNT];   /* the senders' freshness values ... */
static uint8_t auth_tx_counter[DDYN_DBW_FRAME_COUNT];  /* ... and authenticator counters (per frame: enough here) */
static uint64_t auth_cmd_fresh;                        /* the controller's own, for DBW_Command */
static uint32_t auth_seed = 12345u;
static uint32_t auth_insn[5000], with_auth[5000];

static void auth_reset(void)
{
    ddyn_dbw_auth_init(&auth_rx, DDYN_DBW_TEST_KEY, 0u); /* timeout 0: the default 5 ms */
    memset(auth_tx_fresh, 0, sizeof auth_tx_fresh);
    memset(auth_tx_counter, 0, sizeof auth_tx_counter);
    auth_cmd_fresh = 0u;
}

static void auth_bytes(uint8_t d[DDYN_DBW_FRAME_LEN])
{
    unsigned k;
    for (k = 0; k < DDYN_DBW_FRAME_LEN; ++k) {
        auth_seed = auth_seed * 1664525u + 1013904223u;
        d[k] = (uint8_t)(auth_seed >> 24);
    }
}

/* One period's authentication work; returns its instructions. inject: an attacker's frame of the same
 * identifier arrives between each genuine frame and its authenticator (held beside it: the verify then
 * computes two MACs). *bad counts authenticators not accepted or frames not released intact. */
static uint32_t auth_period(int period, int inject, const double u[DDYN_NU], int *bad)
{
    static uint8_t data[AUTH_RX_PER_PERIOD][DDYN_DBW_FRAME_LEN], fake[AUTH_RX_PER_PERIOD][DDYN_DBW_FRAME_LEN];
    static uint8_t auth[AUTH_RX_PER_PERIOD][DDYN_DBW_FRAME_LEN], out[AUTH_RX_PER_PERIOD][DDYN_DBW_FRAME_LEN];
    static ddyn_dbw_failure res[AUTH_RX_PER_PERIOD];
    static ddyn_dbw_frame got[AUTH_RX_PER_PERIOD];
    uint8_t cmd[DDYN_DBW_FRAME_LEN], cmd_auth[DDYN_DBW_FRAME_LEN];
    const uint64_t t0_us = (uint64_t)period * AUTH_PERIOD_US;
    uint64_t t_us, data_t_us;
    uint32_t auth_id[AUTH_RX_PER_PERIOD], t0, n;
    int j;
    /* the senders (not counted): frames, their authenticators, the attacker's frames */
    for (j = 0; j < AUTH_RX_PER_PERIOD; ++j) {
        const ddyn_dbw_frame f = auth_rx_frames[j];
        auth_bytes(data[j]);
        auth_bytes(fake[j]);
        auth_id[j] = ddyn_dbw_auth_id(f);
        if (ddyn_dbw_auth_encode(DDYN_DBW_TEST_KEY, f, data[j], auth_tx_fresh[f]++, auth_tx_counter[f]++,
                                 auth[j]) != DDYN_OK) {
            ++*bad;
        }
    }
    memset(cmd, 0, sizeof cmd); /* the command frame's bytes: its rates here (the MAC's cost does not depend on them) */
    memcpy(cmd, &u[0], sizeof cmd < sizeof u[0] ? sizeof cmd : sizeof u[0]);
    t0 = SYST_CVR;
    for (j = 0; j < AUTH_RX_PER_PERIOD; ++j) {
        t_us = t0_us + (j < 6 ? 0u : 10000u) + 200u * (unsigned)j;
        (void)ddyn_dbw_auth_hold(&auth_rx, auth_rx_frames[j], data[j], t_us);
        if (inject) {
            (void)ddyn_dbw_auth_hold(&auth_rx, auth_rx_frames[j], fake[j], t_us + 50u);
        }
        res[j] = ddyn_dbw_auth_verify(&auth_rx, auth_id[j], auth[j], DDYN_DBW_FRAME_LEN, t_us + 100u, &got[j],
                                      out[j], &data_t_us);
    }
    (void)ddyn_dbw_auth_expire(&auth_rx, t0_us + AUTH_PERIOD_US, NULL);
    /* signed with the controller's prepared key state (one BLAKE2b compression per MAC, issue 35) */
    (void)ddyn_dbw_auth_sign(&auth_rx, DDYN_DBW_FRAME_COMMAND, cmd, auth_cmd_fresh, (uint8_t)(auth_cmd_fresh % 16u),
                             cmd_auth);
    n = ticks_since(t0) * INSN_PER_TICK;
    for (j = 0; j < AUTH_RX_PER_PERIOD; ++j) {
        *bad += res[j] != DDYN_DBW_FAIL_COUNT || got[j] != auth_rx_frames[j] ||
                memcmp(out[j], data[j], DDYN_DBW_FRAME_LEN) != 0;
    }
    *bad += cmd_auth[7] != ddyn_dbw_checksum(ddyn_dbw_auth_id(DDYN_DBW_FRAME_COMMAND), cmd_auth);
    /* the same bytes as the one-shot keyed BLAKE2b with the key (not counted) */
    {
        uint8_t want[DDYN_DBW_FRAME_LEN];
        *bad += ddyn_dbw_auth_encode(DDYN_DBW_TEST_KEY, DDYN_DBW_FRAME_COMMAND, cmd, auth_cmd_fresh,
                                     (uint8_t)(auth_cmd_fresh % 16u), want) != DDYN_OK ||
                memcmp(want, cmd_auth, sizeof want) != 0;
    }
    ++auth_cmd_fresh;
    return n;
}

static uint32_t max_of(const uint32_t *v, int n)
{
    uint32_t m = 0u;
    int i;
    for (i = 0; i < n; ++i) {
        m = v[i] > m ? v[i] : m;
    }
    return m;
}

/* the firmware's stack pointer now */
static uintptr_t stack_pointer(void)
{
    uintptr_t sp;
    __asm__ volatile("mov %0, sp" : "=r"(sp));
    return sp;
}

#ifdef M7_PROFILE
static void profile_dump(void)
{
    uint32_t b;
    profiling = 0;
    SYST_CSR = 0u;
    for (b = 0; b < PROFILE_BUCKETS; ++b) {
        if (profile_hist[b]) {
            put_str("m7: profile ");
            put_ulong((unsigned long)b << 4);
            put_str(" ");
            put_ulong(profile_hist[b]);
            flush();
        }
    }
}
#endif

int main(void)
{
    const int steps = m7_seg_steps < M7_MAX_STEPS ? m7_seg_steps : M7_MAX_STEPS;
    const int cap_steps = M7_CAP_STEPS < steps ? M7_CAP_STEPS : steps;
    const int cold_steps = M7_COLD_STEPS < steps ? M7_COLD_STEPS : steps;
    const int delay_steps = M7_DELAY_STEPS < steps ? M7_DELAY_STEPS : steps;
    uint32_t c1, c4, worst = 0, worst_cap = 0, worst_cold = 0, worst_capped_pass1 = 0, *p;
    uint32_t worst_auth = 0, worst_with_auth = 0, worst_cap_with_auth = 0, worst_cold_with_auth = 0;
    uint32_t worst_auth_injected = 0, worst_delay = 0, worst_delay_with_auth = 0;
    int auth_bad = 0;
    uintptr_t sp_main;
    int i, k, fail = 0, mismatch = 0, loose = 0, status_diff = 0, iter_diff = 0, capped_pass1 = 0, worst_step = 0;
    double max_du[DDYN_NU] = {0.0, 0.0};

    SYST_RVR = 0xFFFFFFu;
    SYST_CVR = 0u;
    SYST_CSR = 5u; /* enable, processor clock, no interrupt */

    /* calibration: instructions per tick on two loop lengths */
    c1 = count_loop(100000u);
    c4 = count_loop(400000u);
    put_str("m7: calibration ticks ");
    put_ulong(c1);
    put_str(" / ");
    put_ulong(c4);
    put_str(" for 200001 / 800001 instructions");
    flush();
    if (c1 < 4990u || c1 > 5010u || c4 < 19990u || c4 > 20010u) {
        m7_puts("m7: FAIL: SysTick does not count 40 instructions per tick: run qemu with -icount shift=0\n");
        return 1;
    }

    kv("sizeof_ddyn_ctrl_bytes", (unsigned long)sizeof(ddyn_ctrl));
    kv("sizeof_ddyn_mpc_bytes", (unsigned long)sizeof(ddyn_mpc));
    kv("sizeof_ddyn_mpc_qp_bytes", (unsigned long)sizeof(ddyn_mpc_qp));
    kv("sizeof_ddyn_ekf_bytes", (unsigned long)sizeof(ddyn_ekf));
    kv("sizeof_ddyn_guard_net_bytes", (unsigned long)sizeof(ddyn_guard_net));
    if (!controller_init(0.0, 0)) {
        m7_puts("m7: FAIL: controller refused the recorded set-up\n");
        return 1;
    }

    /* paint the stack below this frame */
    sp_main = stack_pointer();
    for (p = &__stack_bottom; (uintptr_t)p < sp_main - 64u; ++p) {
        *p = STACK_PAINT;
    }

#ifdef M7_PROFILE
    SYST_RVR = M7_PROFILE - 1u;
    SYST_CVR = 0u;
    SYST_CSR = 7u; /* enable, processor clock, interrupt */
#ifndef M7_PROFILE_COLD
    profiling = 1;
#endif
#endif
    /* pass 1: the recorded segment, commands compared with the host's */
    auth_reset();
    for (i = 0; i < steps; ++i) {
        const m7_seg_period *rec = &m7_seg_periods[i];
        ddyn_ctrl_input in;
        ddyn_ctrl_output out;
        uint32_t t0;
        input_of(rec, &in);
        t0 = SYST_CVR;
        ddyn_ctrl_step(&ctl, &in, &out);
        insn[i] = ticks_since(t0) * INSN_PER_TICK;
        worst = insn[i] > worst ? insn[i] : worst;
        if (insn[i] == worst) {
            worst_step = i;
        }
#ifndef M7_PROFILE /* the profile is of the step alone */
        /* this period's frame authentication, counted apart (it does not touch the controller) */
        auth_insn[i] = auth_period(i, 0, rec->u, &auth_bad);
        with_auth[i] = insn[i] + auth_insn[i];
#endif
        for (k = 0; k < DDYN_NU; ++k) {
            double d = fabs(out.u[k] - rec->u[k]);
            if (!(d <= M7_U_TOL)) {
                if (mismatch < 5) {
                    put_str("m7: command differs at period ");
                    put_ulong((unsigned long)i);
                    put_str(": |du| ");
                    put_sci(d);
                    flush();
                }
                ++mismatch;
            }
            max_du[k] = d > max_du[k] || !isfinite(d) ? d : max_du[k];
        }
#ifdef M7_DEBUG
        if (i < M7_DEBUG) {
            put_str("dbg ");
            put_ulong((unsigned long)i);
            put_str(" st ");
            put_ulong(out.status);
            put_str(" ");
            put_ulong(rec->status);
            put_str(" it ");
            put_ulong((unsigned long)out.mpc_info.qp_iterations);
            put_str(" ");
            put_ulong((unsigned long)rec->qp_iterations);
            put_str(" du ");
            put_sci(fabs(out.u[0] - rec->u[0]));
            put_str(" ");
            put_sci(fabs(out.u[1] - rec->u[1]));
            flush();
        }
#endif
        loose += !(fabs(out.u[0] - rec->u[0]) <= M7_U_TIGHT && fabs(out.u[1] - rec->u[1]) <= M7_U_TIGHT);
        status_diff += out.status != rec->status;
        /* each period is compared from the host's state: the car applied the host's command in the
         * recording, so the filter and the history go on from that one (as on the car), and the MPC's
         * warm start is the host's plan. Without this a last-bit difference of the two C libraries'
         * sin/cos/atan grows through the integrator states (throttle, steering: no sensor corrects
         * them) and the real-time iteration's warm start until whole stretches differ (docs/m7.md). */
#ifndef M7_NO_FEEDBACK /* scripts/m7_no_feedback.sh: what happens without it */
        memcpy(ctl.u_prev, rec->u, sizeof ctl.u_prev);
        memcpy(ctl.mpc.u_plan, rec->u_plan, sizeof ctl.mpc.u_plan);
        ctl.mpc.last_index = rec->last_index;
#endif
        iter_diff += out.mpc_info.qp_iterations != rec->qp_iterations;
        if (out.status & DDYN_CTRL_MPC_NOT_CONVERGED) {
            ++capped_pass1;
            worst_capped_pass1 = insn[i] > worst_capped_pass1 ? insn[i] : worst_capped_pass1;
        }
    }
#if defined(M7_PROFILE) && !defined(M7_PROFILE_COLD)
    profile_dump();
    return 0;
#endif
    kv("periods", (unsigned long)steps);
    kv("insn_per_step_median", (unsigned long)median_of(insn, steps));
    kv("insn_per_step_max", (unsigned long)worst);
    kv("insn_per_step_max_period", (unsigned long)worst_step);
    kv("periods_qp_cap_reached", (unsigned long)capped_pass1);
    kv("insn_per_step_max_qp_cap_reached", (unsigned long)worst_capped_pass1);
    worst_auth = max_of(auth_insn, steps);
    worst_with_auth = max_of(with_auth, steps);
    kv("auth_frames_verified_per_period", AUTH_RX_PER_PERIOD);
    kv("auth_insn_per_period_median", (unsigned long)median_of(auth_insn, steps));
    kv("auth_insn_per_period_max", (unsigned long)worst_auth);
    kv("insn_per_step_with_auth_median", (unsigned long)median_of(with_auth, steps));
    kv("insn_per_step_with_auth_max", (unsigned long)worst_with_auth);
    put_str("m7: max_abs_du dthrottle ");
    put_sci(max_du[0]);
    put_str(" dsteering ");
    put_sci(max_du[1]);
    put_str(" tolerance ");
    put_sci(M7_U_TOL);
    flush();
    kv("commands_outside_tolerance", (unsigned long)mismatch);
    put_str("m7: periods_outside_tight_tolerance ");
    put_ulong((unsigned long)loose);
    put_str(" (tight ");
    put_sci(M7_U_TIGHT);
    put_str(", allowed ");
    put_ulong((unsigned long)(100 - M7_TIGHT_PERCENT));
    put_str(" %)");
    flush();
    kv("periods_status_differs", (unsigned long)status_diff);
    kv("periods_qp_iterations_differ", (unsigned long)iter_diff);

    /* pass 2: every QP to the iteration cap */
    if (!controller_init(1e-300, 0)) {
        m7_puts("m7: FAIL: controller refused the set-up of pass 2\n");
        return 1;
    }
    {
        int capped = 0;
        auth_reset();
        for (i = 0; i < cap_steps; ++i) {
            ddyn_ctrl_input in;
            ddyn_ctrl_output out;
            uint32_t t0;
            input_of(&m7_seg_periods[i], &in);
            /* DAQP (the default solver) ignores the tolerance: it starts from a wrong working set
             * instead, which it takes apart one constraint per iteration */
            ddyn_mpc_qp_daqp_adversarial_start(&ctl.mpc.daqp, ctl.cfg.mpc.horizon);
            t0 = SYST_CVR;
            ddyn_ctrl_step(&ctl, &in, &out);
            insn[i] = ticks_since(t0) * INSN_PER_TICK;
            capped += out.mpc_info.qp_iterations == ctl.cfg.mpc.qp_max_iterations;
            worst_cap = insn[i] > worst_cap ? insn[i] : worst_cap;
            auth_insn[i] = auth_period(i, 0, m7_seg_periods[i].u, &auth_bad);
            with_auth[i] = insn[i] + auth_insn[i];
        }
        kv("cap_pass_periods", (unsigned long)cap_steps);
        kv("cap_pass_qp_max_iterations", (unsigned long)ctl.cfg.mpc.qp_max_iterations);
        kv("cap_pass_periods_at_cap", (unsigned long)capped);
        kv("cap_pass_insn_per_step_median", (unsigned long)median_of(insn, cap_steps));
        kv("cap_pass_insn_per_step_max", (unsigned long)worst_cap);
        worst_cap_with_auth = max_of(with_auth, cap_steps);
        worst_auth = max_of(auth_insn, cap_steps) > worst_auth ? max_of(auth_insn, cap_steps) : worst_auth;
        kv("cap_pass_insn_per_step_with_auth_median", (unsigned long)median_of(with_auth, cap_steps));
        kv("cap_pass_insn_per_step_with_auth_max", (unsigned long)worst_cap_with_auth);
        if (capped == 0) {
            m7_puts("m7: FAIL: no QP of pass 2 reached the iteration cap\n");
            fail = 1;
        }
    }

    /* pass 4: the cold-start path in every period, at its cap. Before each step the MPC is reset as
     * the controller's recovery and a start from standstill leave it (ddyn_mpc_reset: no plan to
     * linearise along, DAQP without a working set), so that every QP takes the cold path: the interior
     * point with its own cap (qp_cold_max_iterations), forced to that cap by the tolerance 1e-300, then
     * DAQP's working set seeded from its solution. The host's applied command is fed back (as in pass 1)
     * so that the filter follows the recording. */
    if (!controller_init(1e-300, 0)) {
        m7_puts("m7: FAIL: controller refused the set-up of pass 4\n");
        return 1;
    }
    {
        int cold = 0, at_cap = 0;
        auth_reset();
        for (i = 0; i < cold_steps; ++i) {
            ddyn_ctrl_input in;
            ddyn_ctrl_output out;
            uint32_t t0;
            input_of(&m7_seg_periods[i], &in);
            ddyn_mpc_reset(&ctl.mpc);
#ifdef M7_PROFILE_COLD
            profiling = 1;
#endif
            t0 = SYST_CVR;
            ddyn_ctrl_step(&ctl, &in, &out);
            insn[i] = ticks_since(t0) * INSN_PER_TICK;
#ifdef M7_PROFILE_COLD
            profiling = 0;
#endif
            cold += out.mpc_info.qp_cold_start;
            at_cap += out.mpc_info.qp_cold_start && out.mpc_info.qp_iterations == ctl.cfg.mpc.qp_cold_max_iterations;
            worst_cold = insn[i] > worst_cold ? insn[i] : worst_cold;
            auth_insn[i] = auth_period(i, 0, m7_seg_periods[i].u, &auth_bad);
            with_auth[i] = insn[i] + auth_insn[i];
            memcpy(ctl.u_prev, m7_seg_periods[i].u, sizeof ctl.u_prev);
        }
        kv("cold_pass_periods", (unsigned long)cold_steps);
        kv("cold_pass_qp_cold_max_iterations", (unsigned long)ctl.cfg.mpc.qp_cold_max_iterations);
        kv("cold_pass_periods_cold_start", (unsigned long)cold);
        kv("cold_pass_periods_at_cold_cap", (unsigned long)at_cap);
        kv("cold_pass_insn_per_step_median", (unsigned long)median_of(insn, cold_steps));
        kv("cold_pass_insn_per_step_max", (unsigned long)worst_cold);
        worst_cold_with_auth = max_of(with_auth, cold_steps);
        worst_auth = max_of(auth_insn, cold_steps) > worst_auth ? max_of(auth_insn, cold_steps) : worst_auth;
        kv("cold_pass_insn_per_step_with_auth_median", (unsigned long)median_of(with_auth, cold_steps));
        kv("cold_pass_insn_per_step_with_auth_max", (unsigned long)worst_cold_with_auth);
        if (at_cap == 0) {
            m7_puts("m7: FAIL: no cold start of pass 4 reached the interior point's cap\n");
            fail = 1;
        }
    }
#ifdef M7_PROFILE_COLD
    profile_dump();
    return 0;
#endif

    /* pass 6: pass 4's cold path with the actuation delays at the compiled maximum
     * (DDYN_CTRL_MAX_DELAY_STEPS periods, ddyn/controller.h), a steering lag (M7_LAG_S) and a bank profile,
     * in two variants, the worse one reported: (a) both delays at the maximum: the filter predicts with
     * the command sent that long ago through the lag and the MPC's start is the estimate stepped through
     * the whole pipe (the most model steps a step can take), over a horizon shortened by as many stages;
     * (b) the throttle delay alone: the full horizon with the most known throttle stages. The host's
     * commands fed back fill the delay lines. */
    {
        int variant;
        for (variant = 1; variant <= 2; ++variant) {
            int cold = 0;
            uint32_t worst_v = 0, worst_v_auth;
            if (!controller_init(1e-300, variant)) {
                m7_puts("m7: FAIL: controller refused the set-up of pass 6 (delays at the maximum)\n");
                return 1;
            }
            auth_reset();
            for (i = 0; i < delay_steps; ++i) {
                ddyn_ctrl_input in;
                ddyn_ctrl_output out;
                uint32_t t0;
                input_of(&m7_seg_periods[i], &in);
                ddyn_mpc_reset(&ctl.mpc);
                t0 = SYST_CVR;
                ddyn_ctrl_step(&ctl, &in, &out);
                insn[i] = ticks_since(t0) * INSN_PER_TICK;
                cold += out.mpc_info.qp_cold_start;
                worst_v = insn[i] > worst_v ? insn[i] : worst_v;
                auth_insn[i] = auth_period(i, 0, m7_seg_periods[i].u, &auth_bad);
                with_auth[i] = insn[i] + auth_insn[i];
                memcpy(ctl.u_prev, m7_seg_periods[i].u, sizeof ctl.u_prev);
            }
            worst_v_auth = max_of(with_auth, delay_steps);
            worst_auth = max_of(auth_insn, delay_steps) > worst_auth ? max_of(auth_insn, delay_steps) : worst_auth;
            m7_puts(variant == 1 ? "m7: pass 6a: both delays at the maximum\n"
                                 : "m7: pass 6b: the throttle delay alone at the maximum\n");
            kv("delay_pass_periods", (unsigned long)delay_steps);
            kv("delay_pass_delay_steps", (unsigned long)ctl.delay_steps[DDYN_CTRL_CH_STEERING]);
            kv("delay_pass_throttle_delay_steps", (unsigned long)ctl.delay_steps[DDYN_CTRL_CH_THROTTLE]);
            kv("delay_pass_horizon", (unsigned long)ctl.mpc.cfg.horizon);
            kv("delay_pass_steer_lag_ms", (unsigned long)(1000.0 * M7_LAG_S + 0.5));
            kv("delay_pass_bank_mrad", (unsigned long)(1000.0 * M7_BANK_RAD + 0.5));
            kv("delay_pass_grade_mrad", (unsigned long)(1000.0 * M7_GRADE_RAD + 0.5));
            kv("delay_pass_mass_offset_permille", (unsigned long)(1000.0 * M7_MASS_OFFSET + 0.5));
            kv("delay_pass_downforce_e4", (unsigned long)(1e4 * M7_DOWNFORCE + 0.5));
            kv("delay_pass_periods_cold_start", (unsigned long)cold);
            kv("delay_pass_insn_per_step_median", (unsigned long)median_of(insn, delay_steps));
            kv("delay_pass_variant_insn_per_step_max", (unsigned long)worst_v);
            kv("delay_pass_variant_insn_per_step_with_auth_max", (unsigned long)worst_v_auth);
            worst_delay = worst_v > worst_delay ? worst_v : worst_delay;
            worst_delay_with_auth = worst_v_auth > worst_delay_with_auth ? worst_v_auth : worst_delay_with_auth;
            if (ctl.delay_steps[DDYN_CTRL_CH_STEERING] != (variant == 1 ? DDYN_CTRL_MAX_DELAY_STEPS : 0) ||
                ctl.delay_steps[DDYN_CTRL_CH_THROTTLE] != DDYN_CTRL_MAX_DELAY_STEPS || cold == 0 ||
                !(ctl.lag_decay > 0.0) || !ctl.mpc.track.have_bank || !ctl.mpc.track.have_grade || !(ctl.mass_speed_scale < 1.0) ||
                !(ctl.mpc.downforce > 0.0)) {
                m7_puts("m7: FAIL: pass 6 did not run the cold path with the delays at the maximum, the lag, the bank, the grade, the mass offset and the downforce\n");
                fail = 1;
            }
        }
        /* the worse variant: the figure the bound is checked on */
        kv("delay_pass_insn_per_step_max", (unsigned long)worst_delay);
        kv("delay_pass_insn_per_step_with_auth_max", (unsigned long)worst_delay_with_auth);
    }

    /* pass 3: the real-time iteration split, feedback and preparation counted apart */
    if (!controller_init(0.0, 0)) {
        m7_puts("m7: FAIL: controller refused the set-up of pass 3\n");
        return 1;
    }
    {
        static uint32_t prep[5000];
        uint32_t worst_fb = 0, worst_prep = 0, worst_sum = 0;
        int n_fb = 0, n_prep = 0, prepared = 0;
        for (i = 0; i < steps; ++i) {
            ddyn_ctrl_input in;
            ddyn_ctrl_output out;
            uint32_t t0, fb, pr;
            input_of(&m7_seg_periods[i], &in);
            t0 = SYST_CVR;
            ddyn_ctrl_step(&ctl, &in, &out);
            fb = ticks_since(t0) * INSN_PER_TICK;
            t0 = SYST_CVR;
            /* refused in safe mode or with the PID throttle: the next step is then a whole iteration */
            pr = ddyn_ctrl_prepare(&ctl) == DDYN_OK;
            pr = pr ? ticks_since(t0) * INSN_PER_TICK : 0u;
            if (prepared) { /* this step followed a preparation: the feedback phase alone */
                insn[n_fb++] = fb;
                worst_fb = fb > worst_fb ? fb : worst_fb;
            }
            if (pr > 0u) {
                prep[n_prep++] = pr;
                worst_prep = pr > worst_prep ? pr : worst_prep;
                worst_sum = fb + pr > worst_sum ? fb + pr : worst_sum;
            }
            prepared = pr > 0u;
        }
        kv("split_pass_feedback_steps", (unsigned long)n_fb);
        kv("split_pass_feedback_insn_median", n_fb > 0 ? (unsigned long)median_of(insn, n_fb) : 0ul);
        kv("split_pass_feedback_insn_max", (unsigned long)worst_fb);
        kv("split_pass_prepare_insn_median", n_prep > 0 ? (unsigned long)median_of(prep, n_prep) : 0ul);
        kv("split_pass_prepare_insn_max", (unsigned long)worst_prep);
        kv("split_pass_step_plus_prepare_insn_max", (unsigned long)worst_sum);
        if (n_fb == 0) {
            m7_puts("m7: FAIL: no step of pass 3 followed a preparation\n");
            fail = 1;
        }
    }

    /* pass 5: the authentication work alone with an attacker's frame held beside every genuine one
     * (every verify computes two MACs), the segment's periods */
    {
        auth_reset();
        for (i = 0; i < steps; ++i) {
            auth_insn[i] = auth_period(i, 1, m7_seg_periods[i].u, &auth_bad);
        }
        worst_auth_injected = max_of(auth_insn, steps);
        kv("auth_injected_insn_per_period_median", (unsigned long)median_of(auth_insn, steps));
        kv("auth_injected_insn_per_period_max", (unsigned long)worst_auth_injected);
        kv("auth_failures", (unsigned long)auth_bad);
        if (auth_bad) {
            m7_puts("m7: FAIL: a genuine frame was not authenticated\n");
            fail = 1;
        }
    }

    /* stack high-water mark */
    for (p = &__stack_bottom; (uintptr_t)p < sp_main && *p == STACK_PAINT; ++p) {
    }
    kv("stack_high_water_bytes", (unsigned long)((uintptr_t)&__stack_top - (uintptr_t)p));
    kv("stack_below_main_bytes", (unsigned long)(sp_main - (uintptr_t)p));
    kv("stack_size_bytes", (unsigned long)((uintptr_t)&__stack_top - (uintptr_t)&__stack_bottom));
    if (p == &__stack_bottom) {
        m7_puts("m7: FAIL: the painted stack was used to its bottom (overflow)\n");
        fail = 1;
    }
    kv("target_max_insn", M7_MAX_INSN);
    {
        /* the worst step of any pass plus the worst period's authentication with an injected frame held
         * beside every genuine one (reported; the bound below is on the step plus each period's own work) */
        uint32_t w = worst > worst_cap ? worst : worst_cap;
        w = worst_cold > w ? worst_cold : w;
        w = worst_delay > w ? worst_delay : w;
        kv("worst_step_plus_auth_injected_max", (unsigned long)(w + worst_auth_injected));
    }
    kv("target_met", worst_with_auth <= M7_MAX_INSN && worst_cap_with_auth <= M7_MAX_INSN &&
                             worst_cold_with_auth <= M7_MAX_INSN && worst_delay_with_auth <= M7_MAX_INSN ? 1ul : 0ul);
    kv("enforced_bound_insn", M7_BOUND_INSN);
    if (mismatch || status_diff || (long)loose * 100 > (long)(100 - M7_TIGHT_PERCENT) * steps) {
        m7_puts("m7: FAIL: commands or status differ from the host build's beyond the tolerance\n");
        fail = 1;
    }
    /* the step with its period's frame authentication (>= the step alone) */
    if (worst_with_auth > M7_BOUND_INSN || worst_cap_with_auth > M7_BOUND_INSN || worst_cold_with_auth > M7_BOUND_INSN ||
        worst_delay_with_auth > M7_BOUND_INSN) {
        m7_puts("m7: FAIL: worst case (step + frame authentication) above the enforced bound (the 3M-instruction target)\n");
        fail = 1;
    }
    m7_puts(fail ? "m7: FAIL\n" : "m7: PASS\n");
    return fail;
}
