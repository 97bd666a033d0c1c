#include "fsim/can_codec.hpp"

#include <algorithm>
#include <cmath>

extern "C" {
#include "ddyn_can.h"
}

namespace fsim {
namespace {

// clamp to the DBC's physical range before the generated encoder (which does not saturate)
double clampv(double v, double lo, double hi) { return std::isfinite(v) ? std::clamp(v, lo, hi) : 0.0; }

double wrap_pi(double a) {
  a = std::fmod(a + M_PI, 2.0 * M_PI);
  if (a < 0.0) a += 2.0 * M_PI;
  return a - M_PI;
}

template <typename Msg, typename Pack>
CanFrame pack(uint32_t id, Msg& m, Pack pack_fn, uint8_t& counter) {
  CanFrame f;
  f.id = id;
  f.dlc = 8;
  m.counter = counter;
  counter = static_cast<uint8_t>((counter + 1) & 0x0F);
  m.checksum = 0;
  pack_fn(f.data.data(), &m, f.data.size());
  seal(f);
  return f;
}

}  // namespace

uint8_t dbc_checksum(uint32_t id, const uint8_t* data) {
  uint8_t crc = 0xFF;
  const uint8_t bytes[9] = {static_cast<uint8_t>(id & 0xFF), static_cast<uint8_t>((id >> 8) & 0xFF),
                            data[0], data[1], data[2], data[3], data[4], data[5], data[6]};
  for (uint8_t b : bytes) {
    crc ^= b;
    for (int i = 0; i < 8; ++i) crc = (crc & 0x80) ? static_cast<uint8_t>((crc << 1) ^ 0x1D) : static_cast<uint8_t>(crc << 1);
  }
  return static_cast<uint8_t>(crc ^ 0xFF);
}

void seal(CanFrame& f) { f.data[7] = dbc_checksum(f.id, f.data.data()); }

const char* command_check_name(CommandCheck c) {
  switch (c) {
    case CommandCheck::kOk: return "ok";
    case CommandCheck::kWrongLength: return "wrong_length";
    case CommandCheck::kBadChecksum: return "bad_checksum";
    case CommandCheck::kRepeatedCounter: return "repeated_counter";
    case CommandCheck::kOutOfRange: return "out_of_range";
    case CommandCheck::kNotEnabled: return "not_enabled";
    case CommandCheck::kStaleCounter: return "stale_counter";
  }
  return "unknown";
}

CommandCheck CommandDecoder::decode(const CanFrame& f, DbwCommand& out) {
  if (f.id != DDYN_CAN_DBW_COMMAND_FRAME_ID || f.dlc != DDYN_CAN_DBW_COMMAND_LENGTH) return CommandCheck::kWrongLength;
  if (dbc_checksum(f.id, f.data.data()) != f.data[7]) return CommandCheck::kBadChecksum;
  ddyn_can_dbw_command_t m;
  if (ddyn_can_dbw_command_unpack(&m, f.data.data(), f.dlc) != 0) return CommandCheck::kWrongLength;
  if (last_counter_ >= 0) {
    // counters move forward by 1 (mod 16); a step of 1..8 is new (a skip means lost frames), 0 is a
    // repeat (stuck sender) and 9..15 is an older frame arriving late: neither may be applied
    const int step = (m.counter - last_counter_ + 16) % 16;
    if (step == 0) return CommandCheck::kRepeatedCounter;
    if (step > 8) return CommandCheck::kStaleCounter;
  }
  last_counter_ = m.counter;
  if (!ddyn_can_dbw_command_throttle_is_in_range(m.throttle) || !ddyn_can_dbw_command_brake_is_in_range(m.brake) ||
      !ddyn_can_dbw_command_steering_angle_is_in_range(m.steering_angle) ||
      !ddyn_can_dbw_command_mode_is_in_range(m.mode))
    return CommandCheck::kOutOfRange;
  out.throttle = ddyn_can_dbw_command_throttle_decode(m.throttle) - ddyn_can_dbw_command_brake_decode(m.brake);
  out.steering = ddyn_can_dbw_command_steering_angle_decode(m.steering_angle);
  out.enable = m.enable != 0;
  out.mode = m.mode;
  out.counter = m.counter;
  if (!out.enable || out.mode != DDYN_CAN_DBW_COMMAND_MODE_AUTONOMOUS_CHOICE) return CommandCheck::kNotEnabled;
  return CommandCheck::kOk;
}

CanFrame FeedbackEncoder::steering(double angle, double rate) {
  ddyn_can_dbw_steering_t m{};
  m.steering_angle = ddyn_can_dbw_steering_steering_angle_encode(clampv(angle, -0.6, 0.6));
  m.steering_rate = ddyn_can_dbw_steering_steering_rate_encode(clampv(rate, -10.0, 10.0));
  return pack(DDYN_CAN_DBW_STEERING_FRAME_ID, m, ddyn_can_dbw_steering_pack, counters[0]);
}

CanFrame FeedbackEncoder::status(double throttle, int mode, bool enabled, uint8_t faults) {
  ddyn_can_dbw_status_t m{};
  m.throttle_pedal = ddyn_can_dbw_status_throttle_pedal_encode(clampv(throttle, 0.0, 1.0));
  m.brake_pedal = ddyn_can_dbw_status_brake_pedal_encode(clampv(-throttle, 0.0, 1.0));
  m.mode = static_cast<uint8_t>(mode);
  m.enabled = enabled ? 1 : 0;
  m.faults = static_cast<uint8_t>(faults & 0x3F);
  return pack(DDYN_CAN_DBW_STATUS_FRAME_ID, m, ddyn_can_dbw_status_pack, counters[1]);
}

CanFrame FeedbackEncoder::wheel_speeds(double front, double rear) {
  ddyn_can_dbw_wheel_speeds_t m{};
  m.wheel_speed_front = ddyn_can_dbw_wheel_speeds_wheel_speed_front_encode(clampv(front, -100.0, 100.0));
  m.wheel_speed_rear = ddyn_can_dbw_wheel_speeds_wheel_speed_rear_encode(clampv(rear, -100.0, 100.0));
  return pack(DDYN_CAN_DBW_WHEEL_SPEEDS_FRAME_ID, m, ddyn_can_dbw_wheel_speeds_pack, counters[2]);
}

CanFrame FeedbackEncoder::imu(double yaw_rate, double ax, double ay) {
  ddyn_can_imu_t m{};
  m.yaw_rate = ddyn_can_imu_yaw_rate_encode(clampv(yaw_rate, -16.0, 16.0));
  m.accel_x = ddyn_can_imu_accel_x_encode(clampv(ax, -160.0, 160.0));
  m.accel_y = ddyn_can_imu_accel_y_encode(clampv(ay, -160.0, 160.0));
  return pack(DDYN_CAN_IMU_FRAME_ID, m, ddyn_can_imu_pack, counters[3]);
}

CanFrame FeedbackEncoder::gnss_position(double x, double y) {
  ddyn_can_gnss_position_t m{};
  m.position_x = ddyn_can_gnss_position_position_x_encode(clampv(x, -30000.0, 30000.0));
  m.position_y = ddyn_can_gnss_position_position_y_encode(clampv(y, -30000.0, 30000.0));
  return pack(DDYN_CAN_GNSS_POSITION_FRAME_ID, m, ddyn_can_gnss_position_pack, counters[4]);
}

CanFrame FeedbackEncoder::gnss_heading(double yaw) {
  ddyn_can_gnss_heading_t m{};
  m.heading = ddyn_can_gnss_heading_heading_encode(clampv(wrap_pi(yaw), -3.1416, 3.1416));
  m.fix_type = DDYN_CAN_GNSS_HEADING_FIX_TYPE_RTK_FIXED_CHOICE;
  return pack(DDYN_CAN_GNSS_HEADING_FRAME_ID, m, ddyn_can_gnss_heading_pack, counters[5]);
}

CanFrame encode_command(double throttle, double steering, bool enable, int mode, int counter) {
  ddyn_can_dbw_command_t m{};
  m.throttle = ddyn_can_dbw_command_throttle_encode(clampv(throttle, 0.0, 1.0));
  m.brake = ddyn_can_dbw_command_brake_encode(clampv(-throttle, 0.0, 1.0));
  m.steering_angle = ddyn_can_dbw_command_steering_angle_encode(clampv(steering, -0.6, 0.6));
  m.enable = enable ? 1 : 0;
  m.mode = static_cast<uint8_t>(mode);
  uint8_t c = static_cast<uint8_t>(counter & 0x0F);
  return pack(DDYN_CAN_DBW_COMMAND_FRAME_ID, m, ddyn_can_dbw_command_pack, c);
}

}  // namespace fsim
