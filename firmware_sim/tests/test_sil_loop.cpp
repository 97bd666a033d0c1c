#include <cmath>

#include "sil_loop.hpp"

// Frames of the plant decode in the controller's node and the node's commands pass the plant's
// DBW checks: the two independent implementations of the protocol agree, and the controller's
// filter follows the car.
TEST(SilLoop, FramesFlowBothWaysAndTheFilterFollowsTheCar) {
  FSIM_REQUIRE_TRACKS();
  auto cfg = fsim_test::orca_sil_config();
  cfg.max_time = 2.0;
  fsim_test::SilLoop loop(cfg);
  double worst = 0.0;
  while (loop.step()) {
    if (loop.periods > 10) {  // after the filter's first readings
      const fsim::State& x = loop.app->plant().state();
      const double* est = loop.node->ctl.ekf.x;
      worst = std::max(worst, std::hypot(est[0] - x[fsim::kX], est[1] - x[fsim::kY]));
    }
  }
  const auto m = loop.app->metrics();
  EXPECT_EQ(loop.node->checksum, 0);
  EXPECT_EQ(loop.node->range, 0);
  EXPECT_EQ(loop.node->frames_lost, 0);
  EXPECT_GT(loop.node->frames_ok, 500);
  EXPECT_NEAR(loop.periods, 100, 2);  // 50 Hz for 2 s
  EXPECT_GE(m["dbw"]["commands_ok"].get<long>(), loop.periods - 1);
  EXPECT_EQ(m["dbw"]["rejected"]["bad_checksum"].get<long>(), 0);
  EXPECT_EQ(m["dbw"]["rejected"]["repeated_counter"].get<long>(), 0);
  EXPECT_LT(worst, 0.03);  // GNSS noise 2 mm; the filter's model is Euler at crawling speed
}

// Damaged checksums on the bus are caught on both sides and counted; nothing damaged is used.
TEST(SilLoop, CorruptedChecksumsAreRejectedOnBothSides) {
  FSIM_REQUIRE_TRACKS();
  auto cfg = fsim_test::orca_sil_config();
  cfg.max_time = 2.0;
  cfg.faults.corrupt = 0.05;
  fsim_test::SilLoop loop(cfg);
  while (loop.step()) {
  }
  const auto m = loop.app->metrics();
  const long tx_bad = m["bus"]["tx_corrupted"], rx_bad = m["bus"]["rx_corrupted"];
  EXPECT_GT(tx_bad, 10);
  EXPECT_EQ(loop.node->checksum, tx_bad);
  EXPECT_EQ(m["dbw"]["rejected"]["bad_checksum"].get<long>(), rx_bad);
}

// The controller process dies mid-run: the DBW unit's watchdog brings the car to a stop within its
// deadline of the last command.
TEST(SilLoop, ControllerKilledMidRunEndsInTheSafeStop) {
  FSIM_REQUIRE_TRACKS();
  auto cfg = fsim_test::orca_sil_config();
  cfg.max_time = 5.0;
  fsim_test::SilLoop loop(cfg);
  while (loop.step()) {
    if (loop.app->plant().time() >= 1.0) loop.controller_alive = false;
  }
  const auto m = loop.app->metrics();
  EXPECT_EQ(m["dbw"]["trips"].get<int>(), 1);
  EXPECT_LE(m["dbw"]["first_trip_latency"].get<double>(), cfg.dbw.deadline + cfg.substep + 1e-9);
  EXPECT_GT(m["dbw"]["first_trip_time"].get<double>(), 1.0);
  EXPECT_EQ(loop.app->end_reason(), "safe_stop");
  EXPECT_DOUBLE_EQ(loop.app->plant().state()[fsim::kVx], 0.0);
}

// Frames held back up to two control periods arrive out of order: the late ones are refused on
// both sides (never applied over newer data), and the DBW unit keeps receiving valid commands.
TEST(SilLoop, DelayedFramesArriveLateAndAreNotApplied) {
  FSIM_REQUIRE_TRACKS();
  auto cfg = fsim_test::orca_sil_config();
  cfg.max_time = 3.0;
  cfg.faults.delay_max = 0.04;
  fsim_test::SilLoop loop(cfg);
  while (loop.step()) {
  }
  const auto m = loop.app->metrics();
  EXPECT_GT(loop.node->late, 10);
  EXPECT_GT(m["dbw"]["rejected"]["stale_counter"].get<long>(), 0);
  EXPECT_GT(m["dbw"]["commands_ok"].get<long>(), 50);
  EXPECT_EQ(m["dbw"]["trips"].get<int>(), 0);  // 80 ms deadline: a 40 ms delay never trips it
}

// A lost position frame still gets its control period: the next position frame's period first runs
// the lost one without the position reading (its command is not sent: the actuators held theirs,
// and the filter predicts it so), then its own with the reading.
TEST(SilLoop, LostPositionFramesAreCaughtUp) {
  FSIM_REQUIRE_TRACKS();
  fsim_test::SilLoop loop(fsim_test::orca_sil_config());
  fsim::FeedbackEncoder enc;
  ddyn_sil_node* node = loop.node.get();
  fsim::CanFrame f = enc.gnss_position(1.2, 0.9);
  EXPECT_EQ(ddyn_sil_node_on_frame(node, f.id, f.data.data(), f.dlc), 1);
  ddyn_sil_period per;
  ddyn_sil_node_period(node, &per);
  const uint8_t counter0 = per.data[6] >> 4;
  enc.gnss_position(1.21, 0.9);  // lost on the bus: its counter is used up
  f = enc.gnss_position(1.22, 0.9);
  EXPECT_EQ(ddyn_sil_node_on_frame(node, f.id, f.data.data(), f.dlc), 1);  // one command to send
  EXPECT_EQ(node->frames_lost, 1);
  EXPECT_EQ(node->catch_up, 1);
  ddyn_sil_node_period(node, &per);  // the lost frame's period, then this one
  EXPECT_EQ(node->catch_up, 0);
  EXPECT_EQ(node->in.reading[DDYN_MEAS_GNSS_POSITION].valid, 0);  // fused in its own period
  EXPECT_EQ(node->steps, 3);
  EXPECT_EQ(per.data[6] >> 4, (counter0 + 1) % 16);  // the caught-up period sent no frame
  EXPECT_EQ(node->ctl.x_hist_n, 3);                  // but the filter ran it
}

// The log's raw readings: a period records the IMU, the steering feedback and the GNSS it fused, and NaN for
// a sensor whose frame did not come in it (the node clears its readings after each step, so the copy in the
// period is what the log can read).
TEST(SilLoop, APeriodCarriesTheRawReadingsItFused) {
  FSIM_REQUIRE_TRACKS();
  fsim_test::SilLoop loop(fsim_test::orca_sil_config());
  fsim::FeedbackEncoder enc;
  ddyn_sil_node* node = loop.node.get();
  fsim::CanFrame f = enc.imu(0.123, 0.5, -2.25);
  EXPECT_EQ(ddyn_sil_node_on_frame(node, f.id, f.data.data(), f.dlc), 0);
  f = enc.steering(-0.05, 0.0);
  EXPECT_EQ(ddyn_sil_node_on_frame(node, f.id, f.data.data(), f.dlc), 0);
  f = enc.gnss_heading(0.75);
  EXPECT_EQ(ddyn_sil_node_on_frame(node, f.id, f.data.data(), f.dlc), 0);
  f = enc.gnss_position(1.2, 0.9);
  EXPECT_EQ(ddyn_sil_node_on_frame(node, f.id, f.data.data(), f.dlc), 1);
  ddyn_sil_period per;
  ddyn_sil_node_period(node, &per);
  double raw[DDYN_SIL_LOG_READINGS];
  ddyn_sil_log_readings(&per, raw);
  EXPECT_NEAR(raw[0], 0.123, 1e-3);   // the frame's resolution
  EXPECT_NEAR(raw[1], -0.05, 1e-3);
  EXPECT_NEAR(raw[2], 0.5, 0.005);     // AccelX, AccelY: 0.005 m/s^2 per bit
  EXPECT_NEAR(raw[3], -2.25, 0.005);
  EXPECT_NEAR(raw[4], 1.2, 0.01);      // the GNSS position and heading as measured, not the estimate
  EXPECT_NEAR(raw[5], 0.9, 0.01);
  EXPECT_NEAR(raw[6], 0.75, 1e-3);
  EXPECT_EQ(node->in.reading[DDYN_MEAS_YAW_RATE].valid, 0);  // the node's own copy is cleared
  f = enc.gnss_position(1.21, 0.9);  // the next period: a position frame only
  EXPECT_EQ(ddyn_sil_node_on_frame(node, f.id, f.data.data(), f.dlc), 1);
  ddyn_sil_node_period(node, &per);
  ddyn_sil_log_readings(&per, raw);
  EXPECT_TRUE(std::isnan(raw[0]));
  EXPECT_TRUE(std::isnan(raw[1]));
  EXPECT_TRUE(std::isnan(raw[3]));
  EXPECT_NEAR(raw[4], 1.21, 0.01);    // this period's position; no heading came in it
  EXPECT_TRUE(std::isnan(raw[6]));
}
