/*
 * ddyn/status.h - the one error type of the runtime's modules (model, EKF, MPC, QP, guard network,
 * controller set-up, drive-by-wire set-up): 0 is success, every other value names one cause.
 *
 * Two other return types are not errors and stay as they are: ddyn_ctrl_status is the set of
 * conditions of one control period (a bitmask: several hold at once), and ddyn_dbw_decode_result
 * classifies a received frame (foreign, unknown, bad length, checksum, range).
 */
#ifndef DDYN_STATUS_H
#define DDYN_STATUS_H

#ifdef __cplusplus
extern "C" {
#endif

typedef enum {
    DDYN_OK = 0,
    DDYN_ERR_ARGUMENT = 1,          /* null pointer or unknown discretisation */
    DDYN_ERR_NONFINITE_INPUT = 2,   /* NaN or inf in x, u or c: nothing computed */
    DDYN_ERR_NONFINITE_OUTPUT = 3,  /* the model produced NaN or inf (e.g. Iz = 0) */
    DDYN_ERR_EVALUATION = 4,        /* the generated function reported failure */
    DDYN_ERR_NOT_POSITIVE_DEFINITE = 5, /* a covariance that must be positive definite is not */
    DDYN_ERR_QP_NOT_CONVERGED = 6,  /* the MPC's QP hit its iteration cap: the command is defined but not optimal */
    DDYN_ERR_NOT_READY = 7,         /* the MPC lacks its track or coefficients; a link not ready to enable */
    /* the guard network's tables (ddyn_guard_net_init), passed on by ddyn_ctrl_init */
    DDYN_ERR_NET_MAGIC = 8,         /* not a ddyn weight table */
    DDYN_ERR_NET_SHAPE = 9,         /* tables exported for another architecture */
    DDYN_ERR_NET_HASH = 10,         /* tables exported from another checkpoint */
    DDYN_ERR_NET_NORMALISATION = 11, /* a feature std that is not finite and > 0, or a non-finite mean */
    DDYN_ERR_NOT_INITIALISED = 12,  /* a context used before its init succeeded */
    DDYN_ERR_CONFIG = 13,           /* a configuration outside its documented ranges */
    DDYN_ERR_RANGE = 14             /* a value outside its allowed range (a CAN signal's DBC range) */
} ddyn_status;

/* "DDYN_OK", "DDYN_ERR_ARGUMENT", ...; "DDYN_ERR_UNKNOWN" for a value outside the enum. */
const char *ddyn_status_name(ddyn_status status);

#ifdef __cplusplus
}
#endif

#endif /* DDYN_STATUS_H */
