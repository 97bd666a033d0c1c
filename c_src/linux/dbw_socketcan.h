/*
 * dbw_socketcan.h - the drive-by-wire monitor (ddyn/dbw.h) fed from a SocketCAN socket
 * (can_socket.h). Linux only.
 */
#ifndef DDYN_LINUX_DBW_SOCKETCAN_H
#define DDYN_LINUX_DBW_SOCKETCAN_H

#include "can_socket.h"
#include "ddyn/dbw.h"

#ifdef __cplusplus
extern "C" {
#endif

typedef enum { DDYN_DBW_ROLE_CONTROLLER = 0, DDYN_DBW_ROLE_DBW_UNIT } ddyn_dbw_role;

/* Open `ifname` with the receive filters of `role`. Both roles receive the protocol's whole
 * identifier block 0x100-0x13F (standard frames only), so that undefined identifiers inside it
 * are seen and counted as unknown frames, while every other identifier is dropped by the
 * kernel. The controller additionally excludes DBW_Command (its own kind of frame, sent by
 * any other controller on the bus); the DBW unit excludes nothing in the block (it decodes but
 * does not monitor feedback). Returns 0 or -errno. */
int ddyn_dbw_socketcan_open(ddyn_can_socket *s, const char *ifname, ddyn_dbw_role role);

/* Receive until deadline_mono_us and feed every frame to `dbw`: data frames through
 * ddyn_dbw_on_frame (with their kernel receive time), error frames as BUS_OFF or BUS_ERROR
 * (error passive, controller overflow, transmit timeout; single protocol errors are counted by
 * the socket, not failures: CAN retransmits them), a receive error ENETDOWN/ENODEV/ENXIO as
 * IFACE_GONE (the kernel reports each link loss once). Returns the number of data frames
 * fed, or -errno for other errors. */
int ddyn_dbw_socketcan_pump(ddyn_can_socket *s, ddyn_dbw *dbw, uint64_t deadline_mono_us);

/* Classify an error frame: DDYN_DBW_FAIL_BUS_OFF, DDYN_DBW_FAIL_BUS_ERROR, or DDYN_DBW_FAIL_COUNT
 * when it is no failure (warnings, lost arbitration, restarted). */
ddyn_dbw_failure ddyn_dbw_socketcan_classify_error(const ddyn_can_rx *rx);

/* Send one encoded protocol frame. Returns 0 or -errno; ENETDOWN/ENODEV/ENXIO are also reported
 * to `dbw` as IFACE_GONE. */
int ddyn_dbw_socketcan_send(ddyn_can_socket *s, ddyn_dbw *dbw, ddyn_dbw_frame frame,
                            const uint8_t data[DDYN_DBW_FRAME_LEN]);

#ifdef __cplusplus
}
#endif

#endif /* DDYN_LINUX_DBW_SOCKETCAN_H */
