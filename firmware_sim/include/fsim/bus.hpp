// fsim/bus.hpp - where the plant's CAN frames go: a Linux SocketCAN interface (vcan0 in SIL) or,
// for in-process tests, a pair of memory queues.
#pragma once

#include <deque>
#include <memory>
#include <string>

#include "fsim/can_codec.hpp"

namespace fsim {

class Bus {
 public:
  virtual ~Bus() = default;
  virtual void send(const CanFrame& f) = 0;
  // next frame if one arrives within timeout_us (0: poll); false on timeout
  virtual bool receive(CanFrame& f, long timeout_us) = 0;
};

// Raw SocketCAN socket bound to one interface; own frames are not looped back to it.
// Throws std::runtime_error naming the interface when it cannot be opened.
std::unique_ptr<Bus> open_socketcan(const std::string& interface);

// Two ends of an in-memory link: what one end sends, the other receives.
struct MemoryLink {
  std::deque<CanFrame> a_to_b, b_to_a;
};
class MemoryBus : public Bus {
 public:
  MemoryBus(MemoryLink& link, bool side_a) : link_(link), a_(side_a) {}
  void send(const CanFrame& f) override { (a_ ? link_.a_to_b : link_.b_to_a).push_back(f); }
  bool receive(CanFrame& f, long) override {
    auto& q = a_ ? link_.b_to_a : link_.a_to_b;
    if (q.empty()) return false;
    f = q.front();
    q.pop_front();
    return true;
  }

 private:
  MemoryLink& link_;
  bool a_;
};

}  // namespace fsim
