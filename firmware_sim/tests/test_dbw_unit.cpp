#include "fsim/dbw_unit.hpp"
#include "test_util.hpp"

using fsim::DbwConfig;
using fsim::DbwMode;
using fsim::DbwUnit;

TEST(DbwUnit, PassesCommandsWhileTheyArrive) {
  DbwUnit d(DbwConfig{});
  EXPECT_EQ(d.mode(), DbwMode::kWaiting);
  EXPECT_DOUBLE_EQ(d.update(0.0, 1.0).throttle, 0.0);
  for (int k = 0; k < 50; ++k) {
    d.on_valid_command(0.02 * k, 0.4, 0.1);
    const auto out = d.update(0.02 * k + 0.019, 1.0);
    EXPECT_DOUBLE_EQ(out.throttle, 0.4);
    EXPECT_DOUBLE_EQ(out.steering, 0.1);
  }
  EXPECT_EQ(d.mode(), DbwMode::kActive);
  EXPECT_EQ(d.trips(), 0);
}

TEST(DbwUnit, DeadlineBringsAControlledStop) {
  DbwConfig cfg;
  cfg.deadline = 0.08;
  DbwUnit d(cfg);
  d.on_valid_command(1.0, 0.6, -0.2);
  EXPECT_EQ(d.update(1.079, 2.0).throttle, 0.6);  // still within the deadline
  EXPECT_EQ(d.mode(), DbwMode::kActive);
  const auto out = d.update(1.081, 2.0);
  EXPECT_EQ(d.mode(), DbwMode::kSafeStop);
  EXPECT_DOUBLE_EQ(out.throttle, cfg.brake_throttle);  // braking
  EXPECT_DOUBLE_EQ(out.steering, -0.2);                // steering held
  EXPECT_NEAR(d.first_trip_latency(), 0.081, 1e-12);
  // latched: later commands are not taken over
  d.on_valid_command(1.1, 1.0, 0.3);
  EXPECT_DOUBLE_EQ(d.update(1.1, 1.0).throttle, cfg.brake_throttle);
  // at standstill the throttle goes to zero and the stop time is recorded
  EXPECT_DOUBLE_EQ(d.update(1.5, 0.01).throttle, 0.0);
  EXPECT_NEAR(d.stopped_time(), 1.5, 1e-12);
  EXPECT_EQ(d.trips(), 1);
}

TEST(DbwUnit, RearmsAfterConsecutiveValidCommands) {
  DbwConfig cfg;
  cfg.rearm_count = 3;
  DbwUnit d(cfg);
  d.on_valid_command(0.0, 0.5, 0.0);
  d.update(0.2, 1.0);
  ASSERT_EQ(d.mode(), DbwMode::kSafeStop);
  d.on_valid_command(0.21, 0.5, 0.0);
  d.on_valid_command(0.22, 0.5, 0.0);
  EXPECT_EQ(d.mode(), DbwMode::kSafeStop);
  d.on_valid_command(0.23, 0.5, 0.0);
  EXPECT_EQ(d.mode(), DbwMode::kActive);
  EXPECT_DOUBLE_EQ(d.update(0.24, 1.0).throttle, 0.5);
}

TEST(DbwUnit, RejectedAndNonFiniteCommandsDoNotFeedTheWatchdog) {
  DbwUnit d(DbwConfig{});
  d.on_valid_command(0.0, 0.5, 0.0);
  for (int k = 1; k < 10; ++k) {
    d.on_rejected_command();
    d.on_valid_command(0.01 * k, NAN, 0.0);
  }
  d.update(0.1, 1.0);
  EXPECT_EQ(d.mode(), DbwMode::kSafeStop);
  EXPECT_EQ(d.rejected(), 18);
}
