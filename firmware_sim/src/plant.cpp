#include "fsim/plant.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <limits>
#include <string>

namespace fsim {

namespace {
constexpr double kGravity = 9.81;  // m/s^2, train/model/effects.py G
}  // namespace

Plant::Plant(const ddyn_vehicle_model* model, const Coeffs& coeffs, const ActuatorLimits& limits,
             const PlantEffects& effects, double substep)
    : model_(model), c_(coeffs), limits_(limits), fx_(effects), h_(substep) {
  if (model_ == nullptr) throw std::invalid_argument("plant: no vehicle model");
  if (!(h_ > 0.0)) throw std::invalid_argument("plant: sub-step must be positive");
  if (fx_.steer_delay < 0 || fx_.throttle_delay < 0 || fx_.steer_lag < 0 || fx_.mass_offset <= -1.0 ||
      !(fx_.downforce >= 0.0 && std::isfinite(fx_.downforce)))
    throw std::invalid_argument("plant: delays, lag and downforce must be >= 0 and mass_offset > -1");
  if (!c_.allFinite()) throw std::invalid_argument("plant: non-finite coefficients");
}

void Plant::reset(const State& x0, double t0) {
  x_ = x0;
  x_[kThrottle] = std::clamp(x_[kThrottle], limits_.throttle_min, limits_.throttle_max);
  x_[kSteer] = std::clamp(x_[kSteer], limits_.steer_min, limits_.steer_max);
  t_ = t0;
  history_.clear();
  // the initial actuator positions count as commanded since forever (what any delay sees first)
  history_.push_back({-std::numeric_limits<double>::infinity(), x_[kThrottle], x_[kSteer]});
  held_ = false;
  throttle_target_ = x_[kThrottle];
  steer_lagged_ = x_[kSteer];
}

void Plant::set_command(double throttle, double steering) {
  if (!std::isfinite(throttle) || !std::isfinite(steering)) return;  // the DBW unit never passes these
  throttle = std::clamp(throttle, limits_.throttle_min, limits_.throttle_max);
  steering = std::clamp(steering, limits_.steer_min, limits_.steer_max);
  if (!history_.empty() && history_.back().t >= t_) history_.pop_back();
  history_.push_back({t_, throttle, steering});
  // keep one set-point older than the longest delay
  const double keep = std::max(fx_.steer_delay, fx_.throttle_delay);
  while (history_.size() > 1 && history_[1].t <= t_ - keep) history_.pop_front();
}

double Plant::delayed(double delay, bool steering) const {
  const double when = t_ - delay;
  // the latest set-point commanded at or before `when` (the oldest one before the start)
  const Setpoint* sp = &history_.front();
  for (const auto& s : history_) {
    if (s.t <= when + 1e-12) sp = &s; else break;
  }
  return steering ? sp->steering : sp->throttle;
}

State Plant::derivative(const State& x, const Eigen::Vector2d& u) {
  State xd;
  // downforce: the tyre peaks of the state's own speed (ddyn_model_downforce; a copy of c_ without it)
  Coeffs c_at;
  ddyn_model_downforce(c_.data(), fx_.downforce, x[kVx], c_at.data());
  const ddyn_status st = ddyn_model_derivatives(model_, x.data(), u.data(), c_at.data(), xd.data(), &work_);
  if (st != DDYN_OK) throw std::runtime_error(std::string("plant: model evaluation failed: ") + ddyn_status_name(st));
  if (fx_.mass_offset != 0.0) {
    // dvx = Fx/m + vy omega, dvy = Fy/m - vx omega: only the force part scales with 1/m
    const double k = 1.0 / (1.0 + fx_.mass_offset);
    const double vy_om = x[kVy] * x[kOmega], vx_om = x[kVx] * x[kOmega];
    xd[kVx] = (xd[kVx] - vy_om) * k + vy_om;
    xd[kVy] = (xd[kVy] + vx_om) * k - vx_om;
  }
  // the road's bank: lateral gravity (train/model/effects.py G, + to the left)
  if (road_bank_ != 0.0) xd[kVy] += kGravity * std::sin(road_bank_);
  // the road's grade: longitudinal gravity (train/model/effects.py G, + uphill slows the car)
  if (road_grade_ != 0.0) xd[kVx] -= kGravity * std::sin(road_grade_);
  return xd;
}

void Plant::substep(double h) {
  throttle_target_ = delayed(fx_.throttle_delay, false);
  const double steer_cmd = delayed(fx_.steer_delay, true);
  // exact first-order lag over the sub-step with the command held
  steer_lagged_ = fx_.steer_lag > 0.0 ? steer_cmd + (steer_lagged_ - steer_cmd) * std::exp(-h / fx_.steer_lag)
                                      : steer_cmd;
  // rate-limited actuators: reach the target within this sub-step if the rate limit allows
  Eigen::Vector2d u;
  u[0] = std::clamp((throttle_target_ - x_[kThrottle]) / h, -limits_.dthrottle_max, limits_.dthrottle_max);
  u[1] = std::clamp((steer_lagged_ - x_[kSteer]) / h, -limits_.dsteer_max, limits_.dsteer_max);
  if (held_) {
    // brakes hold the car: the model's drivetrain law (constant rolling resistance Cr0) is not
    // valid at standstill and would push the car backwards
    x_[kVx] = x_[kVy] = x_[kOmega] = 0.0;
    x_[kThrottle] += h * u[0];
    x_[kSteer] += h * u[1];
    x_[kThrottle] = std::clamp(x_[kThrottle], limits_.throttle_min, limits_.throttle_max);
    x_[kSteer] = std::clamp(x_[kSteer], limits_.steer_min, limits_.steer_max);
    t_ += h;
    return;
  }
  const State k1 = derivative(x_, u);
  const State k2 = derivative(x_ + 0.5 * h * k1, u);
  const State k3 = derivative(x_ + 0.5 * h * k2, u);
  const State k4 = derivative(x_ + h * k3, u);
  x_ += (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4);
  // the actuator positions move linearly: remove round-off outside their ranges
  x_[kThrottle] = std::clamp(x_[kThrottle], limits_.throttle_min, limits_.throttle_max);
  x_[kSteer] = std::clamp(x_[kSteer], limits_.steer_min, limits_.steer_max);
  t_ += h;
  if (!x_.allFinite()) throw std::runtime_error("plant: state became non-finite");
}

void Plant::advance(double dt) {
  if (!(dt > 0.0)) return;
  const int n = std::max(1, static_cast<int>(std::ceil(dt / h_ - 1e-9)));
  const double h = dt / n;
  for (int i = 0; i < n; ++i) substep(h);
}

}  // namespace fsim
