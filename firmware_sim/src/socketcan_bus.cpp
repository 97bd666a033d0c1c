// Linux SocketCAN transport of the plant (raw CAN_RAW socket).
#include <linux/can.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <stdexcept>

#include "fsim/bus.hpp"

namespace fsim {
namespace {

class SocketCanBus : public Bus {
 public:
  explicit SocketCanBus(const std::string& ifname) {
    fd_ = ::socket(PF_CAN, SOCK_RAW, CAN_RAW);
    if (fd_ < 0) throw std::runtime_error("socketcan: socket(): " + std::string(std::strerror(errno)));
    const unsigned idx = ::if_nametoindex(ifname.c_str());
    if (idx == 0) {
      ::close(fd_);
      throw std::runtime_error("socketcan: no CAN interface '" + ifname + "' (on a host: ip link add dev " + ifname +
                               " type vcan && ip link set up " + ifname + ")");
    }
    sockaddr_can addr{};
    addr.can_family = AF_CAN;
    addr.can_ifindex = static_cast<int>(idx);
    if (::bind(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) < 0) {
      const std::string err = std::strerror(errno);
      ::close(fd_);
      throw std::runtime_error("socketcan: bind(" + ifname + "): " + err);
    }
    // a process does not need its own frames back
    int recv_own = 0;
    ::setsockopt(fd_, SOL_CAN_RAW, CAN_RAW_RECV_OWN_MSGS, &recv_own, sizeof recv_own);
  }
  ~SocketCanBus() override { ::close(fd_); }

  void send(const CanFrame& f) override {
    can_frame cf{};
    cf.can_id = f.id;
    cf.can_dlc = f.dlc;
    std::memcpy(cf.data, f.data.data(), 8);
    // a full queue on vcan drops the frame: like a busy bus, counted by the caller's metrics
    if (::write(fd_, &cf, sizeof cf) != static_cast<ssize_t>(sizeof cf)) ++send_errors_;
  }

  bool receive(CanFrame& f, long timeout_us) override {
    pollfd p{fd_, POLLIN, 0};
    const int ms = timeout_us <= 0 ? 0 : static_cast<int>((timeout_us + 999) / 1000);
    if (::poll(&p, 1, ms) <= 0) return false;
    can_frame cf{};
    if (::read(fd_, &cf, sizeof cf) != static_cast<ssize_t>(sizeof cf)) return false;
    f.id = cf.can_id & CAN_SFF_MASK;
    f.dlc = cf.can_dlc;
    std::memcpy(f.data.data(), cf.data, 8);
    return true;
  }

 private:
  int fd_ = -1;
  long send_errors_ = 0;
};

}  // namespace

std::unique_ptr<Bus> open_socketcan(const std::string& interface) {
  return std::make_unique<SocketCanBus>(interface);
}

}  // namespace fsim
