/* Names of the runtime's one error type (ddyn/status.h). */
#include "ddyn/status.h"

const char *ddyn_status_name(ddyn_status status)
{
    switch (status) {
    case DDYN_OK:
        return "DDYN_OK";
    case DDYN_ERR_ARGUMENT:
        return "DDYN_ERR_ARGUMENT";
    case DDYN_ERR_NONFINITE_INPUT:
        return "DDYN_ERR_NONFINITE_INPUT";
    case DDYN_ERR_NONFINITE_OUTPUT:
        return "DDYN_ERR_NONFINITE_OUTPUT";
    case DDYN_ERR_EVALUATION:
        return "DDYN_ERR_EVALUATION";
    case DDYN_ERR_NOT_POSITIVE_DEFINITE:
        return "DDYN_ERR_NOT_POSITIVE_DEFINITE";
    case DDYN_ERR_QP_NOT_CONVERGED:
        return "DDYN_ERR_QP_NOT_CONVERGED";
    case DDYN_ERR_NOT_READY:
        return "DDYN_ERR_NOT_READY";
    case DDYN_ERR_NET_MAGIC:
        return "DDYN_ERR_NET_MAGIC";
    case DDYN_ERR_NET_SHAPE:
        return "DDYN_ERR_NET_SHAPE";
    case DDYN_ERR_NET_HASH:
        return "DDYN_ERR_NET_HASH";
    case DDYN_ERR_NET_NORMALISATION:
        return "DDYN_ERR_NET_NORMALISATION";
    case DDYN_ERR_NOT_INITIALISED:
        return "DDYN_ERR_NOT_INITIALISED";
    case DDYN_ERR_CONFIG:
        return "DDYN_ERR_CONFIG";
    case DDYN_ERR_RANGE:
        return "DDYN_ERR_RANGE";
    }
    return "DDYN_ERR_UNKNOWN";
}
