#include "fsim/sensors.hpp"

#include <cmath>
#include <stdexcept>
#include <string>

namespace fsim {

SensorSuite::SensorSuite(std::array<SensorConfig, DDYN_MEAS_COUNT> cfg, double yaw_rate_bias, unsigned seed)
    : cfg_(cfg), bias_(yaw_rate_bias), rng_(seed) {
  for (const auto& c : cfg_)
    if (c.enabled && !(c.rate > 0.0)) throw std::invalid_argument("sensor rate must be positive");
}

void SensorSuite::sample(const Plant& plant, double t_prev, double t, std::vector<Measurement>& out) {
  for (int k = 0; k < DDYN_MEAS_COUNT; ++k) {
    const SensorConfig& c = cfg_[k];
    if (!c.enabled) continue;
    // a sample is due when the time crosses a multiple of the sensor's period
    const double period = 1.0 / c.rate;
    const long n_prev = static_cast<long>(std::floor(t_prev / period + 1e-9));
    const long n_now = static_cast<long>(std::floor(t / period + 1e-9));
    if (n_now <= n_prev) continue;
    if (c.silent_from >= 0.0 && t >= c.silent_from && (c.silent_until < 0.0 || t < c.silent_until)) continue;
    Measurement m;
    m.kind = static_cast<ddyn_meas_kind>(k);
    m.t = t;
    m.dim = ddyn_meas_dim(m.kind);
    double h[DDYN_MEAS_MAX_DIM] = {0.0, 0.0};
    const ddyn_status st = ddyn_model_measure(plant.model(), m.kind, plant.state().data(), plant.coeffs().data(), h,
                                              nullptr, &work_);
    if (st != DDYN_OK) throw std::runtime_error(std::string("sensor model failed: ") + ddyn_status_name(st));
    for (int i = 0; i < m.dim; ++i) m.value[i] = h[i] + c.noise_std[i] * normal_(rng_);
    if (m.kind == DDYN_MEAS_YAW_RATE) m.value[0] += bias_;
    out.push_back(m);
  }
}

}  // namespace fsim
