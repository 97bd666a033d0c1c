/*
 * controller_config.h - the configuration file of ddyn_controller (the car's and the SIL's
 * controller process, docs/deploy.md "Configuration reference"): JSON, read with cJSON (the Linux
 * application only; the c_src runtime core stays free of it), validated key by key against ONE
 * table of keys (controller_config.c KEYS): an unknown key, a wrong type, a value out of range, a
 * missing required key or an unreadable file is refused with a message that names the key, e.g.
 *   controller.json: control.period: 0 is out of range (0.0001 .. 10)
 * Adding a setting is one row of that table plus a field here.
 *
 * Host-side (stdio, cJSON); the node built from the configuration is controller_node.h's.
 */
#ifndef DDYN_CONTROLLER_CONFIG_H
#define DDYN_CONTROLLER_CONFIG_H

#include <stdio.h>

#include "controller_node.h"

#ifdef __cplusplus
extern "C" {
#endif

#define DDYN_APP_MAX_STEPS 200000
#define DDYN_APP_PATH_LEN 512
#define DDYN_APP_ERROR_LEN 640

typedef enum { DDYN_APP_PACING_FRAME = 0, DDYN_APP_PACING_TIMER = 1 } ddyn_app_pacing;

typedef struct {
    /* vehicle + coefficients */
    char vehicle[64];                   /* vehicle: a generated model (ddyn_model_find) */
    double nominal[DDYN_NC];            /* nominal_coefficients.<name> (all required) */
    int fixed;                          /* coefficients.source: 0 network, 1 fixed */
    double coeffs[DDYN_NC];             /* coefficients.fixed.<name> (required with source fixed) */
    int have_coeffs[DDYN_NC];
    char checkpoint_hash[65];           /* coefficients.checkpoint_hash ("" = not checked) */
    /* CAN */
    char can_interface[32];             /* can.interface */
    int stale[DDYN_DBW_FRAME_COUNT];    /* can.stale_periods.<frame> (0 = not monitored) */
    char key_file[DDYN_APP_PATH_LEN];   /* can.key_file: the frame authentication key ("" = $DDYN_DBW_KEY_FILE, else off) */
    int cycle_ms[DDYN_DBW_FRAME_COUNT]; /* can.cycle_ms.<frame>: the rate the car sends it at (0 = the DBC's) */
    /* control */
    double period;                      /* control.period, s */
    int throttle_pid;                   /* control.throttle: "mpc" 0 / "pid" 1 */
    double pid[4];                      /* control.pid.{kp,ki,kd,preview} */
    int have_pid[4];
    double delay[2];                    /* control.delay.{steering,throttle}, s (0 = none) */
    double lag[1];                      /* control.lag.steering: the steering lag's time constant, s (0 = none) */
    double mass_offset;                 /* control.mass_offset: the car's mass is (1 + it) times the model's */
    double downforce;                   /* control.downforce: k, s^2/m^2 (tyre peaks times 1 + k vx^2) */
    int bank;                           /* control.bank: the raceline's 6th column is the road's bank (rad) */
    int grade;                          /* control.grade: the raceline's next column is the road's grade (rad) */
    /* effects: what the configuration was made from (`ddyn sil effects`, issue 34); "" = not recorded */
    char effects_diagnosis[DDYN_APP_PATH_LEN]; /* effects.diagnosis: the diagnosis.json (recorded, not read) */
    char effects_sha256[65];            /* effects.diagnosis_sha256: its sha256 */
    double effects_delay[2];            /* effects.delay.{steering,throttle}: the delays it gave, s */
    double effects_lag[1];              /* effects.lag.steering: the steering lag it gave, s */
    double effects_mass_offset;         /* effects.mass_offset: the mass offset it gave */
    double effects_downforce;           /* effects.downforce: the downforce it gave */
    int effects_bank;                   /* effects.bank: whether it gave the road's bank (control.bank must match) */
    double effects_bank_peak;           /* effects.bank_peak: the largest |bank| (rad) of the column it gave */
    char effects_bank_from[DDYN_APP_PATH_LEN]; /* effects.bank_from: which bank it is (recorded, not read) */
    int effects_grade;                  /* effects.grade: whether it gave the road's grade (control.grade must match) */
    double effects_grade_peak;          /* effects.grade_peak: the largest |grade| (rad) of the column it gave */
    int prepare;                        /* control.prepare: RTI split (ddyn_ctrl_prepare after each command) */
    long max_steps;                     /* control.max_steps */
    /* filter */
    double x0[DDYN_NX];                 /* filter.x0 */
    double q[DDYN_NX];                  /* filter.process_noise (0 = the controller's default) */
    double r_std[DDYN_MEAS_COUNT][DDYN_MEAS_MAX_DIM]; /* filter.sensor_std.<sensor> (0 = default) */
    /* track */
    char raceline[DDYN_APP_PATH_LEN];   /* raceline: CSV file x,y,speed,width_left,width_right[,bank] */
    int n_track;
    double track[7][DDYN_MPC_MAX_TRACK_POINTS]; /* the columns; track[5]: the bank (0 without control.bank),
                                                   track[6]: the grade (0 without control.grade) */
    /* MPC overrides (unset: ddyn_ctrl_default_config's) */
    ddyn_mpc_config mpc;                /* mpc.* */
    /* telemetry and outputs */
    char lcm_url[256];                  /* telemetry.lcm_url ("" = none) */
    char metrics[DDYN_APP_PATH_LEN];    /* telemetry.metrics */
    char log[DDYN_APP_PATH_LEN];        /* telemetry.log ("" = no per-period log) */
    /* real time */
    ddyn_app_pacing pacing;             /* realtime.pacing */
    int priority;                       /* realtime.priority: SCHED_FIFO priority, 0 = none */
    int cpu;                            /* realtime.cpu: CPU to pin to, -1 = none */
    int lock_memory;                    /* realtime.lock_memory: mlockall */
    double lockstep_silence;            /* realtime.lockstep_silence, s (0 = real time) */
    double idle_exit;                   /* realtime.idle_exit, s (0 = never) */
    /* SIL fault injection */
    long die_at_step;                   /* sil.die_at_step (-1 = never) */
} ddyn_app_config;

/* Read and validate a configuration file. On failure returns 0 and writes the reason (naming the
 * key) into err. Relative file names are relative to the configuration file's directory. */
int ddyn_app_config_read(const char *path, ddyn_app_config *c, char err[DDYN_APP_ERROR_LEN]);

/* The same from JSON text (base_dir: the directory relative file names are resolved against). */
int ddyn_app_config_parse(const char *text, const char *base_dir, const char *name, ddyn_app_config *c,
                          char err[DDYN_APP_ERROR_LEN]);

/* Refuse a network built for another checkpoint than the configuration's checkpoint_hash (when
 * it names one). Returns 0 and writes the reason into err on a mismatch. */
int ddyn_app_check_network(const ddyn_app_config *c, const ddyn_net_tables *tables, char err[DDYN_APP_ERROR_LEN]);

/* The controller configuration (ddyn_ctrl_default_config, then the file's settings), the node
 * initialised with it and the raceline set, and frame authentication enabled with the key of
 * can.key_file (else $DDYN_DBW_KEY_FILE; neither: off; a key file that cannot be used is refused by
 * name, never a silent fall back to unauthenticated frames). Prints the reason to stderr and returns
 * the error on failure (after ddyn_app_check_network). */
ddyn_status ddyn_app_node_init(ddyn_sil_node *node, const ddyn_app_config *c, const ddyn_net_tables *tables);

/* The table of keys, one line each (key, type, range, default, meaning), for --keys and docs. */
void ddyn_app_config_keys(FILE *out);

/* Print the configuration as read, with the defaults filled in, as JSON (for --check). */
void ddyn_app_config_print(const ddyn_app_config *c, FILE *out);

#ifdef __cplusplus
}
#endif

#endif
