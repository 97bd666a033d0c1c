// FrameAuth's freshness across a restart (docs/sil.md, frame authentication with a restarting plant)
#include <gtest/gtest.h>

#include <utility>
#include <vector>

#include "fsim/can_codec.hpp"
#include "fsim/frame_auth.hpp"

extern "C" {
#include "ddyn_can.h"
}

namespace {

using fsim::CanFrame;
using fsim::FrameAuth;

const uint8_t kKey[DDYN_DBW_AUTH_KEY_LEN] = {1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16,
                                              17, 18, 19, 20, 21, 22, 23, 24, 25, 26, 27, 28, 29, 30, 31, 32};
const uint32_t kSteering = 1u << DDYN_DBW_FRAME_STEERING;

CanFrame steering_frame(uint8_t k) {
  CanFrame f;
  f.id = DDYN_CAN_DBW_STEERING_FRAME_ID;
  f.dlc = 8;
  for (int i = 0; i < 7; ++i) f.data[i] = static_cast<uint8_t>(k + i);
  f.data[6] = static_cast<uint8_t>((f.data[6] & 0x0F) | ((k % 16) << 4));
  f.data[7] = fsim::dbc_checksum(f.id, f.data.data());
  return f;
}

// the receiver's verdict on frame f signed by `sender` at time t
FrameAuth::Verdict deliver(FrameAuth& sender, FrameAuth& receiver, const CanFrame& f, double t) {
  const CanFrame a = sender.sign(f);
  CanFrame out;
  EXPECT_EQ(receiver.on_frame(f, t, &out), FrameAuth::Verdict::kHeld);
  return receiver.on_frame(a, t + 1e-4, &out);
}

TEST(FrameAuth, ARestartedSenderResumesItsFreshnessAheadOfTheSnapshot) {
  FrameAuth plant(kKey, 0u), controller(kKey, kSteering);
  double t = 0.0;
  for (int k = 0; k < 20; ++k, t += 0.01) ASSERT_EQ(deliver(plant, controller, steering_frame(k), t), FrameAuth::Verdict::kAccepted);
  const FrameAuth::Freshness saved = plant.freshness();  // the snapshot
  EXPECT_EQ(saved.tx[DDYN_DBW_FRAME_STEERING], 20u);
  // the plant goes on after the snapshot, then dies
  for (int k = 20; k < 25; ++k, t += 0.01) ASSERT_EQ(deliver(plant, controller, steering_frame(k), t), FrameAuth::Verdict::kAccepted);
  // restarted without its freshness: from 0 again, refused as replays
  FrameAuth cold(kKey, 0u);
  EXPECT_EQ(deliver(cold, controller, steering_frame(30), t += 0.01), FrameAuth::Verdict::kReplay);
  // restarted with it, as exactly saved: the values sent after the snapshot come again, refused
  FrameAuth exact(kKey, 0u);
  exact.restore_freshness(saved, 0);
  EXPECT_EQ(deliver(exact, controller, steering_frame(31), t += 0.01), FrameAuth::Verdict::kReplay);
  // with the margin: accepted, and the next ones too
  FrameAuth warm(kKey, 0u);
  warm.restore_freshness(saved, 1024);
  EXPECT_EQ(warm.freshness().tx[DDYN_DBW_FRAME_STEERING], 20u + 1024u);
  for (int k = 32; k < 40; ++k) EXPECT_EQ(deliver(warm, controller, steering_frame(k), t += 0.01), FrameAuth::Verdict::kAccepted) << k;
}

TEST(FrameAuth, ARestartedReceiverKeepsRefusingWhatItAcceptedBeforeTheSnapshot) {
  FrameAuth controller(kKey, 0u), plant(kKey, kSteering);
  double t = 0.0;
  std::vector<std::pair<CanFrame, CanFrame>> recorded;  // an eavesdropper's recording
  for (int k = 0; k < 10; ++k, t += 0.01) {
    const CanFrame f = steering_frame(k), a = controller.sign(f);
    recorded.push_back({f, a});
    CanFrame out;
    ASSERT_EQ(plant.on_frame(f, t, &out), FrameAuth::Verdict::kHeld);
    ASSERT_EQ(plant.on_frame(a, t + 1e-4, &out), FrameAuth::Verdict::kAccepted);
  }
  const FrameAuth::Freshness saved = plant.freshness();
  EXPECT_TRUE(saved.rx_valid[DDYN_DBW_FRAME_STEERING]);
  EXPECT_EQ(saved.rx[DDYN_DBW_FRAME_STEERING], 9u);
  FrameAuth restarted(kKey, kSteering);
  restarted.restore_freshness(saved, 1024);
  CanFrame out;
  // a recorded command replayed after the restart: refused
  ASSERT_EQ(restarted.on_frame(recorded[3].first, t, &out), FrameAuth::Verdict::kHeld);
  EXPECT_EQ(restarted.on_frame(recorded[3].second, t + 1e-4, &out), FrameAuth::Verdict::kReplay);
  // the controller kept counting: its next command is accepted
  t += 0.01;
  const CanFrame f = steering_frame(10), a = controller.sign(f);
  ASSERT_EQ(restarted.on_frame(f, t, &out), FrameAuth::Verdict::kHeld);
  EXPECT_EQ(restarted.on_frame(a, t + 1e-4, &out), FrameAuth::Verdict::kAccepted);
  // a cold receiver would have taken the recorded one (trust on first use)
  FrameAuth cold(kKey, kSteering);
  ASSERT_EQ(cold.on_frame(recorded[3].first, t, &out), FrameAuth::Verdict::kHeld);
  EXPECT_EQ(cold.on_frame(recorded[3].second, t + 1e-4, &out), FrameAuth::Verdict::kAccepted);
}

}  // namespace
