#include <cmath>

#include "fsim/lap_monitor.hpp"
#include "fsim/track.hpp"
#include "test_util.hpp"

using fsim::Footprint;
using fsim::LapMonitor;
using fsim::Track;
using fsim::Vec2;

namespace {

// a 4 m x 2 m rectangle track, 1 m wide, counter-clockwise
Track rectangle_track() {
  // corners joined by straight edges, sampled every 0.1 m (the bounds' distance at a centre-line
  // corner is the corner-to-corner distance, so sparse points would widen the track)
  auto rect = [](double hx, double hy) {
    const std::vector<Vec2> c{{-hx, -hy}, {hx, -hy}, {hx, hy}, {-hx, hy}};
    std::vector<Vec2> p;
    for (int i = 0; i < 4; ++i) {
      const Vec2 a = c[i], b = c[(i + 1) % 4];
      const int n = static_cast<int>(std::lround((b - a).norm() / 0.1));
      for (int k = 0; k < n; ++k) p.push_back(a + (b - a) * (static_cast<double>(k) / n));
    }
    return p;
  };
  return Track("rect", rect(2.0, 1.0), rect(1.5, 0.5), rect(2.5, 1.5));
}

}  // namespace

TEST(Track, RectangleGeometry) {
  const Track t = rectangle_track();
  EXPECT_NEAR(t.length(), 12.0, 1e-12);
  EXPECT_NEAR(t.width(), 1.0, 1e-9);
  // counter-clockwise: the inner rectangle is on the left
  const auto p = t.project(Vec2(0.0, -0.8));
  EXPECT_NEAR(p.s, 2.0, 1e-12);
  EXPECT_NEAR(p.lateral, 0.2, 1e-12);
  EXPECT_NEAR(p.boundary_distance(), 0.3, 1e-12);
  EXPECT_NEAR(t.project(Vec2(0.0, -1.7)).boundary_distance(), -0.2, 1e-12);
  // windowed search agrees with the full one
  EXPECT_NEAR(t.project(Vec2(1.9, 0.2), 5.0, 1.5).s, t.project(Vec2(1.9, 0.2)).s, 1e-12);
  EXPECT_NEAR(t.heading_at(1.0), 0.0, 1e-9);
  EXPECT_NEAR(t.heading_at(4.5), M_PI / 2, 1e-9);
}

TEST(Track, FootprintCornersAndClearance) {
  const Track t = rectangle_track();
  const Footprint fp{0.4, 0.2, 0.1, 0.1};
  const auto c = fp.corners(0.0, -1.0, 0.0);
  EXPECT_NEAR(c[0].x(), 0.2, 1e-12);
  EXPECT_NEAR(c[0].y(), -0.9, 1e-12);
  EXPECT_NEAR(c[2].x(), -0.2, 1e-12);
  EXPECT_NEAR(c[2].y(), -1.1, 1e-12);
  // centred: 0.5 - 0.1 of clearance; shifted right by 0.45: the right corners are 0.05 outside
  EXPECT_NEAR(fsim::footprint_clearance(t, fp, 0.0, -1.0, 0.0, 2.0, 2.0), 0.4, 1e-12);
  EXPECT_NEAR(fsim::footprint_clearance(t, fp, 0.0, -1.45, 0.0, 2.0, 2.0), -0.05, 1e-12);
  // turned 90 degrees in place: the half length now counts laterally
  EXPECT_NEAR(fsim::footprint_clearance(t, fp, 0.0, -1.0, M_PI / 2, 2.0, 2.0), 0.3, 1e-12);
}

TEST(LapMonitor, LapTimeAndViolationEpisodes) {
  const Track t = rectangle_track();
  LapMonitor mon(t, Footprint{0.2, 0.1, 0.05, 0.05});
  const double v = 2.0, dt = 0.001;
  // two laps along the centre line at constant speed, leaving the track twice in the second lap
  int outs = 0;
  for (int k = 0; k <= static_cast<int>(2.0 * 12.0 / v / dt) + 5; ++k) {
    const double time = k * dt, s = v * time;
    const double sl = std::fmod(s, 12.0);
    const bool wobble = s > 12.0 && ((sl > 1.0 && sl < 1.5) || (sl > 7.0 && sl < 7.2));
    const Vec2 p = t.position(s);
    Vec2 n(-std::sin(t.heading_at(s)), std::cos(t.heading_at(s)));
    const Vec2 q = p + (wobble ? 0.6 : 0.0) * n;
    mon.update(time, q.x(), q.y(), t.heading_at(s));
    outs += mon.outside() ? 1 : 0;
  }
  ASSERT_EQ(mon.laps_completed(), 2);
  EXPECT_NEAR(mon.result().lap_times[0], 6.0, 1e-6);
  EXPECT_NEAR(mon.result().lap_times[1], 6.0, 1e-6);
  EXPECT_EQ(mon.result().violations, 2);
  EXPECT_NEAR(mon.result().time_outside, 0.35, 0.01);
  EXPECT_LT(mon.result().worst_clearance, -0.1);
  EXPECT_GT(outs, 0);
}

TEST(Track, EthzMobilFromSharedData) {
  FSIM_REQUIRE_TRACKS();
  const Track t = Track::load(fsim_test::shared_data() + "/tracks", "ethzMobil");
  // shared/data/README.md: width 0.46 m, centre line about 12.8 m
  EXPECT_NEAR(t.width(), 0.46, 0.01);
  EXPECT_NEAR(t.length(), 12.8, 0.2);
  for (int i = 0; i < t.center().size(); i += 17) {
    const auto p = t.project(t.center().points()[i]);
    EXPECT_NEAR(p.lateral, 0.0, 1e-12);
    EXPECT_GT(p.boundary_distance(), 0.15);
  }
  EXPECT_THROW(Track::load(fsim_test::shared_data() + "/tracks", "no_such_track"), std::runtime_error);
}
