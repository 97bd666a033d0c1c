#include "fsim/dbw_unit.hpp"

#include <cmath>

namespace fsim {

void DbwUnit::on_valid_command(double t, double throttle, double steering) {
  if (!std::isfinite(throttle) || !std::isfinite(steering)) {
    ++rejected_;
    return;
  }
  last_valid_ = t;
  ++streak_;
  if (mode_ == DbwMode::kSafeStop) {
    if (cfg_.rearm_count > 0 && streak_ >= cfg_.rearm_count) mode_ = DbwMode::kActive;
    else return;  // the set-points are not taken over while safe
  }
  mode_ = DbwMode::kActive;
  throttle_ = throttle;
  steering_ = steering;
}

DbwOutput DbwUnit::update(double t, double vx) {
  if (mode_ == DbwMode::kActive && t - last_valid_ > cfg_.deadline) {
    mode_ = DbwMode::kSafeStop;
    streak_ = 0;
    ++trips_;
    if (first_trip_ < 0.0) {
      first_trip_ = t;
      first_latency_ = t - last_valid_;
    }
  }
  DbwOutput out;
  switch (mode_) {
    case DbwMode::kWaiting:  // before the first command the car stands still
      out = {0.0, 0.0};
      break;
    case DbwMode::kActive:
      out = {throttle_, steering_};
      break;
    case DbwMode::kSafeStop:
      if (std::fabs(vx) > cfg_.stop_speed) {
        out = {vx > 0.0 ? cfg_.brake_throttle : 0.0, steering_};
      } else {
        out = {0.0, steering_, true};
        if (stopped_ < 0.0) stopped_ = t;
      }
      break;
  }
  return out;
}

}  // namespace fsim
