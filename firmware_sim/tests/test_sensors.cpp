#include <cmath>
#include <vector>

#include "fsim/sensors.hpp"
#include "test_util.hpp"

namespace {

std::array<fsim::SensorConfig, DDYN_MEAS_COUNT> rates(double hz) {
  std::array<fsim::SensorConfig, DDYN_MEAS_COUNT> c{};
  for (auto& s : c) s.rate = hz;
  return c;
}

}  // namespace

TEST(Sensors, RatesNoiseAndBias) {
  fsim::Plant plant(&ddyn_model_orca_1_43, fsim_test::orca_true(), {}, {}, 1e-3);
  fsim::State x = fsim::State::Zero();
  x[fsim::kX] = 1.0;
  x[fsim::kY] = -2.0;
  x[fsim::kVx] = 1.0;
  x[fsim::kOmega] = 0.5;
  plant.reset(x);
  auto cfg = rates(100.0);
  cfg[DDYN_MEAS_GNSS_POSITION].rate = 50.0;
  cfg[DDYN_MEAS_GNSS_POSITION].noise_std = {0.01, 0.01};
  cfg[DDYN_MEAS_STEERING].enabled = false;
  fsim::SensorSuite s(cfg, 0.03, 7);
  std::vector<fsim::Measurement> out;
  const double dt = 1e-3;
  for (int k = 1; k <= 10000; ++k) s.sample(plant, (k - 1) * dt, k * dt, out);  // 10 s, state frozen
  int gnss = 0, gyro = 0, steer = 0;
  double sum = 0.0, sum2 = 0.0;
  for (const auto& m : out) {
    if (m.kind == DDYN_MEAS_GNSS_POSITION) {
      ++gnss;
      sum += m.value[0] - 1.0;
      sum2 += (m.value[0] - 1.0) * (m.value[0] - 1.0);
    }
    if (m.kind == DDYN_MEAS_YAW_RATE) {
      ++gyro;
      EXPECT_DOUBLE_EQ(m.value[0], 0.5 + 0.03);  // noise-free gyro with its bias
    }
    if (m.kind == DDYN_MEAS_STEERING) ++steer;
  }
  EXPECT_EQ(gnss, 500);
  EXPECT_EQ(gyro, 1000);
  EXPECT_EQ(steer, 0);
  const double mean = sum / gnss, sd = std::sqrt(sum2 / gnss - mean * mean);
  EXPECT_NEAR(mean, 0.0, 0.002);
  EXPECT_NEAR(sd, 0.01, 0.0015);
}

TEST(Sensors, SilentWindow) {
  fsim::Plant plant(&ddyn_model_orca_1_43, fsim_test::orca_true(), {}, {}, 1e-3);
  plant.reset(fsim::State::Zero());
  auto cfg = rates(100.0);
  cfg[DDYN_MEAS_YAW_RATE].silent_from = 1.0;
  cfg[DDYN_MEAS_YAW_RATE].silent_until = 2.0;
  fsim::SensorSuite s(cfg, 0.0, 1);
  std::vector<fsim::Measurement> out;
  for (int k = 1; k <= 3000; ++k) s.sample(plant, (k - 1) * 1e-3, k * 1e-3, out);
  int gyro = 0;
  for (const auto& m : out) {
    if (m.kind != DDYN_MEAS_YAW_RATE) continue;
    ++gyro;
    EXPECT_TRUE(m.t < 1.0 || m.t >= 2.0) << m.t;
  }
  EXPECT_EQ(gyro, 200);
}
