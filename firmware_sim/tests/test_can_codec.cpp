#include <cstring>

#include "fsim/can_codec.hpp"
#include "test_util.hpp"

extern "C" {
#include "ddyn_can.h"
}

using fsim::CanFrame;
using fsim::CommandCheck;

TEST(CanCodec, ChecksumIsCrc8SaeJ1850) {
  // the CRC catalogue's check value of CRC-8/SAE-J1850 over "123456789" is 0x4B; here the first two
  // bytes are the identifier (little-endian) and the other seven the data bytes
  const uint8_t data[8] = {'3', '4', '5', '6', '7', '8', '9', 0};
  EXPECT_EQ(fsim::dbc_checksum(0x3231, data), 0x4B);
}

TEST(CanCodec, CommandRoundTripAndChecks) {
  fsim::CommandDecoder dec;
  fsim::DbwCommand cmd;
  CanFrame f = fsim::encode_command(0.42, -0.21, true, DDYN_CAN_DBW_COMMAND_MODE_AUTONOMOUS_CHOICE, 3);
  ASSERT_EQ(dec.decode(f, cmd), CommandCheck::kOk);
  EXPECT_NEAR(cmd.throttle, 0.42, 1e-4);
  EXPECT_NEAR(cmd.steering, -0.21, 1e-4);
  EXPECT_EQ(cmd.counter, 3);
  // the same counter again: a stuck sender
  EXPECT_EQ(dec.decode(f, cmd), CommandCheck::kRepeatedCounter);
  // braking: negative model throttle travels as Brake
  f = fsim::encode_command(-0.1, 0.0, true, DDYN_CAN_DBW_COMMAND_MODE_AUTONOMOUS_CHOICE, 5);
  ASSERT_EQ(dec.decode(f, cmd), CommandCheck::kOk);
  EXPECT_NEAR(cmd.throttle, -0.1, 1e-4);
  // one flipped bit anywhere is caught by the checksum
  for (int byte = 0; byte < 8; ++byte) {
    CanFrame g = fsim::encode_command(0.3, 0.1, true, DDYN_CAN_DBW_COMMAND_MODE_AUTONOMOUS_CHOICE, 6 + byte % 8);
    g.data[byte] ^= 0x10;
    EXPECT_EQ(dec.decode(g, cmd), CommandCheck::kBadChecksum) << byte;
  }
  // an older frame arriving late (counter behind the last good one) is never applied
  f = fsim::encode_command(0.9, 0.3, true, DDYN_CAN_DBW_COMMAND_MODE_AUTONOMOUS_CHOICE, 2);
  EXPECT_EQ(dec.decode(f, cmd), CommandCheck::kStaleCounter);
  f = fsim::encode_command(0.3, 0.1, false, DDYN_CAN_DBW_COMMAND_MODE_AUTONOMOUS_CHOICE, 9);
  EXPECT_EQ(dec.decode(f, cmd), CommandCheck::kNotEnabled);
  f = fsim::encode_command(0.3, 0.1, true, DDYN_CAN_DBW_COMMAND_MODE_AUTONOMOUS_CHOICE, 10);
  f.dlc = 6;
  EXPECT_EQ(dec.decode(f, cmd), CommandCheck::kWrongLength);
}

TEST(CanCodec, FeedbackFramesDecodeWithTheGeneratedCode) {
  fsim::FeedbackEncoder enc;
  CanFrame f = enc.gnss_position(1.2345, -0.5);
  ASSERT_EQ(f.id, DDYN_CAN_GNSS_POSITION_FRAME_ID);
  EXPECT_EQ(f.data[7], fsim::dbc_checksum(f.id, f.data.data()));
  ddyn_can_gnss_position_t p;
  ASSERT_EQ(ddyn_can_gnss_position_unpack(&p, f.data.data(), 8), 0);
  EXPECT_NEAR(ddyn_can_gnss_position_position_x_decode(p.position_x), 1.2345, 1e-3);
  EXPECT_NEAR(ddyn_can_gnss_position_position_y_decode(p.position_y), -0.5, 1e-3);
  EXPECT_EQ(p.counter, 0);
  f = enc.gnss_position(0.0, 0.0);
  ASSERT_EQ(ddyn_can_gnss_position_unpack(&p, f.data.data(), 8), 0);
  EXPECT_EQ(p.counter, 1);  // rolling counter per identifier
  f = enc.imu(0.7, -1.0, 2.5);
  ddyn_can_imu_t m;
  ASSERT_EQ(ddyn_can_imu_unpack(&m, f.data.data(), 8), 0);
  EXPECT_NEAR(ddyn_can_imu_yaw_rate_decode(m.yaw_rate), 0.7, 5e-4);
  EXPECT_NEAR(ddyn_can_imu_accel_y_decode(m.accel_y), 2.5, 5e-3);
  // heading wraps into the signal's range
  f = enc.gnss_heading(3.0 * M_PI / 2.0);
  ddyn_can_gnss_heading_t h;
  ASSERT_EQ(ddyn_can_gnss_heading_unpack(&h, f.data.data(), 8), 0);
  EXPECT_NEAR(ddyn_can_gnss_heading_heading_decode(h.heading), -M_PI / 2.0, 1e-4);
}
