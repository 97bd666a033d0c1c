#include "fsim/lap_monitor.hpp"

#include <cmath>

namespace fsim {

LapMonitor::LapMonitor(const Track& track, const Footprint& footprint) : track_(track), footprint_(footprint) {}

void LapMonitor::restore(double t, double x, double y, double s, double lap_start_time, const LapMonitorResult& r) {
  started_ = true;
  t_prev_ = t;
  x_prev_ = x;
  y_prev_ = y;
  s_ = s;
  lap_start_time_ = lap_start_time;
  result_ = r;
  outside_ = false;
}

void LapMonitor::update(double t, double x, double y, double yaw) {
  // the car moves far less than this between two updates; wide enough for any plant step
  const double window = 0.1 * track_.length();
  if (!started_) {
    started_ = true;
    s_ = track_.project(Vec2(x, y)).s;
    lap_start_time_ = t_prev_ = t;
    x_prev_ = x;
    y_prev_ = y;
    clearance_ = footprint_clearance(track_, footprint_, x, y, yaw, s_, window);
    result_.worst_clearance = clearance_;
    outside_ = clearance_ < 0.0;
    if (outside_) result_.violations = 1;
    return;
  }
  const double s_new = track_.project(Vec2(x, y), s_, window).s;
  double ds = s_new - s_;
  const double L = track_.length();
  if (ds > 0.5 * L) ds -= L;
  if (ds < -0.5 * L) ds += L;
  s_ = s_new;
  const double progress = result_.progress + ds;
  // a lap ends when the progress crosses the next multiple of the length (time interpolated)
  const double next_line = (laps_completed() + 1) * L;
  if (progress >= next_line && ds > 0.0) {
    const double frac = (next_line - result_.progress) / ds;
    const double t_cross = t_prev_ + frac * (t - t_prev_);
    result_.lap_times.push_back(t_cross - lap_start_time_);
    lap_start_time_ = t_cross;
  }
  result_.progress = progress;
  result_.distance += std::hypot(x - x_prev_, y - y_prev_);
  clearance_ = footprint_clearance(track_, footprint_, x, y, yaw, s_, window);
  result_.worst_clearance = std::min(result_.worst_clearance, clearance_);
  const bool out = clearance_ < 0.0;
  if (out && !outside_) ++result_.violations;
  if (out) result_.time_outside += t - t_prev_;
  outside_ = out;
  t_prev_ = t;
  x_prev_ = x;
  y_prev_ = y;
}

}  // namespace fsim
