// fsim/sensors.hpp - the car's sensors: what each reads comes from the generated sensor models
// (train/model/sensors.py -> c_src/generated, ddyn_model_measure), sampled at its own rate with
// Gaussian noise (seeded), the gyro's bias effect, and a "silent" window for fault scenarios.
#pragma once

#include <array>
#include <random>
#include <vector>

#include "fsim/plant.hpp"

namespace fsim {

struct SensorConfig {
  bool enabled = true;
  double rate = 100.0;                   // Hz
  std::array<double, DDYN_MEAS_MAX_DIM> noise_std{};  // per component
  double silent_from = -1.0;             // s: no samples in [silent_from, silent_until) (fault)
  double silent_until = -1.0;
};

struct Measurement {
  ddyn_meas_kind kind;
  double t;
  int dim;
  std::array<double, DDYN_MEAS_MAX_DIM> value;
};

class SensorSuite {
 public:
  SensorSuite(std::array<SensorConfig, DDYN_MEAS_COUNT> cfg, double yaw_rate_bias, unsigned seed);
  // samples due in (t_prev, t], read from the plant's current state
  void sample(const Plant& plant, double t_prev, double t, std::vector<Measurement>& out);
  const SensorConfig& config(ddyn_meas_kind k) const { return cfg_[k]; }

 private:
  std::array<SensorConfig, DDYN_MEAS_COUNT> cfg_;
  double bias_;
  std::mt19937_64 rng_;
  std::normal_distribution<double> normal_{0.0, 1.0};
  ddyn_model_work work_{};
};

}  // namespace fsim
