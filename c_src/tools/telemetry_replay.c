/*
 * ddyn_telemetry_replay: publish a stream of controller telemetry read from stdin through
 * the telemetry module (ddyn/telemetry.h), so the whole path C -> LCM -> log -> `ddyn import`
 * runs without the controller. `ddyn lcm replay` feeds it a dataset.
 *
 * usage: ddyn_telemetry_replay [-u URL] [-p PREFIX] [-c CONTROL_HZ] [-r KIND=HZ]... [-s SPEED] [-m] < stream
 *   URL: LCM provider (default: LCM's default), e.g. "file:///tmp/run.lcm?mode=w"
 *   KIND: state, coeffs, plan, timing, faults (default rates: ddyn_telemetry_default_config)
 *   SPEED: pace the messages by their utime at SPEED times real time (default 0: as fast as
 *          possible, which can overrun a UDP receiver's buffer)
 *   -m: publish this loop's own timing (no T lines then): per step, the wall time each
 *       message kind took to parse from its line and publish (stages state, coeffs, plan,
 *       faults), their total, the
 *       period of the utime clock and a deadline of one control period
 * Input lines (numbers separated by spaces; utime in microseconds, step an integer):
 *   B lo[17] hi[17] margin                        guard bounds (only as the first line)
 *   S utime step x[8] cov_diag[8]                 state estimate
 *   C utime step c[17]                            guard coefficients
 *   P utime step status NAME qp_iter cost N states[(N+1)*8] inputs[N*2]
 *   T utime step period total deadline n NAME_1 s_1 ... NAME_n s_n
 *   F utime step active                           fault bit flags
 * At the end it prints one line per kind: "KIND published P skipped S errors E". A
 * malformed line or a publish error stops with a message and status 1.
 */
#define _POSIX_C_SOURCE 199309L /* clock_gettime, nanosleep */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "ddyn/telemetry.h"

#define LINE_MAX_CHARS (1 << 16)
#define NAME_MAX_CHARS 64

static int read_numbers(char **p, double *v, int n)
{
    int i;
    for (i = 0; i < n; ++i) {
        char *end = NULL;
        v[i] = strtod(*p, &end);
        if (end == *p) {
            return 0;
        }
        *p = end;
    }
    return 1;
}

static int read_int64(char **p, int64_t *v)
{
    char *end = NULL;
    long long x = strtoll(*p, &end, 10);
    if (end == *p) {
        return 0;
    }
    *v = (int64_t)x;
    *p = end;
    return 1;
}

/* one whitespace-delimited word into out (at most NAME_MAX_CHARS - 1 characters) */
static int read_word(char **p, char *out)
{
    int n = 0;
    char *s = *p;
    while (*s == ' ' || *s == '\t') {
        ++s;
    }
    while (*s != '\0' && *s != ' ' && *s != '\t' && *s != '\n' && *s != '\r') {
        if (n + 1 >= NAME_MAX_CHARS) {
            return 0;
        }
        out[n++] = *s++;
    }
    out[n] = '\0';
    *p = s;
    return n > 0;
}

static double now_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* sleep until the wall clock is (utime - first utime) / speed past the start */
static void pace(int64_t utime, double speed)
{
    static int started = 0;
    static int64_t utime0;
    static double wall0;
    double wait;
    if (!started) {
        started = 1;
        utime0 = utime;
        wall0 = now_s();
        return;
    }
    wait = wall0 + 1e-6 * (double)(utime - utime0) / speed - now_s();
    if (wait > 0.0 && wait < 3600.0) {
        struct timespec ts;
        ts.tv_sec = (time_t)wait;
        ts.tv_nsec = (long)((wait - (double)ts.tv_sec) * 1e9);
        nanosleep(&ts, NULL);
    }
}

/* -m: the replay loop's own timing, one step (the lines sharing a step number) at a time */
typedef struct {
    int open;               /* a step is being timed */
    int64_t utime, step, prev_utime;
    int have_prev;
    double stage_s[4];      /* state, coeffs, plan, faults */
} self_timing;

static const char *const self_stage_names[4] = {"state", "coeffs", "plan", "faults"};

static ddyn_tm_status finish_step(ddyn_telemetry *tm, self_timing *st, double control_hz)
{
    ddyn_tm_timing t;
    int k;
    if (!st->open) {
        return DDYN_TM_SKIPPED;
    }
    memset(&t, 0, sizeof t);
    t.utime = st->utime;
    t.step = st->step;
    t.period_s = st->have_prev ? 1e-6 * (double)(st->utime - st->prev_utime) : 0.0;
    t.deadline_s = 1.0 / control_hz;
    t.n_stages = 4;
    for (k = 0; k < 4; ++k) {
        t.stage_names[k] = self_stage_names[k];
        t.stage_s[k] = st->stage_s[k];
        t.total_s += st->stage_s[k];
    }
    st->prev_utime = st->utime;
    st->have_prev = 1;
    st->open = 0;
    return ddyn_telemetry_publish_timing(tm, &t);
}

static int stage_of(char kind)
{
    return kind == 'S' ? 0 : kind == 'C' ? 1 : kind == 'P' ? 2 : kind == 'F' ? 3 : -1;
}

static int parse_rate(const char *arg, ddyn_telemetry_config *cfg)
{
    int k;
    const char *eq = strchr(arg, '=');
    if (eq == NULL) {
        return 0;
    }
    for (k = 0; k < DDYN_TM_KIND_COUNT; ++k) {
        const char *name = ddyn_tm_kind_name((ddyn_tm_kind)k);
        size_t n = strlen(name), i;
        int same = (size_t)(eq - arg) == n;
        for (i = 0; same && i < n; ++i) {
            same = (arg[i] == name[i] || arg[i] == name[i] - 'A' + 'a');
        }
        if (same) {
            cfg->rate_hz[k] = strtod(eq + 1, NULL);
            return 1;
        }
    }
    return 0;
}

/* publish the line's record; *ok = 0 when the line is malformed */
static ddyn_tm_status publish_line(ddyn_telemetry *tm, char *line, int *ok)
{
    static double v[(DDYN_TM_PLAN_MAX_HORIZON + 1) * DDYN_NX + DDYN_TM_PLAN_MAX_HORIZON * DDYN_NU];
    static char names[DDYN_TM_MAX_STAGES][NAME_MAX_CHARS];
    char status_name[NAME_MAX_CHARS];
    char kind = line[0];
    char *p = line + 1;
    int64_t utime, step;
    *ok = 0;
    if (!read_int64(&p, &utime) || !read_int64(&p, &step)) {
        return DDYN_TM_ERR_ARGUMENT;
    }
    if (kind == 'S' && read_numbers(&p, v, 2 * DDYN_NX)) {
        ddyn_tm_state m;
        m.utime = utime;
        m.step = step;
        memcpy(m.x, v, sizeof m.x);
        memcpy(m.cov_diag, v + DDYN_NX, sizeof m.cov_diag);
        *ok = 1;
        return ddyn_telemetry_publish_state(tm, &m);
    }
    if (kind == 'C' && read_numbers(&p, v, DDYN_NC)) {
        ddyn_tm_coeffs m;
        m.utime = utime;
        m.step = step;
        memcpy(m.coeffs, v, sizeof m.coeffs);
        *ok = 1;
        return ddyn_telemetry_publish_coeffs(tm, &m);
    }
    if (kind == 'P') {
        ddyn_tm_plan m;
        double head[4];
        int n;
        if (!read_numbers(&p, head, 1) || !read_word(&p, status_name) || !read_numbers(&p, head + 1, 3)) {
            return DDYN_TM_ERR_ARGUMENT;
        }
        n = (int)head[3];
        if (n < 0 || n > DDYN_TM_PLAN_MAX_HORIZON || !read_numbers(&p, v, (n + 1) * DDYN_NX + n * DDYN_NU)) {
            return DDYN_TM_ERR_ARGUMENT;
        }
        m.utime = utime;
        m.step = step;
        m.status = (int)head[0];
        m.status_name = status_name;
        m.qp_iterations = (int)head[1];
        m.cost = head[2];
        m.horizon = n;
        m.states = v;
        m.inputs = v + (n + 1) * DDYN_NX;
        *ok = 1;
        return ddyn_telemetry_publish_plan(tm, &m);
    }
    if (kind == 'T') {
        ddyn_tm_timing m;
        double head[4];
        int k;
        if (!read_numbers(&p, head, 4) || head[3] < 0 || head[3] > DDYN_TM_MAX_STAGES) {
            return DDYN_TM_ERR_ARGUMENT;
        }
        m.utime = utime;
        m.step = step;
        m.period_s = head[0];
        m.total_s = head[1];
        m.deadline_s = head[2];
        m.n_stages = (int)head[3];
        for (k = 0; k < m.n_stages; ++k) {
            if (!read_word(&p, names[k]) || !read_numbers(&p, &m.stage_s[k], 1)) {
                return DDYN_TM_ERR_ARGUMENT;
            }
            m.stage_names[k] = names[k];
        }
        *ok = 1;
        return ddyn_telemetry_publish_timing(tm, &m);
    }
    if (kind == 'F') {
        ddyn_tm_faults m;
        int64_t active;
        if (!read_int64(&p, &active) || active < 0 || active > (int64_t)0xffffffffu) {
            return DDYN_TM_ERR_ARGUMENT;
        }
        m.utime = utime;
        m.step = step;
        m.active = (uint32_t)active;
        *ok = 1;
        return ddyn_telemetry_publish_faults(tm, &m);
    }
    return DDYN_TM_ERR_ARGUMENT;
}

int main(int argc, char **argv)
{
    static ddyn_telemetry tm;
    static char line[LINE_MAX_CHARS];
    static double bounds[2 * DDYN_NC + 1];
    ddyn_telemetry_config cfg;
    double control_hz = 50.0, speed = 0.0;
    self_timing st;
    int i, k, opened = 0, status = 0, measure_self = 0;
    long line_no = 0;
    ddyn_telemetry_default_config(&cfg, control_hz);
    for (i = 1; i < argc; ++i) { /* -c first fixes the defaults the -r options then change */
        if (strcmp(argv[i], "-c") == 0 && i + 1 < argc) {
            control_hz = strtod(argv[i + 1], NULL);
            ddyn_telemetry_default_config(&cfg, control_hz);
        }
    }
    for (i = 1; i < argc; ++i) {
        if (strcmp(argv[i], "-u") == 0 && i + 1 < argc) {
            cfg.url = argv[++i];
        } else if (strcmp(argv[i], "-p") == 0 && i + 1 < argc) {
            cfg.channel_prefix = argv[++i];
        } else if (strcmp(argv[i], "-c") == 0 && i + 1 < argc) {
            ++i;
        } else if (strcmp(argv[i], "-s") == 0 && i + 1 < argc) {
            speed = strtod(argv[++i], NULL);
        } else if (strcmp(argv[i], "-m") == 0) {
            measure_self = 1;
        } else if (strcmp(argv[i], "-r") == 0 && i + 1 < argc && parse_rate(argv[i + 1], &cfg)) {
            ++i;
        } else {
            fprintf(stderr, "usage: %s [-u URL] [-p PREFIX] [-c CONTROL_HZ] [-r KIND=HZ]... [-s SPEED] [-m] < stream\n",
                    argv[0]);
            return 2;
        }
    }
    memset(&st, 0, sizeof st);
    while (fgets(line, sizeof line, stdin) != NULL) {
        ddyn_tm_status s;
        int64_t utime = 0, step = 0;
        char *head = line + 1;
        double t0;
        int ok, stage = stage_of(line[0]);
        ++line_no;
        if (line[0] == 'B' && line_no == 1) {
            char *p = line + 1;
            if (!read_numbers(&p, bounds, 2 * DDYN_NC + 1)) {
                fprintf(stderr, "ddyn_telemetry_replay: line 1: expected B lo[17] hi[17] margin\n");
                return 1;
            }
            cfg.coeff_lo = bounds;
            cfg.coeff_hi = bounds + DDYN_NC;
            cfg.sat_margin = bounds[2 * DDYN_NC];
            continue;
        }
        if (!opened) {
            s = ddyn_telemetry_open(&tm, &cfg);
            if (s != DDYN_TM_PUBLISHED) {
                fprintf(stderr, "ddyn_telemetry_replay: cannot open telemetry (url %s): %s\n",
                        cfg.url != NULL ? cfg.url : "LCM default", ddyn_tm_status_name(s));
                return 1;
            }
            opened = 1;
        }
        if (!read_int64(&head, &utime) || !read_int64(&head, &step) || (measure_self && line[0] == 'T')) {
            fprintf(stderr, "ddyn_telemetry_replay: line %ld: expected S, C, P, T or F with utime and step%s\n",
                    line_no, measure_self ? " (no T lines with -m)" : "");
            status = 1;
            break;
        }
        if (!st.open || step != st.step) { /* a new step: the previous one is complete */
            s = finish_step(&tm, &st, control_hz);
            if (measure_self && s != DDYN_TM_PUBLISHED && s != DDYN_TM_SKIPPED) {
                fprintf(stderr, "ddyn_telemetry_replay: line %ld: timing: %s\n", line_no, ddyn_tm_status_name(s));
                status = 1;
                break;
            }
            if (speed > 0.0) {
                pace(utime, speed);
            }
            memset(st.stage_s, 0, sizeof st.stage_s);
            st.open = measure_self;
            st.utime = utime;
            st.step = step;
        }
        t0 = now_s();
        s = publish_line(&tm, line, &ok);
        if (st.open && stage >= 0) {
            st.stage_s[stage] += now_s() - t0;
        }
        if (!ok) {
            fprintf(stderr, "ddyn_telemetry_replay: line %ld: expected S, C, P, T or F with its fields\n", line_no);
            status = 1;
            break;
        }
        if (s != DDYN_TM_PUBLISHED && s != DDYN_TM_SKIPPED) {
            fprintf(stderr, "ddyn_telemetry_replay: line %ld: %s\n", line_no, ddyn_tm_status_name(s));
            status = 1;
            break;
        }
    }
    if (status == 0 && finish_step(&tm, &st, control_hz) > DDYN_TM_SKIPPED) {
        fprintf(stderr, "ddyn_telemetry_replay: timing of the last step could not be published\n");
        status = 1;
    }
    for (k = 0; k < DDYN_TM_KIND_COUNT; ++k) {
        printf("%s published %llu skipped %llu errors %llu\n", ddyn_tm_kind_name((ddyn_tm_kind)k),
               (unsigned long long)tm.limiter[k].published, (unsigned long long)tm.limiter[k].skipped,
               (unsigned long long)tm.limiter[k].errors);
    }
    ddyn_telemetry_close(&tm);
    return status;
}
