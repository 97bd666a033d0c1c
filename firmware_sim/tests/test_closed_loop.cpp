// Plant + DBW unit + lap monitor closed around a simple test driver (pure pursuit on the centre
// line, proportional speed control): a lap of ETHZMobil completes inside the bounds, and a driver
// that falls silent mid-lap is stopped by the watchdog.
#include <cmath>

#include "fsim/dbw_unit.hpp"
#include "fsim/lap_monitor.hpp"
#include "fsim/plant.hpp"
#include "fsim/track.hpp"
#include "test_util.hpp"

namespace {

struct Driver {
  const fsim::Track& track;
  double speed;
  double s_hint = 0.0;
  std::pair<double, double> command(const fsim::State& x) {
    const auto p = track.project(fsim::Vec2(x[fsim::kX], x[fsim::kY]), s_hint, 1.0);
    s_hint = p.s;
    const double look = 0.25;
    const fsim::Vec2 target = track.position(p.s + look);
    const double dx = target.x() - x[fsim::kX], dy = target.y() - x[fsim::kY];
    const double alpha = std::atan2(dy, dx) - x[fsim::kYaw];
    const double steer = std::atan2(2.0 * 0.062 * std::sin(alpha), std::hypot(dx, dy));
    const double throttle = 0.12 + 0.5 * (speed - x[fsim::kVx]);
    return {throttle, steer};
  }
};

struct Loop {
  fsim::Track track;
  fsim::Plant plant;
  fsim::DbwUnit dbw;
  fsim::LapMonitor monitor;
  Loop()
      : track(fsim::Track::load(fsim_test::shared_data() + "/tracks", "ethzMobil")),
        plant(&ddyn_model_orca_1_43, fsim_test::orca_true(), {}, {}, 1e-3),
        dbw(fsim::DbwConfig{}),
        monitor(track, fsim::Footprint{0.1, 0.05, 0.029, 0.033}) {
    fsim::State x0 = fsim::State::Zero();
    const fsim::Vec2 p = track.position(0.0);
    x0[fsim::kX] = p.x();
    x0[fsim::kY] = p.y();
    x0[fsim::kYaw] = track.heading_at(0.0);
    x0[fsim::kVx] = 0.1;
    plant.reset(x0);
  }
  // run with a control period of 20 ms and a plant step of 1 ms; the driver is silent after t_silent
  void run(double duration, double t_silent, double speed) {
    Driver driver{track, speed};
    const int steps = static_cast<int>(std::lround(duration / 1e-3));
    for (int k = 0; k < steps; ++k) {
      const double t = plant.time();
      if (k % 20 == 0 && t < t_silent) {
        const auto c = driver.command(plant.state());
        dbw.on_valid_command(t, c.first, c.second);
      }
      const auto out = dbw.update(t, plant.state()[fsim::kVx]);
      plant.set_command(out.throttle, out.steering);
      plant.set_hold(out.hold);
      plant.advance(1e-3);
      monitor.update(plant.time(), plant.state()[fsim::kX], plant.state()[fsim::kY], plant.state()[fsim::kYaw]);
    }
  }
};

}  // namespace

TEST(ClosedLoop, TestDriverCompletesALapInsideTheBounds) {
  FSIM_REQUIRE_TRACKS();
  Loop loop;
  loop.run(16.0, 1e9, 1.0);
  ASSERT_GE(loop.monitor.laps_completed(), 1);
  const double lap = loop.monitor.result().lap_times[0];
  EXPECT_GT(lap, loop.track.length() / 1.2);
  EXPECT_LT(lap, loop.track.length() / 0.7);
  EXPECT_EQ(loop.monitor.result().violations, 0);
  EXPECT_EQ(loop.dbw.trips(), 0);
}

TEST(ClosedLoop, SilentDriverIsStoppedByTheWatchdog) {
  FSIM_REQUIRE_TRACKS();
  Loop loop;
  loop.run(5.0, 3.0, 1.0);
  EXPECT_EQ(loop.dbw.trips(), 1);
  // the last command went out at t < 3.0; the safe state follows within the deadline (+ one step)
  EXPECT_LE(loop.dbw.first_trip_latency(), 0.08 + 1e-3 + 1e-9);
  EXPECT_GT(loop.dbw.first_trip_time(), 3.0);
  EXPECT_LT(loop.dbw.first_trip_time(), 3.1);
  EXPECT_GT(loop.dbw.stopped_time(), 0.0);
  EXPECT_DOUBLE_EQ(loop.plant.state()[fsim::kVx], 0.0);
  EXPECT_TRUE(loop.plant.held());
  // braking from about 1 m/s takes about half a second with the drivetrain's reverse torque
  EXPECT_LT(loop.dbw.stopped_time() - loop.dbw.first_trip_time(), 1.0);
}
