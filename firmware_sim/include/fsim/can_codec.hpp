// fsim/can_codec.hpp - the DBW unit's and the sensors' side of the CAN protocol (can/ddyn_dbw.dbc):
// frames packed and unpacked with the cantools-generated C (c_src/generated/can), plus what the
// DBC's comment asks of every frame: a 4-bit rolling counter and a CRC-8/SAE-J1850 checksum over
// the identifier (two little-endian bytes) and data bytes 0-6.
//
// This is the plant's own implementation of the frame checks (the car-side one is c_src's DBW
// logic): two independent implementations that must agree, which the tests check.
#pragma once

#include <array>
#include <cstdint>

namespace fsim {

struct CanFrame {
  uint32_t id = 0;
  uint8_t dlc = 0;
  std::array<uint8_t, 8> data{};
};

// CRC-8/SAE-J1850 (poly 0x1D, init 0xFF, xorout 0xFF) over id (2 bytes LE) + data[0..6]
uint8_t dbc_checksum(uint32_t id, const uint8_t* data);
void seal(CanFrame& f);  // write the checksum into byte 7

enum class CommandCheck { kOk, kWrongLength, kBadChecksum, kRepeatedCounter, kOutOfRange, kNotEnabled, kStaleCounter };
const char* command_check_name(CommandCheck c);

struct DbwCommand {
  double throttle = 0.0;  // the model's throttle: Throttle - Brake
  double steering = 0.0;  // rad
  bool enable = false;
  int mode = 0;
  int counter = 0;
};

// DBW-unit side: checks of a received DBW_Command frame. A repeated counter means a stuck sender
// (rejected); a counter up to 8 behind means an older frame arriving late (rejected); a skipped
// counter means lost frames (accepted).
class CommandDecoder {
 public:
  CommandCheck decode(const CanFrame& f, DbwCommand& out);

 private:
  int last_counter_ = -1;
};

// Sensor and feedback frames, each with its own rolling counter.
struct FeedbackEncoder {
  CanFrame steering(double angle, double rate);
  CanFrame status(double throttle, int mode, bool enabled, uint8_t faults);
  CanFrame wheel_speeds(double front, double rear);
  CanFrame imu(double yaw_rate, double ax, double ay);
  CanFrame gnss_position(double x, double y);
  CanFrame gnss_heading(double yaw);
  std::array<uint8_t, 7> counters{};
};

// Controller side helper for tests and tools: a DBW_Command frame.
CanFrame encode_command(double throttle, double steering, bool enable, int mode, int counter);

}  // namespace fsim
