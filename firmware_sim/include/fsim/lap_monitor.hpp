// fsim/lap_monitor.hpp - progress along the track, lap times and boundary violations of the
// car's footprint, updated once per plant step.
#pragma once

#include <vector>

#include "fsim/track.hpp"

namespace fsim {

struct LapMonitorResult {
  std::vector<double> lap_times;   // s, one per completed lap
  int violations = 0;              // episodes with any footprint corner outside the bounds
  double time_outside = 0.0;       // s, total time with a corner outside
  double worst_clearance = 0.0;    // m, smallest clearance seen (negative: depth outside)
  double progress = 0.0;           // m driven along the centre line since the start (unwrapped)
  double distance = 0.0;           // m of path driven by the reference point
};

class LapMonitor {
 public:
  LapMonitor(const Track& track, const Footprint& footprint);
  // the car's pose at time t; the first call fixes the start line (at the car's s)
  void update(double t, double x, double y, double yaw);
  // continue a run from a snapshot (plant restart): the last pose's time, s, and the result so far
  void restore(double t, double x, double y, double s, double lap_start_time, const LapMonitorResult& r);
  double lap_start_time() const { return lap_start_time_; }
  int laps_completed() const { return static_cast<int>(result_.lap_times.size()); }
  const LapMonitorResult& result() const { return result_; }
  double s() const { return s_; }
  double clearance() const { return clearance_; }
  bool outside() const { return outside_; }

 private:
  const Track& track_;
  Footprint footprint_;
  LapMonitorResult result_;
  bool started_ = false;
  double t_prev_ = 0.0, s_ = 0.0, progress_prev_ = 0.0, lap_start_time_ = 0.0;
  double x_prev_ = 0.0, y_prev_ = 0.0, clearance_ = 0.0;
  bool outside_ = false;
};

}  // namespace fsim
