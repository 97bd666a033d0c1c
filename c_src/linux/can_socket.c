/*
 * SocketCAN raw-socket transport (can_socket.h). Linux only: ppoll, SO_TIMESTAMPING and the
 * ifreq ioctls need the GNU/Linux interfaces, hence _GNU_SOURCE in this file alone.
 */
#define _GNU_SOURCE
#include "can_socket.h"

#include <errno.h>
#include <fcntl.h>
#include <net/if.h>
#include <poll.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include <linux/can/error.h>
#include <linux/can/raw.h>
#include <linux/errqueue.h>
#include <linux/net_tstamp.h>

#ifndef SO_TIMESTAMPING
#define SO_TIMESTAMPING 37
#endif
#ifndef SCM_TIMESTAMPING
#define SCM_TIMESTAMPING SO_TIMESTAMPING
#endif

static uint64_t ts_us(const struct timespec *t)
{
    return (uint64_t)t->tv_sec * 1000000u + (uint64_t)t->tv_nsec / 1000u;
}

static uint64_t clock_us(clockid_t id)
{
    struct timespec t;
    if (clock_gettime(id, &t) != 0) {
        return 0u;
    }
    return ts_us(&t);
}

uint64_t ddyn_can_mono_us(void) { return clock_us(CLOCK_MONOTONIC); }

static int fail_close(ddyn_can_socket *s, int err)
{
    close(s->fd);
    s->fd = -1;
    return -err;
}

int ddyn_can_open(ddyn_can_socket *s, const char *ifname, const struct can_filter *filters, size_t n_filters,
                  bool join, bool want_fd)
{
    struct ifreq ifr;
    struct sockaddr_can addr;
    const can_err_mask_t err_mask = CAN_ERR_MASK;
    const int on = 1;
    const int ts_flags = SOF_TIMESTAMPING_RX_SOFTWARE | SOF_TIMESTAMPING_SOFTWARE;
    int flags;
    if (s == NULL || ifname == NULL || strlen(ifname) >= sizeof(ifr.ifr_name) || (filters == NULL && n_filters > 0)) {
        return -EINVAL;
    }
    memset(s, 0, sizeof(*s));
    s->fd = socket(PF_CAN, SOCK_RAW, CAN_RAW);
    if (s->fd < 0) {
        return -errno;
    }
    memset(&ifr, 0, sizeof(ifr));
    strncpy(ifr.ifr_name, ifname, sizeof(ifr.ifr_name) - 1u);
    if (ioctl(s->fd, SIOCGIFINDEX, &ifr) != 0) {
        return fail_close(s, errno);
    }
    s->ifindex = ifr.ifr_ifindex;
    strncpy(s->ifname, ifname, sizeof(s->ifname) - 1u);
    /* filters before bind, so that no unfiltered frame is ever queued; without filters the
     * socket keeps the kernel's default, which receives everything (an empty filter list would
     * receive nothing) */
    if (n_filters > 0 &&
        setsockopt(s->fd, SOL_CAN_RAW, CAN_RAW_FILTER, filters, (socklen_t)(n_filters * sizeof(*filters))) != 0) {
        return fail_close(s, errno);
    }
    if (join && setsockopt(s->fd, SOL_CAN_RAW, CAN_RAW_JOIN_FILTERS, &on, sizeof(on)) != 0) {
        return fail_close(s, errno);
    }
    if (setsockopt(s->fd, SOL_CAN_RAW, CAN_RAW_ERR_FILTER, &err_mask, sizeof(err_mask)) != 0) {
        return fail_close(s, errno);
    }
    if (want_fd) {
        if (setsockopt(s->fd, SOL_CAN_RAW, CAN_RAW_FD_FRAMES, &on, sizeof(on)) != 0) {
            return fail_close(s, errno);
        }
        s->fd_frames = true;
    }
    if (setsockopt(s->fd, SOL_SOCKET, SO_TIMESTAMPING, &ts_flags, sizeof(ts_flags)) != 0) {
        return fail_close(s, errno);
    }
    (void)setsockopt(s->fd, SOL_SOCKET, SO_RXQ_OVFL, &on, sizeof(on)); /* drop counter: optional */
    flags = fcntl(s->fd, F_GETFL, 0);
    if (flags < 0 || fcntl(s->fd, F_SETFL, flags | O_NONBLOCK) != 0) {
        return fail_close(s, errno);
    }
    memset(&addr, 0, sizeof(addr));
    addr.can_family = AF_CAN;
    addr.can_ifindex = s->ifindex;
    if (bind(s->fd, (struct sockaddr *)&addr, sizeof(addr)) != 0) {
        return fail_close(s, errno);
    }
    return 0;
}

int ddyn_can_send(ddyn_can_socket *s, uint32_t id, bool extended, const uint8_t *data, uint8_t len)
{
    struct canfd_frame f;
    size_t size;
    ssize_t n;
    if (s == NULL || s->fd < 0 || (data == NULL && len > 0) || len > (s->fd_frames ? 64u : 8u) ||
        id > (extended ? CAN_EFF_MASK : CAN_SFF_MASK)) {
        return -EINVAL;
    }
    memset(&f, 0, sizeof(f));
    f.can_id = id | (extended ? CAN_EFF_FLAG : 0u);
    f.len = len;
    if (len > 0) {
        memcpy(f.data, data, len);
    }
    size = len > 8u ? CANFD_MTU : CAN_MTU; /* struct can_frame is the first CAN_MTU bytes */
    n = write(s->fd, &f, size);
    if (n < 0) {
        return -errno;
    }
    if ((size_t)n != size) {
        return -EIO;
    }
    s->tx_frames++;
    return 0;
}

/* Pull the kernel stamp and the drop counter out of the control messages. */
static void read_cmsgs(ddyn_can_socket *s, struct msghdr *msg, ddyn_can_rx *rx)
{
    struct cmsghdr *c;
    unsigned guard = 0;
    for (c = CMSG_FIRSTHDR(msg); c != NULL && guard < 8u; c = CMSG_NXTHDR(msg, c), ++guard) {
        if (c->cmsg_level != SOL_SOCKET) {
            continue;
        }
        if (c->cmsg_type == SCM_TIMESTAMPING) {
            struct timespec ts[3];
            memcpy(ts, CMSG_DATA(c), sizeof(ts));
            rx->t_kernel_realtime_us = ts_us(&ts[0]); /* [0]: software stamp */
        } else if (c->cmsg_type == SO_RXQ_OVFL) {
            uint32_t dropped;
            memcpy(&dropped, CMSG_DATA(c), sizeof(dropped));
            s->rx_dropped = dropped;
        }
    }
}

int ddyn_can_receive(ddyn_can_socket *s, ddyn_can_rx *rx, uint64_t deadline_mono_us)
{
    struct canfd_frame f;
    struct iovec iov;
    struct msghdr msg;
    union {
        char buf[CMSG_SPACE(3 * sizeof(struct timespec)) + CMSG_SPACE(sizeof(uint32_t))];
        struct cmsghdr align;
    } ctrl;
    ssize_t n;
    unsigned attempt;
    if (s == NULL || rx == NULL || s->fd < 0) {
        return -EINVAL;
    }
    /* two attempts: read what is queued; if nothing, wait once until the deadline and read again */
    for (attempt = 0; attempt < 2u; ++attempt) {
        memset(&msg, 0, sizeof(msg));
        iov.iov_base = &f;
        iov.iov_len = sizeof(f);
        msg.msg_iov = &iov;
        msg.msg_iovlen = 1;
        msg.msg_control = ctrl.buf;
        msg.msg_controllen = sizeof(ctrl.buf);
        n = recvmsg(s->fd, &msg, MSG_DONTWAIT);
        if (n >= 0) {
            break;
        }
        if (errno != EAGAIN && errno != EWOULDBLOCK) {
            return -errno;
        }
        if (attempt == 0u) {
            uint64_t now = ddyn_can_mono_us();
            struct pollfd p;
            struct timespec wait;
            int pr;
            if (now >= deadline_mono_us) {
                return 0;
            }
            wait.tv_sec = (time_t)((deadline_mono_us - now) / 1000000u);
            wait.tv_nsec = (long)(((deadline_mono_us - now) % 1000000u) * 1000u);
            p.fd = s->fd;
            p.events = POLLIN;
            p.revents = 0;
            pr = ppoll(&p, 1, &wait, NULL);
            if (pr < 0) {
                return errno == EINTR ? 0 : -errno;
            }
            if (pr == 0) {
                return 0;
            }
            /* POLLERR: the socket's pending error (ENETDOWN, ENODEV) comes out of recvmsg */
        } else {
            return 0;
        }
    }
    memset(rx, 0, sizeof(*rx));
    rx->t_user_mono_us = ddyn_can_mono_us();
    if (n != (ssize_t)CAN_MTU && n != (ssize_t)CANFD_MTU) {
        return -EIO;
    }
    read_cmsgs(s, &msg, rx);
    if (rx->t_kernel_realtime_us != 0u) {
        /* move the stamp to the monotonic clock with the offset between the clocks now */
        uint64_t real_now = clock_us(CLOCK_REALTIME);
        uint64_t age = real_now > rx->t_kernel_realtime_us ? real_now - rx->t_kernel_realtime_us : 0u;
        rx->t_mono_us = rx->t_user_mono_us > age ? rx->t_user_mono_us - age : 0u;
    } else {
        rx->t_mono_us = rx->t_user_mono_us;
    }
    rx->fd = n == (ssize_t)CANFD_MTU;
    rx->len = f.len > (rx->fd ? 64u : 8u) ? (rx->fd ? 64u : 8u) : f.len;
    memcpy(rx->data, f.data, rx->len);
    rx->extended = (f.can_id & CAN_EFF_FLAG) != 0u;
    rx->rtr = (f.can_id & CAN_RTR_FLAG) != 0u;
    rx->error = (f.can_id & CAN_ERR_FLAG) != 0u;
    if (rx->error) {
        rx->err_class = f.can_id & CAN_ERR_MASK;
        rx->id = 0u;
        s->rx_error_frames++;
    } else {
        rx->id = f.can_id & (rx->extended ? CAN_EFF_MASK : CAN_SFF_MASK);
        s->rx_frames++;
    }
    return 1;
}

bool ddyn_can_link_up(const ddyn_can_socket *s)
{
    struct ifreq ifr;
    if (s == NULL || s->fd < 0) {
        return false;
    }
    memset(&ifr, 0, sizeof(ifr));
    /* by index: a new interface with the old name is not the one we are bound to */
    ifr.ifr_ifindex = s->ifindex;
    if (ioctl(s->fd, SIOCGIFNAME, &ifr) != 0) {
        return false;
    }
    if (ioctl(s->fd, SIOCGIFFLAGS, &ifr) != 0) {
        return false;
    }
    return (ifr.ifr_flags & IFF_UP) != 0;
}

void ddyn_can_close(ddyn_can_socket *s)
{
    if (s != NULL && s->fd >= 0) {
        close(s->fd);
        s->fd = -1;
    }
}
