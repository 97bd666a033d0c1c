/*
 * controller_config.c - ddyn_controller's configuration file: one table of keys (KEYS), a walk of
 * the JSON document against it, and the node built from the result. Format and every key:
 * docs/deploy.md "Configuration reference" (`ddyn_controller --keys` prints this table).
 */
#define _POSIX_C_SOURCE 200809L
#include "controller_config.h"

#include <cjson/cJSON.h>
#include "dbw_auth_key.h"
#include <errno.h>
#include <math.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

/* ---------------------------------------------------------------------------------------- names */

/* the model's coefficient order (ddyn/model.h; train/model/single_track.py COEFF_NAMES) */
static const char *const COEFF_NAMES[DDYN_NC] = {"Bf", "Cf", "Df", "Ef", "Gf", "Kf", "Br", "Cr", "Dr",
                                                 "Er", "Gr", "Kr", "Cm1", "Cm2", "Cr0", "Cd", "Iz"};
/* ddyn_dbw_frame order */
static const char *const FRAME_NAMES[DDYN_DBW_FRAME_COUNT] = {"command", "steering",      "status",      "wheel_speeds",
                                                              "imu",     "gnss_position", "gnss_heading"};
static const char *const SOURCE_NAMES[] = {"network", "fixed", NULL};
static const char *const THROTTLE_NAMES[] = {"mpc", "pid", NULL};
static const char *const PACING_NAMES[] = {"frame", "timer", NULL};
static const char *const PID_NAMES[4] = {"kp", "ki", "kd", "preview"};
static const char *const DELAY_NAMES[2] = {"steering", "throttle"};
static const char *const LAG_NAMES[1] = {"steering"};

/* ---------------------------------------------------------------------------------------- the table */

typedef enum {
    K_SECTION,   /* an object whose members are rows of their own */
    K_STRING,    /* char[size] */
    K_ENUM,      /* one of names[]: its index as int */
    K_FILE,      /* an existing readable file, resolved against the config's directory: char[size] */
    K_OUTPUT,    /* a file to write, in an existing directory: char[size] */
    K_HASH,      /* 64 hex digits: char[65] */
    K_NUMBER,    /* double in [lo, hi] */
    K_INT,       /* int in [lo, hi] */
    K_LONG,      /* long in [lo, hi] */
    K_BOOL,      /* int 0/1 */
    K_NUMBERS,   /* n doubles in [lo, hi] */
    K_NAMED,     /* an object {names[i]: number in [lo, hi]}: double[n], have flags at aux */
    K_NAMED_INT  /* the same with integers: int[n] */
} key_type;

typedef struct {
    const char *key;            /* dotted path */
    key_type type;
    size_t offset;              /* of the field in ddyn_app_config */
    size_t size;                /* string buffer size */
    int n;                      /* array length / names */
    double lo, hi;              /* range of numbers (each element) */
    int required;
    const char *const *names;   /* K_ENUM / K_NAMED* names */
    size_t aux;                 /* K_NAMED: offset of the int have-flags (SIZE_MAX: none) */
    const char *help;           /* default and meaning, one line (--keys, docs/deploy.md) */
} key_spec;

#define OFF(f) offsetof(ddyn_app_config, f)
#define FSZ(f) sizeof(((ddyn_app_config *)0)->f)
#define R_STD(k) (OFF(r_std) + (size_t)(k) * sizeof(((ddyn_app_config *)0)->r_std[0]))
#define MPC(f) (OFF(mpc) + offsetof(ddyn_mpc_config, f))
#define NONE ((size_t)-1)
#define BIG 1e300

/* ONE table: every key the file may hold. Another module's setting is one more row (and a field). */
static const key_spec KEYS[] = {
    {"vehicle", K_STRING, OFF(vehicle), FSZ(vehicle), 0, 0, 0, 1, NULL, NONE,
     "the generated vehicle model (orca_1_43, av21)"},
    {"nominal_coefficients", K_NAMED, OFF(nominal), 0, DDYN_NC, -BIG, BIG, 1, COEFF_NAMES, NONE,
     "all 17 (Bf .. Iz): the vehicle file's coefficients, the fallback of last resort"},
    {"coefficients", K_SECTION, 0, 0, 0, 0, 0, 0, NULL, NONE, "where each period's coefficients come from"},
    {"coefficients.source", K_ENUM, OFF(fixed), 0, 0, 0, 0, 0, SOURCE_NAMES, NONE,
     "network (default: the guard network built in) or fixed (coefficients.fixed, the network never run)"},
    {"coefficients.fixed", K_NAMED, OFF(coeffs), 0, DDYN_NC, -BIG, BIG, 0, COEFF_NAMES, OFF(have_coeffs),
     "with source fixed, all 17: the coefficients used every period"},
    {"coefficients.checkpoint_hash", K_HASH, OFF(checkpoint_hash), FSZ(checkpoint_hash), 0, 0, 0, 0, NULL, NONE,
     "sha256 of the checkpoint the network must come from; a build for another is refused (default: not checked)"},
    {"can", K_SECTION, 0, 0, 0, 0, 0, 1, NULL, NONE, "the drive-by-wire bus"},
    {"can.interface", K_STRING, OFF(can_interface), FSZ(can_interface), 0, 0, 0, 1, NULL, NONE,
     "the SocketCAN interface (can0, vcan0)"},
    {"can.stale_periods", K_NAMED_INT, OFF(stale), 0, DDYN_DBW_FRAME_COUNT, 0, 1000, 0, FRAME_NAMES, NONE,
     "per frame, periods it may be missing before the safe command; 0 = not monitored (default 0 1 1 1 1 2 2)"},
    {"can.key_file", K_FILE, OFF(key_file), FSZ(key_file), 0, 0, 0, 0, NULL, NONE,
     "frame authentication key (docs/can.md): 64 hex digits, mode 0600/0400; every frame read must verify, every "
     "command is signed (default: $DDYN_DBW_KEY_FILE, else off)"},
    {"can.cycle_ms", K_NAMED_INT, OFF(cycle_ms), 0, DDYN_DBW_FRAME_COUNT, 0, 10000, 0, FRAME_NAMES, NONE,
     "per frame, the cycle (ms) this car sends it at, which dates its frames (degraded-bus mode); 0 (default) = "
     "the DBC's (gnss_position 20, gnss_heading 20, the others 10); gnss_position's must be control.period"},
    {"control", K_SECTION, 0, 0, 0, 0, 0, 1, NULL, NONE, "the control loop"},
    {"control.period", K_NUMBER, OFF(period), 0, 0, 1e-4, 10.0, 1, NULL, NONE,
     "the control period, s (the vehicle's sample time: 0.02 for orca_1_43)"},
    {"control.throttle", K_ENUM, OFF(throttle_pid), 0, 0, 0, 0, 0, THROTTLE_NAMES, NONE,
     "mpc (default: the MPC plans throttle and steering) or pid (a PID on the speed error sets the throttle)"},
    {"control.pid", K_NAMED, OFF(pid), 0, 4, 0.0, 1e6, 0, PID_NAMES,
     OFF(have_pid), "throttle PID gains and preview time (s), each >= 0 (default: the controller's)"},
    {"control.delay", K_NAMED, OFF(delay), 0, 2, 0.0, 1.0, 0, DELAY_NAMES, NONE,
     "known actuation delays, s: a set-point acts this long after it is sent; the filter predicts with the "
     "command acting, the MPC plans from the state its command acts in (default 0 0; at most the build's "
     "DDYN_CTRL_MAX_DELAY_STEPS periods)"},
    {"control.lag", K_NAMED, OFF(lag), 0, 1, 0.0, 1.0, 0, LAG_NAMES, NONE,
     "known steering lag, s: the time constant tau of the acting steering's first-order lag behind its set-point; "
     "the filter predicts with the acting steering, the MPC plans from it and its first command inverts the "
     "lag (default 0: none; ddyn/controller.h)"},
    {"control.mass_offset", K_NUMBER, OFF(mass_offset), 0, 0, DDYN_CTRL_MASS_OFFSET_MIN, DDYN_CTRL_MASS_OFFSET_MAX,
     0, NULL, NONE,
     "known mass offset: the car's mass is (1 + it) times the model's; the filter, the pipe and the MPC use the "
     "coefficients scaled for it (default 0: none; ddyn/controller.h)"},
    {"control.downforce", K_NUMBER, OFF(downforce), 0, 0, 0.0, DDYN_MODEL_DOWNFORCE_MAX, 0, NULL, NONE,
     "known downforce k, s^2/m^2: the tyres' peak forces are 1 + k vx^2 times the model's; the filter, the pipe "
     "and each MPC stage use the coefficients of their own speed, the line's speeds are not raised (default 0: "
     "none; ddyn/controller.h)"},
    {"control.bank", K_BOOL, OFF(bank), 0, 0, 0, 0, 0, NULL, NONE,
     "false (default): a flat road; true: the raceline's 6th column is the road's bank (rad, + tilting the road "
     "so that gravity pulls to the left; |bank| < 45 deg) at each point, and the filter and the MPC predict with "
     "its lateral gravity g sin(bank) at their track positions (issue 34; ddyn/controller.h ddyn_ctrl_set_bank)"},
    {"control.grade", K_BOOL, OFF(grade), 0, 0, 0, 0, 0, NULL, NONE,
     "false (default): a level road; true: the raceline's next column (the 6th, the 7th after a bank) is the road's "
     "grade (rad, + uphill in the direction of travel; |grade| < 20 deg) at each point, and the filter and the MPC "
     "predict with its longitudinal gravity -g sin(grade) at their track positions (issue 34; ddyn/controller.h "
     "ddyn_ctrl_set_grade)"},
    {"effects", K_SECTION, 0, 0, 0, 0, 0, 0, NULL, NONE,
     "the diagnosis the actuation delays, the steering lag, the mass offset, the downforce and the road's bank and "
     "grade come from (`ddyn sil run --effects-from D`, docs/sil.md); a file whose control.delay differs from "
     "effects.delay, control.lag from effects.lag, control.mass_offset from effects.mass_offset, control.downforce "
     "from effects.downforce, control.bank from effects.bank, control.grade from effects.grade (or the raceline's "
     "bank or grade column from effects.bank_peak, effects.grade_peak) is refused"},
    {"effects.diagnosis", K_STRING, OFF(effects_diagnosis), FSZ(effects_diagnosis), 0, 0, 0, 0, NULL, NONE,
     "the diagnosis.json the effects were taken from (recorded, not read; default none)"},
    {"effects.diagnosis_sha256", K_HASH, OFF(effects_sha256), FSZ(effects_sha256), 0, 0, 0, 0, NULL, NONE,
     "sha256 of that diagnosis.json; when given, control.delay must equal effects.delay (default: not checked)"},
    {"effects.delay", K_NAMED, OFF(effects_delay), 0, 2, 0.0, 1.0, 0, DELAY_NAMES, NONE,
     "the delays (s) the diagnosis gave the controller: steering, throttle (default 0 0)"},
    {"effects.lag", K_NAMED, OFF(effects_lag), 0, 1, 0.0, 1.0, 0, LAG_NAMES, NONE,
     "the steering lag (s) the diagnosis gave the controller (default 0)"},
    {"effects.mass_offset", K_NUMBER, OFF(effects_mass_offset), 0, 0, DDYN_CTRL_MASS_OFFSET_MIN,
     DDYN_CTRL_MASS_OFFSET_MAX, 0, NULL, NONE, "the mass offset the diagnosis gave the controller (default 0)"},
    {"effects.downforce", K_NUMBER, OFF(effects_downforce), 0, 0, 0.0, DDYN_MODEL_DOWNFORCE_MAX, 0, NULL, NONE,
     "the downforce k (s^2/m^2) the diagnosis gave the controller (default 0)"},
    {"effects.bank", K_BOOL, OFF(effects_bank), 0, 0, 0, 0, 0, NULL, NONE,
     "whether the diagnosis gave the controller the road's bank (raceline.csv's 6th column; default false); with "
     "a sha256 given, control.bank must equal it"},
    {"effects.bank_peak", K_NUMBER, OFF(effects_bank_peak), 0, 0, 0.0, 1.0, 0, NULL, NONE,
     "the largest |bank| (rad) of the bank column the diagnosis gave; with effects.bank, the raceline's column "
     "must have it (default 0)"},
    {"effects.grade", K_BOOL, OFF(effects_grade), 0, 0, 0, 0, 0, NULL, NONE,
     "whether the diagnosis gave the controller the road's grade (the raceline's grade column; default false); "
     "with a sha256 given, control.grade must equal it"},
    {"effects.grade_peak", K_NUMBER, OFF(effects_grade_peak), 0, 0, 0.0, 1.0, 0, NULL, NONE,
     "the largest |grade| (rad) of the grade column the diagnosis gave; with effects.grade, the raceline's column "
     "must have it (default 0)"},
    {"effects.bank_from", K_STRING, OFF(effects_bank_from), FSZ(effects_bank_from), 0, 0, 0, 0, NULL, NONE,
     "which bank the diagnosis gave: its effect and the column it made (recorded, not read; default none)"},
    {"control.prepare", K_BOOL, OFF(prepare), 0, 0, 0, 0, 0, NULL, NONE,
     "true (default): the MPC's preparation runs after each command (RTI split, docs/controller.md)"},
    {"control.max_steps", K_LONG, OFF(max_steps), 0, 0, 0, 1e12, 0, NULL, NONE,
     "stop after this many periods; 0 (default) = never"},
    {"filter", K_SECTION, 0, 0, 0, 0, 0, 0, NULL, NONE, "the state estimator (EKF)"},
    {"filter.x0", K_NUMBERS, OFF(x0), 0, DDYN_NX, -1e6, 1e6, 0, NULL, NONE,
     "initial state x, y, yaw, vx, vy, omega, throttle, steering (default all 0)"},
    {"filter.process_noise", K_NUMBERS, OFF(q), 0, DDYN_NX, 0.0, 1e6, 0, NULL, NONE,
     "process noise variance per period and state; 0 = the controller's default"},
    {"filter.sensor_std", K_SECTION, 0, 0, 0, 0, 0, 0, NULL, NONE,
     "the noise std the filter assumes per sensor component; 0 = a floor of 1e-4"},
    {"filter.sensor_std.gnss_position", K_NUMBERS, R_STD(DDYN_MEAS_GNSS_POSITION), 0, 2, 0.0, 1e6, 0, NULL, NONE,
     "x, y (m)"},
    {"filter.sensor_std.heading", K_NUMBERS, R_STD(DDYN_MEAS_HEADING), 0, 1, 0.0, 1e6, 0, NULL, NONE, "yaw (rad)"},
    {"filter.sensor_std.yaw_rate", K_NUMBERS, R_STD(DDYN_MEAS_YAW_RATE), 0, 1, 0.0, 1e6, 0, NULL, NONE,
     "omega (rad/s)"},
    {"filter.sensor_std.acceleration", K_NUMBERS, R_STD(DDYN_MEAS_ACCELERATION), 0, 2, 0.0, 1e6, 0, NULL, NONE,
     "ax, ay (m/s^2)"},
    {"filter.sensor_std.wheel_speed", K_NUMBERS, R_STD(DDYN_MEAS_WHEEL_SPEED), 0, 2, 0.0, 1e6, 0, NULL, NONE,
     "front, rear (m/s)"},
    {"filter.sensor_std.steering", K_NUMBERS, R_STD(DDYN_MEAS_STEERING), 0, 1, 0.0, 1e6, 0, NULL, NONE,
     "steering angle (rad)"},
    {"raceline", K_FILE, OFF(raceline), FSZ(raceline), 0, 0, 0, 1, NULL, NONE,
     "CSV x,y,speed,width_left,width_right[,bank][,grade] (header line optional), 4 .. 1024 rows, closed loop; "
     "the bank column (rad) with control.bank true only, the grade column (rad) with control.grade true only"},
    {"mpc", K_SECTION, 0, 0, 0, 0, 0, 0, NULL, NONE, "overrides of the MPC's defaults (docs/mpc.md)"},
    {"mpc.horizon", K_INT, MPC(horizon), 0, 0, 1, DDYN_MPC_MAX_HORIZON, 0, NULL, NONE,
     "stages (with a steering delay of n periods the MPC plans n fewer: ddyn/controller.h)"},
    {"mpc.q_pos", K_NUMBERS, MPC(q_pos), 0, 2, 0.0, 1e12, 0, NULL, NONE, "weights of the x and y error"},
    {"mpc.q_terminal_scale", K_NUMBER, MPC(q_terminal_scale), 0, 0, 0.0, 1e12, 0, NULL, NONE,
     "last stage's position weight factor"},
    {"mpc.r_rate", K_NUMBERS, MPC(r_rate), 0, 2, 0.0, 1e12, 0, NULL, NONE, "weights of dthrottle, dsteering"},
    {"mpc.slack_l1", K_NUMBER, MPC(slack_l1), 0, 0, 0.0, 1e12, 0, NULL, NONE, "track-bound penalty per metre"},
    {"mpc.slack_l2", K_NUMBER, MPC(slack_l2), 0, 0, 1e-12, 1e12, 0, NULL, NONE,
     "track-bound penalty per square metre (> 0)"},
    {"telemetry", K_SECTION, 0, 0, 0, 0, 0, 0, NULL, NONE, "what the controller reports"},
    {"telemetry.lcm_url", K_STRING, OFF(lcm_url), FSZ(lcm_url), 0, 0, 0, 0, NULL, NONE,
     "publish live LCM telemetry there, e.g. udpm://239.255.76.67:7667?ttl=0 (default \"\": none)"},
    {"telemetry.metrics", K_OUTPUT, OFF(metrics), FSZ(metrics), 0, 0, 0, 0, NULL, NONE,
     "JSON metrics written at exit: loop times, overruns, frame counts (default controller_metrics.json)"},
    {"telemetry.log", K_OUTPUT, OFF(log), FSZ(log), 0, 0, 0, 0, NULL, NONE,
     "per-period CSV log (default \"\": none)"},
    {"realtime", K_SECTION, 0, 0, 0, 0, 0, 0, NULL, NONE, "scheduling (docs/deploy.md real-time set-up)"},
    {"realtime.pacing", K_ENUM, OFF(pacing), 0, 0, 0, 0, 0, PACING_NAMES, NONE,
     "frame (default: a period per GNSS position frame, the own timer when frames stop) or timer (absolute "
     "deadlines, clock_nanosleep)"},
    {"realtime.priority", K_INT, OFF(priority), 0, 0, 0, 99, 0, NULL, NONE,
     "SCHED_FIFO priority 1..99; 0 (default) = normal scheduling; not permitted = a warning"},
    {"realtime.cpu", K_INT, OFF(cpu), 0, 0, -1, 1023, 0, NULL, NONE, "pin to this CPU; -1 (default) = none"},
    {"realtime.lock_memory", K_BOOL, OFF(lock_memory), 0, 0, 0, 0, 0, NULL, NONE,
     "mlockall(MCL_CURRENT | MCL_FUTURE) (default true; not permitted = a warning)"},
    {"realtime.lockstep_silence", K_NUMBER, OFF(lockstep_silence), 0, 0, 0.0, 60.0, 0, NULL, NONE,
     "SIL lock-step: the own timer runs only after this much wall time without any frame; 0 (default) = real time"},
    {"realtime.idle_exit", K_NUMBER, OFF(idle_exit), 0, 0, 0.0, 1e6, 0, NULL, NONE,
     "exit after this many seconds without frames; 0 (default) = never"},
    {"sil", K_SECTION, 0, 0, 0, 0, 0, 0, NULL, NONE, "SIL fault injection (never in a car's file)"},
    {"sil.die_at_step", K_LONG, OFF(die_at_step), 0, 0, -1, 1e12, 0, NULL, NONE,
     "SIGKILL itself at this period (the killed-controller scenario); -1 (default) = never"},
};
#define N_KEYS ((int)(sizeof KEYS / sizeof KEYS[0]))

/* ---------------------------------------------------------------------------------------- helpers */

typedef struct {
    ddyn_app_config *c;
    const char *base_dir;
    const char *name;
    char *err;
    int seen[N_KEYS];
} parse_ctx;

static int fail(parse_ctx *p, const char *key, const char *fmt, ...)
{
    va_list ap;
    int n = snprintf(p->err, DDYN_APP_ERROR_LEN, "%s: %s: ", p->name, key);
    va_start(ap, fmt);
    if (n >= 0 && n < DDYN_APP_ERROR_LEN) {
        vsnprintf(p->err + n, (size_t)(DDYN_APP_ERROR_LEN - n), fmt, ap);
    }
    va_end(ap);
    return 0;
}

static int find_key(const char *key)
{
    int i;
    for (i = 0; i < N_KEYS; ++i) {
        if (strcmp(KEYS[i].key, key) == 0) {
            return i;
        }
    }
    return -1;
}

static const char *type_name(const cJSON *v)
{
    if (cJSON_IsNumber(v)) return "a number";
    if (cJSON_IsString(v)) return "a string";
    if (cJSON_IsBool(v)) return "a boolean";
    if (cJSON_IsArray(v)) return "an array";
    if (cJSON_IsObject(v)) return "an object";
    return "null";
}

static void *field(parse_ctx *p, const key_spec *k)
{
    return (char *)p->c + k->offset;
}

/* a number of a row (integer rows: integral) in its range */
static int number_in(parse_ctx *p, const char *key, const key_spec *k, const cJSON *v, int integral, double *out)
{
    double x;
    if (!cJSON_IsNumber(v)) {
        return fail(p, key, "expected %s, got %s", integral ? "an integer" : "a number", type_name(v));
    }
    x = v->valuedouble;
    if (!isfinite(x) || (integral && x != floor(x))) {
        return fail(p, key, "%.10g is not %s", x, integral ? "an integer" : "finite");
    }
    if (x < k->lo || x > k->hi) {
        return fail(p, key, "%.10g is out of range (%.6g .. %.6g)", x, k->lo, k->hi);
    }
    *out = x;
    return 1;
}

static int resolve(parse_ctx *p, const char *key, const char *name, char *out, size_t size)
{
    int n;
    if (name[0] == '\0') {
        out[0] = '\0';
        return 1;
    }
    n = name[0] == '/' ? snprintf(out, size, "%s", name) : snprintf(out, size, "%s/%s", p->base_dir, name);
    if (n < 0 || (size_t)n >= size) {
        return fail(p, key, "path longer than %zu characters", size - 1);
    }
    return 1;
}

static int dir_exists_for(const char *path)
{
    char dir[DDYN_APP_PATH_LEN];
    const char *slash = strrchr(path, '/');
    struct stat st;
    size_t n;
    if (slash == NULL) {
        return 1;
    }
    n = (size_t)(slash - path);
    if (n == 0) {
        return 1;
    }
    if (n >= sizeof dir) {
        return 0;
    }
    memcpy(dir, path, n);
    dir[n] = '\0';
    return stat(dir, &st) == 0 && S_ISDIR(st.st_mode);
}

static int is_hex64(const char *s)
{
    int i;
    for (i = 0; i < 64; ++i) {
        char ch = s[i];
        if (!((ch >= '0' && ch <= '9') || (ch >= 'a' && ch <= 'f'))) {
            return 0;
        }
    }
    return s[64] == '\0';
}

/* ---------------------------------------------------------------------------------------- the walk */

static int leaf(parse_ctx *p, const char *key, const key_spec *k, const cJSON *v)
{
    double x;
    int i;
    switch (k->type) {
    case K_STRING:
    case K_FILE:
    case K_OUTPUT:
    case K_HASH: {
        char *dst = (char *)field(p, k);
        if (!cJSON_IsString(v)) {
            return fail(p, key, "expected a string, got %s", type_name(v));
        }
        if (k->type == K_HASH) {
            if (v->valuestring[0] != '\0' && !is_hex64(v->valuestring)) { /* "": not checked */
                return fail(p, key, "'%s' is not a sha256 (64 lowercase hex digits)", v->valuestring);
            }
            memcpy(dst, v->valuestring, 65);
            return 1;
        }
        if (k->type == K_STRING) {
            if (strlen(v->valuestring) >= k->size) {
                return fail(p, key, "longer than %zu characters", k->size - 1);
            }
            strcpy(dst, v->valuestring);
            return 1;
        }
        if (!resolve(p, key, v->valuestring, dst, k->size)) {
            return 0;
        }
        if (k->type == K_FILE && dst[0] == '\0' && !k->required) {
            return 1; /* "": none (the key's default) */
        }
        if (k->type == K_FILE) {
            FILE *f = fopen(dst, "r");
            if (f == NULL) {
                return fail(p, key, "cannot read %s: %s", dst, strerror(errno));
            }
            fclose(f);
        } else if (dst[0] != '\0' && !dir_exists_for(dst)) {
            return fail(p, key, "the directory of %s does not exist", dst);
        }
        return 1;
    }
    case K_ENUM:
        if (!cJSON_IsString(v)) {
            return fail(p, key, "expected a string, got %s", type_name(v));
        }
        for (i = 0; k->names[i] != NULL; ++i) {
            if (strcmp(k->names[i], v->valuestring) == 0) {
                *(int *)field(p, k) = i;
                return 1;
            }
        }
        {
            char allowed[128] = "";
            for (i = 0; k->names[i] != NULL; ++i) {
                strncat(allowed, i ? ", " : "", sizeof allowed - strlen(allowed) - 1);
                strncat(allowed, k->names[i], sizeof allowed - strlen(allowed) - 1);
            }
            return fail(p, key, "'%s' is not one of %s", v->valuestring, allowed);
        }
    case K_NUMBER:
        if (!number_in(p, key, k, v, 0, &x)) return 0;
        *(double *)field(p, k) = x;
        return 1;
    case K_INT:
        if (!number_in(p, key, k, v, 1, &x)) return 0;
        *(int *)field(p, k) = (int)x;
        return 1;
    case K_LONG:
        if (!number_in(p, key, k, v, 1, &x)) return 0;
        *(long *)field(p, k) = (long)x;
        return 1;
    case K_BOOL:
        if (!cJSON_IsBool(v)) {
            return fail(p, key, "expected true or false, got %s", type_name(v));
        }
        *(int *)field(p, k) = cJSON_IsTrue(v) ? 1 : 0;
        return 1;
    case K_NUMBERS: {
        double *dst = (double *)field(p, k);
        const cJSON *e;
        char ekey[200];
        if (!cJSON_IsArray(v) || cJSON_GetArraySize(v) != k->n) {
            return fail(p, key, "expected an array of %d numbers, got %s%s", k->n, type_name(v),
                        cJSON_IsArray(v) ? " of another length" : "");
        }
        i = 0;
        cJSON_ArrayForEach(e, v)
        {
            snprintf(ekey, sizeof ekey, "%.120s[%d]", key, i);
            if (!number_in(p, ekey, k, e, 0, &dst[i])) return 0;
            ++i;
        }
        return 1;
    }
    case K_NAMED:
    case K_NAMED_INT: {
        const cJSON *e;
        char ekey[200];
        int *have = k->aux != NONE ? (int *)((char *)p->c + k->aux) : NULL;
        if (!cJSON_IsObject(v)) {
            return fail(p, key, "expected an object {name: number}, got %s", type_name(v));
        }
        cJSON_ArrayForEach(e, v)
        {
            int j = -1;
            snprintf(ekey, sizeof ekey, "%.120s.%.60s", key, e->string);
            for (i = 0; i < k->n; ++i) {
                if (strcmp(k->names[i], e->string) == 0) j = i;
            }
            if (j < 0) {
                return fail(p, ekey, "unknown key (`ddyn_controller --keys` lists them)");
            }
            if (!number_in(p, ekey, k, e, k->type == K_NAMED_INT, &x)) return 0;
            if (k->type == K_NAMED_INT) {
                ((int *)field(p, k))[j] = (int)x;
            } else {
                ((double *)field(p, k))[j] = x;
            }
            if (have != NULL) have[j] = 1;
        }
        if (k->required || have != NULL) {
            for (i = 0; i < k->n; ++i) {
                if (k->required && cJSON_GetObjectItemCaseSensitive(v, k->names[i]) == NULL) {
                    snprintf(ekey, sizeof ekey, "%.120s.%.60s", key, k->names[i]);
                    return fail(p, ekey, "missing (all %d are required)", k->n);
                }
            }
        }
        return 1;
    }
    case K_SECTION:
    default:
        return 0;
    }
}

static int walk(parse_ctx *p, const cJSON *obj, const char *prefix)
{
    const cJSON *m;
    cJSON_ArrayForEach(m, obj)
    {
        char key[160];
        int i;
        snprintf(key, sizeof key, "%.100s%s%.50s", prefix, prefix[0] ? "." : "", m->string);
        i = find_key(key);
        if (i < 0) {
            return fail(p, key, "unknown key (`ddyn_controller --keys` lists them)");
        }
        if (p->seen[i]) {
            return fail(p, key, "given twice");
        }
        p->seen[i] = 1;
        if (KEYS[i].type == K_SECTION) {
            if (!cJSON_IsObject(m)) {
                return fail(p, key, "expected an object, got %s", type_name(m));
            }
            if (!walk(p, m, key)) return 0;
        } else if (!leaf(p, key, &KEYS[i], m)) {
            return 0;
        }
    }
    return 1;
}

/* a bank (grade) column made from a diagnosis (effects.bank, effects.grade) must be the one it made: its largest
 * |value| recorded in effects.bank_peak (effects.grade_peak; written exactly: the CSV's and the JSON's numbers
 * round-trip), so a raceline swapped for another bank (the track's true one) is refused as an edited control.bank
 * is */
static int check_peak(parse_ctx *p, int given, const double *column, double recorded, const char *key,
                      const char *what)
{
    const ddyn_app_config *c = p->c;
    double peak = 0.0;
    int i;
    if (c->effects_sha256[0] == '\0' || !given) {
        return 1;
    }
    for (i = 0; i < c->n_track; ++i) {
        peak = fmax(peak, fabs(column[i]));
    }
    if (fabs(peak - recorded) > 1e-9) {
        return fail(p, key,
                    "%.9g rad from diagnosis %s (sha256 %.12s...), but %s's %s column peaks at %.9g rad: remake "
                    "the file (`ddyn sil run --effects-from D --config-only`) instead of editing it",
                    recorded, c->effects_diagnosis[0] ? c->effects_diagnosis : "(unnamed)", c->effects_sha256,
                    c->raceline, what, peak);
    }
    return 1;
}

static int check_column_peaks(parse_ctx *p)
{
    const ddyn_app_config *c = p->c;
    return check_peak(p, c->effects_bank, c->track[5], c->effects_bank_peak, "effects.bank_peak", "bank") &&
           check_peak(p, c->effects_grade, c->track[6], c->effects_grade_peak, "effects.grade_peak", "grade");
}

/* the raceline CSV: rows x, y, speed, width_left, width_right and, with control.bank, the bank, then with
 * control.grade, the grade */
static int read_raceline(parse_ctx *p)
{
    ddyn_app_config *c = p->c;
    FILE *in = fopen(c->raceline, "r");
    char line[512];
    int lineno = 0, k;
    const int cols = 5 + (c->bank ? 1 : 0) + (c->grade ? 1 : 0), grade_col = c->bank ? 6 : 5;
    if (in == NULL) {
        return fail(p, "raceline", "cannot read %s: %s", c->raceline, strerror(errno));
    }
    c->n_track = 0;
    while (fgets(line, sizeof line, in) != NULL) {
        double row[7];
        char *s = line, *end;
        lineno += 1;
        while (*s == ' ' || *s == '\t') ++s;
        if (*s == '\n' || *s == '\0' || *s == '#' || (lineno == 1 && (*s == 'x' || *s == 'X'))) {
            continue; /* blank, comment, header */
        }
        for (k = 0; k < cols; ++k) {
            row[k] = strtod(s, &end);
            if (end == s || !isfinite(row[k])) {
                fclose(in);
                if (k == 5 && c->bank) {
                    return fail(p, "control.bank", "true, but %s line %d has no finite 6th column (the bank, rad)",
                                c->raceline, lineno);
                }
                if (k == grade_col && c->grade) {
                    return fail(p, "control.grade", "true, but %s line %d has no finite %s column (the grade, rad)",
                                c->raceline, lineno, grade_col == 5 ? "6th" : "7th");
                }
                return fail(p, "raceline", "%s line %d: expected 5 numbers x,y,speed,width_left,width_right",
                            c->raceline, lineno);
            }
            s = end;
            while (*s == ' ' || *s == '\t' || (k < cols - 1 && *s == ',')) ++s;
        }
        if (*s != '\n' && *s != '\0' && *s != '\r') {
            char *b = s + 1, *e = NULL;
            fclose(in);
            (void)strtod(b, &e); /* exactly one more number: a bank column */
            while (e != NULL && e != b && (*e == ' ' || *e == '\t' || *e == '\r')) ++e;
            if (!c->bank && !c->grade && *s == ',' && e != NULL && e != b && (*e == '\n' || *e == '\0')) {
                return fail(p, "control.bank", "false, but %s line %d has a 6th column (a bank): set control.bank "
                            "true or drop the column", c->raceline, lineno);
            }
            if (!c->grade && *s == ',' && e != NULL && e != b && (*e == '\n' || *e == '\0')) {
                return fail(p, "control.grade", "false, but %s line %d has a 7th column (a grade after the bank): set "
                            "control.grade true or drop the column", c->raceline, lineno);
            }
            return fail(p, "raceline", "%s line %d: more than %d columns", c->raceline, lineno, cols);
        }
        if (!(row[2] > 0.0) || row[3] < 0.0 || row[4] < 0.0) {
            fclose(in);
            return fail(p, "raceline", "%s line %d: speed must be > 0 and the widths >= 0", c->raceline, lineno);
        }
        if (c->bank && !(fabs(row[5]) < DDYN_MPC_MAX_BANK)) {
            fclose(in);
            return fail(p, "control.bank", "%s line %d: bank %g rad, beyond +-%.4g rad (45 degrees)", c->raceline,
                        lineno, row[5], DDYN_MPC_MAX_BANK);
        }
        if (c->grade && !(fabs(row[grade_col]) < DDYN_MPC_MAX_GRADE)) {
            fclose(in);
            return fail(p, "control.grade", "%s line %d: grade %g rad, beyond +-%.4g rad (20 degrees)", c->raceline,
                        lineno, row[grade_col], DDYN_MPC_MAX_GRADE);
        }
        if (c->n_track >= DDYN_MPC_MAX_TRACK_POINTS) {
            fclose(in);
            return fail(p, "raceline", "%s: more than %d points (the MPC's table)", c->raceline,
                        DDYN_MPC_MAX_TRACK_POINTS);
        }
        for (k = 0; k < 5; ++k) {
            c->track[k][c->n_track] = row[k];
        }
        c->track[5][c->n_track] = c->bank ? row[5] : 0.0;
        c->track[6][c->n_track] = c->grade ? row[grade_col] : 0.0;
        c->n_track += 1;
    }
    fclose(in);
    if (c->n_track < 4) {
        return fail(p, "raceline", "%s: %d points, at least 4 needed", c->raceline, c->n_track);
    }
    return 1;
}

static void set_defaults(ddyn_app_config *c)
{
    static const int stale[DDYN_DBW_FRAME_COUNT] = {0, 1, 1, 1, 1, 2, 2};
    memset(c, 0, sizeof *c);
    memcpy(c->stale, stale, sizeof c->stale);
    c->prepare = 1;
    c->cpu = -1;
    c->lock_memory = 1;
    c->die_at_step = -1;
}

int ddyn_app_config_parse(const char *text, const char *base_dir, const char *name, ddyn_app_config *c,
                          char err[DDYN_APP_ERROR_LEN])
{
    parse_ctx p;
    cJSON *root;
    const cJSON *veh;
    const ddyn_vehicle_model *model;
    ddyn_ctrl_config defaults;
    int i, ok;
    memset(&p, 0, sizeof p);
    p.c = c;
    p.base_dir = base_dir;
    p.name = name;
    p.err = err;
    err[0] = '\0';
    set_defaults(c);
    root = cJSON_Parse(text);
    if (root == NULL) {
        const char *where = cJSON_GetErrorPtr();
        int line = 1;
        const char *s;
        for (s = text; where != NULL && s < where && *s; ++s) line += *s == '\n';
        return fail(&p, "(document)", "not valid JSON (near line %d)", line);
    }
    if (!cJSON_IsObject(root)) {
        cJSON_Delete(root);
        return fail(&p, "(document)", "expected a JSON object");
    }
    /* the vehicle first: the MPC's defaults are the vehicle's */
    veh = cJSON_GetObjectItemCaseSensitive(root, "vehicle");
    if (veh != NULL && cJSON_IsString(veh)) {
        model = ddyn_model_find(veh->valuestring);
        if (model == NULL) {
            fail(&p, "vehicle", "no generated model '%s'", veh->valuestring);
            cJSON_Delete(root);
            return 0;
        }
        ddyn_ctrl_default_config(model, &defaults);
        c->mpc = defaults.mpc;
    }
    ok = walk(&p, root, "");
    cJSON_Delete(root);
    for (i = 0; ok && i < N_KEYS; ++i) {
        if (KEYS[i].required && !p.seen[i]) {
            const char *dot = strrchr(KEYS[i].key, '.');
            int parent = -1;
            if (dot != NULL) { /* a required key of an absent optional section is not asked for */
                char sec[160];
                snprintf(sec, sizeof sec, "%.*s", (int)(dot - KEYS[i].key), KEYS[i].key);
                parent = find_key(sec);
            }
            if (parent < 0 || p.seen[parent] || KEYS[parent].required) {
                ok = fail(&p, KEYS[i].key, "missing (required)");
            }
        }
    }
    if (ok && c->fixed) {
        for (i = 0; i < DDYN_NC; ++i) {
            if (!c->have_coeffs[i]) {
                char key[64];
                snprintf(key, sizeof key, "coefficients.fixed.%s", COEFF_NAMES[i]);
                ok = fail(&p, key, "missing (coefficients.source is fixed: all 17 are required)");
                break;
            }
        }
    }
    if (ok && !c->throttle_pid) {
        for (i = 0; i < 4; ++i) {
            if (c->have_pid[i]) {
                ok = fail(&p, "control.pid", "given, but control.throttle is not pid");
                break;
            }
        }
    }
    if (ok && c->effects_sha256[0] != '\0' &&
        (fabs(c->effects_delay[0] - c->delay[0]) > 1e-12 || fabs(c->effects_delay[1] - c->delay[1]) > 1e-12)) {
        /* like coefficients.checkpoint_hash: a file edited after it was made from a diagnosis is refused */
        ok = fail(&p, "effects.delay",
                  "steering %g s, throttle %g s from diagnosis %s (sha256 %.12s...), but control.delay is steering "
                  "%g s, throttle %g s: remake the file (`ddyn sil run --effects-from D --config-only`) instead of editing it",
                  c->effects_delay[0], c->effects_delay[1], c->effects_diagnosis[0] ? c->effects_diagnosis : "(unnamed)",
                  c->effects_sha256, c->delay[0], c->delay[1]);
    }
    if (ok && c->effects_sha256[0] != '\0' && fabs(c->effects_lag[0] - c->lag[0]) > 1e-12) {
        ok = fail(&p, "effects.lag",
                  "steering %g s from diagnosis %s (sha256 %.12s...), but control.lag is steering %g s: remake the "
                  "file (`ddyn sil run --effects-from D --config-only`) instead of editing it",
                  c->effects_lag[0], c->effects_diagnosis[0] ? c->effects_diagnosis : "(unnamed)", c->effects_sha256,
                  c->lag[0]);
    }
    if (ok && c->effects_sha256[0] != '\0' && fabs(c->effects_mass_offset - c->mass_offset) > 1e-12) {
        ok = fail(&p, "effects.mass_offset",
                  "%g from diagnosis %s (sha256 %.12s...), but control.mass_offset is %g: remake the file (`ddyn sil "
                  "run --effects-from D --config-only`) instead of editing it",
                  c->effects_mass_offset, c->effects_diagnosis[0] ? c->effects_diagnosis : "(unnamed)",
                  c->effects_sha256, c->mass_offset);
    }
    if (ok && c->effects_sha256[0] != '\0' && fabs(c->effects_downforce - c->downforce) > 1e-12) {
        ok = fail(&p, "effects.downforce",
                  "%g from diagnosis %s (sha256 %.12s...), but control.downforce is %g: remake the file (`ddyn sil "
                  "run --effects-from D --config-only`) instead of editing it",
                  c->effects_downforce, c->effects_diagnosis[0] ? c->effects_diagnosis : "(unnamed)",
                  c->effects_sha256, c->downforce);
    }
    if (ok && c->effects_sha256[0] != '\0' && c->effects_grade != c->grade) {
        ok = fail(&p, "effects.grade",
                  "%s from diagnosis %s (sha256 %.12s...), but control.grade is %s: remake the file (`ddyn sil run "
                  "--effects-from D --config-only`) instead of editing it",
                  c->effects_grade ? "true" : "false", c->effects_diagnosis[0] ? c->effects_diagnosis : "(unnamed)",
                  c->effects_sha256, c->grade ? "true" : "false");
    }
    if (ok && c->effects_sha256[0] != '\0' && c->effects_bank != c->bank) {
        /* a bank the diagnosis did not give (the track's true one, say), or one it gave and the file dropped */
        ok = fail(&p, "effects.bank",
                  "%s from diagnosis %s (sha256 %.12s...), but control.bank is %s: remake the file (`ddyn sil run "
                  "--effects-from D --config-only`) instead of editing it",
                  c->effects_bank ? "true" : "false", c->effects_diagnosis[0] ? c->effects_diagnosis : "(unnamed)",
                  c->effects_sha256, c->bank ? "true" : "false");
    }
    if (ok) {
        /* a position frame starts each period: dated at another cycle than the one it comes at, every
         * clean period reads as late (issue 34: the AV-21's 40 ms periods against the DBC's 20 ms) */
        double gnss = c->cycle_ms[DDYN_DBW_FRAME_GNSS_POSITION] > 0
                          ? 1e-3 * c->cycle_ms[DDYN_DBW_FRAME_GNSS_POSITION]
                          : 1e-6 * (double)ddyn_dbw_cycle_us(DDYN_DBW_FRAME_GNSS_POSITION);
        if (fabs(gnss - c->period) > 1e-9) {
            ok = fail(&p, "can.cycle_ms.gnss_position",
                      "%g ms, but a position frame starts each period of control.period %g s: set it to the "
                      "period (the DBC's is %g ms)",
                      gnss * 1e3, c->period, 1e-3 * (double)ddyn_dbw_cycle_us(DDYN_DBW_FRAME_GNSS_POSITION));
        }
    }
    if (ok && p.seen[find_key("telemetry.metrics")] == 0) {
        ok = resolve(&p, "telemetry.metrics", "controller_metrics.json", c->metrics, sizeof c->metrics);
    }
    if (ok) {
        ok = read_raceline(&p);
    }
    if (ok) {
        ok = check_column_peaks(&p);
    }
    return ok;
}

int ddyn_app_config_read(const char *path, ddyn_app_config *c, char err[DDYN_APP_ERROR_LEN])
{
    FILE *in = fopen(path, "rb");
    char *text, dir[DDYN_APP_PATH_LEN];
    const char *slash = strrchr(path, '/');
    long n;
    int ok;
    if (in == NULL) {
        snprintf(err, DDYN_APP_ERROR_LEN, "%s: cannot read: %s", path, strerror(errno));
        return 0;
    }
    if (fseek(in, 0, SEEK_END) != 0 || (n = ftell(in)) < 0 || n > (1L << 22) || fseek(in, 0, SEEK_SET) != 0) {
        fclose(in);
        snprintf(err, DDYN_APP_ERROR_LEN, "%s: not a regular file of at most 4 MB", path);
        return 0;
    }
    text = (char *)malloc((size_t)n + 1); /* the application, not the runtime: read once at start-up */
    if (text == NULL || fread(text, 1, (size_t)n, in) != (size_t)n) {
        fclose(in);
        free(text);
        snprintf(err, DDYN_APP_ERROR_LEN, "%s: read failed", path);
        return 0;
    }
    fclose(in);
    text[n] = '\0';
    if (slash == NULL) {
        strcpy(dir, ".");
    } else if (slash == path) {
        strcpy(dir, "/");
    } else {
        snprintf(dir, sizeof dir, "%.*s", (int)(slash - path), path);
    }
    ok = ddyn_app_config_parse(text, dir, path, c, err);
    free(text);
    return ok;
}

int ddyn_app_check_network(const ddyn_app_config *c, const ddyn_net_tables *tables, char err[DDYN_APP_ERROR_LEN])
{
    const char *built = tables != NULL && tables->checkpoint_sha256 != NULL ? tables->checkpoint_sha256 : "";
    err[0] = '\0';
    if (c->checkpoint_hash[0] == '\0' || strcmp(built, c->checkpoint_hash) == 0) {
        return 1;
    }
    snprintf(err, DDYN_APP_ERROR_LEN,
             "coefficients.checkpoint_hash: this controller was built for checkpoint %.12s..., not for %.12s... "
             "(a stale build): `ddyn export CKPT --out DIR`, then rebuild with -DDDYN_NET_EXPORT_DIR=DIR",
             built[0] ? built : "(none)", c->checkpoint_hash);
    return 0;
}

ddyn_status ddyn_app_node_init(ddyn_sil_node *node, const ddyn_app_config *c, const ddyn_net_tables *tables)
{
    const ddyn_vehicle_model *model = ddyn_model_find(c->vehicle);
    ddyn_ctrl_config cfg;
    ddyn_status st;
    char err[DDYN_APP_ERROR_LEN];
    int i, k;
    if (model == NULL) {
        fprintf(stderr, "ddyn_controller: vehicle: no generated model '%s'\n", c->vehicle);
        return DDYN_ERR_ARGUMENT;
    }
    if (!ddyn_app_check_network(c, tables, err)) {
        fprintf(stderr, "ddyn_controller: refused: %s\n", err);
        return DDYN_ERR_NET_HASH;
    }
    ddyn_ctrl_default_config(model, &cfg);
    memcpy(cfg.c_nominal, c->nominal, sizeof cfg.c_nominal);
    cfg.mpc = c->mpc;
    cfg.delay.steering = c->delay[0];
    cfg.delay.throttle = c->delay[1];
    cfg.lag.steering = c->lag[0];
    cfg.mass_offset = c->mass_offset;
    cfg.downforce = c->downforce;
    {
        int steps[DDYN_NU];
        if (ddyn_ctrl_delay_steps(&cfg.delay, model->sample_time, steps) != DDYN_OK) {
            fprintf(stderr,
                    "ddyn_controller: control.delay: steering %g s, throttle %g s: above this build's maximum of %d "
                    "periods (%g s at %g s; DDYN_CTRL_MAX_DELAY_STEPS)\n",
                    c->delay[0], c->delay[1], DDYN_CTRL_MAX_DELAY_STEPS,
                    DDYN_CTRL_MAX_DELAY_STEPS * model->sample_time, model->sample_time);
            return DDYN_ERR_ARGUMENT;
        }
    }
    if (c->fixed) {
        cfg.coeff_source = DDYN_CTRL_SOURCE_FIXED; /* the network is never run */
        memcpy(cfg.c_fixed, c->coeffs, sizeof cfg.c_fixed);
    }
    if (c->throttle_pid) {
        double *gain[4];
        gain[0] = &cfg.pid.kp;
        gain[1] = &cfg.pid.ki;
        gain[2] = &cfg.pid.kd;
        gain[3] = &cfg.pid.preview;
        cfg.throttle_mode = DDYN_CTRL_THROTTLE_PID;
        for (i = 0; i < 4; ++i) {
            if (c->have_pid[i]) *gain[i] = c->pid[i];
        }
    }
    for (k = 0; k < DDYN_NX; ++k) {
        if (c->q[k] > 0.0) {
            cfg.q_diag[k] = c->q[k];
        }
    }
    for (k = 0; k < DDYN_MEAS_COUNT; ++k) {
        for (i = 0; i < DDYN_MEAS_MAX_DIM; ++i) {
            double sd = c->r_std[k][i] > 1e-4 ? c->r_std[k][i] : 1e-4;
            cfg.r_diag[k][i] = sd * sd;
        }
    }
    st = ddyn_sil_node_init(node, model, tables, &cfg, c->x0, c->period, c->stale);
    for (k = 0; st == DDYN_OK && k < DDYN_DBW_FRAME_COUNT; ++k) {
        /* the link dates each frame by its counter and the cycle it really comes at */
        st = ddyn_dbw_link_set_cycle(&node->link, (ddyn_dbw_frame)k, (uint32_t)c->cycle_ms[k] * 1000u);
    }
    if (st == DDYN_OK) {
        st = ddyn_ctrl_set_track(&node->ctl, c->n_track, c->track[0], c->track[1], c->track[2], c->track[3],
                                 c->track[4]);
    }
    if (st == DDYN_OK && c->bank) {
        st = ddyn_ctrl_set_bank(&node->ctl, c->track[5]); /* the road's bank along the raceline */
    }
    if (st == DDYN_OK && c->grade) {
        st = ddyn_ctrl_set_grade(&node->ctl, c->track[6]); /* the road's grade along the raceline */
    }
    if (st == DDYN_OK) {
        /* frame authentication: can.key_file, else $DDYN_DBW_KEY_FILE, else off */
        const char *key_path = ddyn_dbw_auth_key_path(c->key_file);
        if (key_path != NULL) {
            uint8_t key[DDYN_DBW_AUTH_KEY_LEN];
            const char *why = NULL;
            st = ddyn_dbw_auth_read_key_file(key_path, key, &why);
            if (st != DDYN_OK) {
                fprintf(stderr, "ddyn_controller: %s %s: %s\n", c->key_file[0] ? "can.key_file" : DDYN_DBW_KEY_FILE_ENV,
                        key_path, why != NULL ? why : "unreadable");
                return st;
            }
            st = ddyn_sil_node_auth_enable(node, key);
            memset(key, 0, sizeof key);
        }
    }
    if (st != DDYN_OK) {
        fprintf(stderr, "ddyn_controller: the controller refused the configuration: %s%s\n", ddyn_status_name(st),
                st == DDYN_ERR_NET_SHAPE || st == DDYN_ERR_NET_HASH || st == DDYN_ERR_NET_MAGIC
                    ? " (network built for another export?)"
                    : "");
    }
    return st;
}

/* ---------------------------------------------------------------------------------------- printing */

static cJSON *section_of(cJSON *root, const char *key, const char **leaf_name)
{
    char part[160];
    const char *s = key, *dot;
    cJSON *obj = root;
    while ((dot = strchr(s, '.')) != NULL) {
        cJSON *next;
        snprintf(part, sizeof part, "%.*s", (int)(dot - s), s);
        next = cJSON_GetObjectItemCaseSensitive(obj, part);
        if (next == NULL) {
            next = cJSON_AddObjectToObject(obj, part);
        }
        obj = next;
        s = dot + 1;
    }
    *leaf_name = s;
    return obj;
}

void ddyn_app_config_print(const ddyn_app_config *c, FILE *out)
{
    cJSON *root = cJSON_CreateObject();
    char *text;
    int i, j;
    for (i = 0; i < N_KEYS; ++i) {
        const key_spec *k = &KEYS[i];
        const char *name;
        const void *f = (const char *)c + k->offset;
        cJSON *obj;
        if (k->type == K_SECTION) {
            continue;
        }
        obj = section_of(root, k->key, &name);
        switch (k->type) {
        case K_STRING:
        case K_FILE:
        case K_OUTPUT:
        case K_HASH:
            cJSON_AddStringToObject(obj, name, (const char *)f);
            break;
        case K_ENUM:
            cJSON_AddStringToObject(obj, name, k->names[*(const int *)f]);
            break;
        case K_NUMBER:
            cJSON_AddNumberToObject(obj, name, *(const double *)f);
            break;
        case K_INT:
            cJSON_AddNumberToObject(obj, name, *(const int *)f);
            break;
        case K_LONG:
            cJSON_AddNumberToObject(obj, name, (double)*(const long *)f);
            break;
        case K_BOOL:
            cJSON_AddBoolToObject(obj, name, *(const int *)f);
            break;
        case K_NUMBERS:
            cJSON_AddItemToObject(obj, name, cJSON_CreateDoubleArray((const double *)f, k->n));
            break;
        case K_NAMED:
        case K_NAMED_INT: {
            cJSON *o = cJSON_AddObjectToObject(obj, name);
            const int *have = k->aux != NONE ? (const int *)((const char *)c + k->aux) : NULL;
            for (j = 0; j < k->n; ++j) {
                if (have != NULL && !have[j]) continue;
                cJSON_AddNumberToObject(o, k->names[j],
                                        k->type == K_NAMED ? ((const double *)f)[j] : ((const int *)f)[j]);
            }
            break;
        }
        default:
            break;
        }
    }
    cJSON_AddNumberToObject(root, "raceline_points", c->n_track);
    text = cJSON_Print(root);
    if (text != NULL) {
        fprintf(out, "%s\n", text);
        cJSON_free(text);
    }
    cJSON_Delete(root);
}

void ddyn_app_config_keys(FILE *out)
{
    static const char *const TYPE_NAMES[] = {"object", "string", "choice", "file", "output file", "sha256",
                                             "number", "integer", "integer", "boolean", "numbers", "{name: number}",
                                             "{name: integer}"};
    int i, j;
    for (i = 0; i < N_KEYS; ++i) {
        const key_spec *k = &KEYS[i];
        fprintf(out, "%-34s %s", k->key, TYPE_NAMES[k->type]);
        if (k->type == K_NUMBERS) fprintf(out, "[%d]", k->n);
        if (k->type == K_ENUM || k->type == K_NAMED || k->type == K_NAMED_INT) {
            fputs(" (", out);
            for (j = 0; k->names[j] != NULL && (k->type == K_ENUM || j < k->n); ++j) {
                fprintf(out, "%s%s", j ? " " : "", k->names[j]);
                if (k->type != K_ENUM && j + 1 >= k->n) break;
            }
            fputc(')', out);
        }
        if (k->type == K_NUMBER || k->type == K_INT || k->type == K_LONG || k->type == K_NUMBERS ||
            k->type == K_NAMED || k->type == K_NAMED_INT) {
            if (k->lo > -BIG) fprintf(out, " %.6g..%.6g", k->lo, k->hi);
        }
        fprintf(out, "%s: %s\n", k->required ? " required" : "", k->help);
    }
}
