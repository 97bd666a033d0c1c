/* The drive-by-wire monitor fed from SocketCAN (dbw_socketcan.h). */
#include "dbw_socketcan.h"

#include <errno.h>

#include <linux/can/error.h>

/* at most this many frames per pump call: bounded work even on a flooded bus */
#define PUMP_MAX_FRAMES 256u

int ddyn_dbw_socketcan_open(ddyn_can_socket *s, const char *ifname, ddyn_dbw_role role)
{
    /* standard data frames only: the EFF and RTR flags are part of the compared bits */
    const canid_t flags = CAN_EFF_FLAG | CAN_RTR_FLAG;
    struct can_filter f[7];
    unsigned b;
    if (role != DDYN_DBW_ROLE_CONTROLLER) {
        f[0].can_id = DDYN_DBW_ID_BLOCK_BASE;
        f[0].can_mask = DDYN_DBW_ID_BLOCK_MASK | flags;
        return ddyn_can_open(s, ifname, f, 1u, false, false);
    }
    /* the block without its first identifier (DBW_Command, 0x100) as a union of aligned
     * sub-blocks 0x101, 0x102-0x103, 0x104-0x107, ..., 0x120-0x13F. (Joined filters with an
     * inverted one would say the same, but the kernel then drops error frames, which match
     * only the error mask and never "all" filters.) */
    for (b = 0; b < 6u; ++b) {
        f[b].can_id = DDYN_DBW_ID_BLOCK_BASE | (1u << b);
        f[b].can_mask = (CAN_SFF_MASK & ~((1u << b) - 1u)) | flags;
    }
    return ddyn_can_open(s, ifname, f, 6u, false, false);
}

ddyn_dbw_failure ddyn_dbw_socketcan_classify_error(const ddyn_can_rx *rx)
{
    const uint8_t passive_or_overflow = CAN_ERR_CRTL_RX_PASSIVE | CAN_ERR_CRTL_TX_PASSIVE |
                                        CAN_ERR_CRTL_RX_OVERFLOW | CAN_ERR_CRTL_TX_OVERFLOW;
    if (rx == NULL || !rx->error) {
        return DDYN_DBW_FAIL_COUNT;
    }
    if (rx->err_class & CAN_ERR_BUSOFF) {
        return DDYN_DBW_FAIL_BUS_OFF;
    }
    if ((rx->err_class & CAN_ERR_TX_TIMEOUT) ||
        ((rx->err_class & CAN_ERR_CRTL) && (rx->data[1] & passive_or_overflow))) {
        return DDYN_DBW_FAIL_BUS_ERROR;
    }
    return DDYN_DBW_FAIL_COUNT;
}

static bool is_iface_gone(int err)
{
    return err == ENETDOWN || err == ENODEV || err == ENXIO;
}

int ddyn_dbw_socketcan_pump(ddyn_can_socket *s, ddyn_dbw *dbw, uint64_t deadline_mono_us)
{
    unsigned i;
    int fed = 0;
    if (s == NULL || dbw == NULL) {
        return -EINVAL;
    }
    for (i = 0; i < PUMP_MAX_FRAMES; ++i) {
        ddyn_can_rx rx;
        int r = ddyn_can_receive(s, &rx, deadline_mono_us);
        if (r == 0) {
            break;
        }
        if (r < 0) {
            if (is_iface_gone(-r)) {
                ddyn_dbw_report(dbw, DDYN_DBW_FAIL_IFACE_GONE, ddyn_can_mono_us());
                /* the error is reported once by the kernel; without frames, waiting is all there is */
                continue;
            }
            return r;
        }
        if (rx.error) {
            ddyn_dbw_failure k = ddyn_dbw_socketcan_classify_error(&rx);
            if (k != DDYN_DBW_FAIL_COUNT) {
                ddyn_dbw_report(dbw, k, rx.t_mono_us);
            }
            continue;
        }
        if (rx.extended || rx.rtr) {
            continue; /* the filters drop these; a frame that slips through is not ours */
        }
        (void)ddyn_dbw_on_frame(dbw, rx.id, rx.data, rx.len, rx.t_mono_us);
        ++fed;
    }
    return fed;
}

int ddyn_dbw_socketcan_send(ddyn_can_socket *s, ddyn_dbw *dbw, ddyn_dbw_frame frame,
                            const uint8_t data[DDYN_DBW_FRAME_LEN])
{
    int r = ddyn_can_send(s, ddyn_dbw_frame_id(frame), false, data, DDYN_DBW_FRAME_LEN);
    if (r < 0 && dbw != NULL && is_iface_gone(-r)) {
        ddyn_dbw_report(dbw, DDYN_DBW_FAIL_IFACE_GONE, ddyn_can_mono_us());
    }
    return r;
}
