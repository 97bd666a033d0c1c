/*
 * ddyn/linux can_socket.h - SocketCAN raw-socket transport (Linux only; not part of the
 * Cortex-M7 build). One socket bound to one interface by name, with kernel receive filters,
 * error frames enabled, kernel software receive timestamps (SO_TIMESTAMPING), and a
 * non-blocking receive that waits at most until a deadline on the monotonic clock.
 *
 * Times: CLOCK_MONOTONIC microseconds. The kernel stamps frames on CLOCK_REALTIME; each
 * received frame carries both the raw stamp and its monotonic equivalent (offset sampled at
 * receive), so deadlines never depend on wall-clock steps.
 */
#ifndef DDYN_LINUX_CAN_SOCKET_H
#define DDYN_LINUX_CAN_SOCKET_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include <linux/can.h>

#ifdef __cplusplus
extern "C" {
#endif

#define DDYN_CAN_IFNAME_MAX 16 /* IFNAMSIZ */

typedef struct {
    int fd;
    int ifindex;
    char ifname[DDYN_CAN_IFNAME_MAX];
    bool fd_frames;          /* CAN FD frames enabled (CAN_RAW_FD_FRAMES) */
    uint32_t rx_frames;      /* data frames received */
    uint32_t rx_error_frames;
    uint32_t rx_dropped;     /* kernel receive-queue drops (SO_RXQ_OVFL), last value seen */
    uint32_t tx_frames;
} ddyn_can_socket;

typedef struct {
    uint32_t id;             /* 11- or 29-bit identifier, flags removed */
    bool extended;
    bool rtr;
    bool error;              /* an error frame: err_class holds the CAN_ERR_* class bits */
    bool fd;                 /* a CAN FD frame */
    uint8_t len;
    uint8_t data[64];
    uint32_t err_class;
    uint64_t t_kernel_realtime_us; /* the kernel's software receive stamp */
    uint64_t t_mono_us;            /* the same instant on CLOCK_MONOTONIC */
    uint64_t t_user_mono_us;       /* when recvmsg returned it to us */
} ddyn_can_rx;

/* CLOCK_MONOTONIC in microseconds. */
uint64_t ddyn_can_mono_us(void);

/* Open a raw CAN socket on interface `ifname` with the given receive filters (NULL/0: receive
 * everything; `join` = all filters must match, CAN_RAW_JOIN_FILTERS, else any), error frames
 * of every class, receive timestamps and non-blocking I/O; CAN FD frames when want_fd.
 * Returns 0 or -errno (ENODEV: no such interface). */
int ddyn_can_open(ddyn_can_socket *s, const char *ifname, const struct can_filter *filters, size_t n_filters,
                  bool join, bool want_fd);

/* Send one classic frame (len <= 8) or, with CAN FD enabled, an FD frame (len <= 64).
 * Returns 0 or -errno (EAGAIN: the transmit queue is full; ENETDOWN: interface down). */
int ddyn_can_send(ddyn_can_socket *s, uint32_t id, bool extended, const uint8_t *data, uint8_t len);

/* Receive one frame, waiting at most until deadline_mono_us. Returns 1 (frame in *rx),
 * 0 (deadline reached, nothing received) or -errno (ENETDOWN / ENODEV: interface gone). */
int ddyn_can_receive(ddyn_can_socket *s, ddyn_can_rx *rx, uint64_t deadline_mono_us);

/* Whether the interface still exists and is up (SIOCGIFFLAGS). */
bool ddyn_can_link_up(const ddyn_can_socket *s);

void ddyn_can_close(ddyn_can_socket *s);

#ifdef __cplusplus
}
#endif

#endif /* DDYN_LINUX_CAN_SOCKET_H */
