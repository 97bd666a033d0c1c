// fsim/dbw_unit.hpp - the car's drive-by-wire unit as the plant plays it: it passes valid
// commands to the actuators and runs a watchdog. No valid command within `deadline` seconds
// brings the car to a controlled stop, as a real unit would: the steering is held at the last
// valid set-point, the drivetrain brakes (throttle at its minimum) until the car is slower
// than `stop_speed`, then the throttle goes to zero and the standstill brake holds the car. The unit stays in the safe state until
// `rearm_count` consecutive valid commands arrive (0: latched until the plant restarts).
#pragma once

namespace fsim {

enum class DbwMode { kWaiting, kActive, kSafeStop };

struct DbwConfig {
  double deadline = 0.08;     // s without a valid command before the safe stop (4 control periods at 50 Hz)
  double brake_throttle = -0.1;
  double stop_speed = 0.05;   // m/s
  int rearm_count = 0;
};

struct DbwOutput {
  double throttle = 0.0;
  double steering = 0.0;
  bool hold = false;  // standstill brake engaged (safe state reached)
};

class DbwUnit {
 public:
  explicit DbwUnit(const DbwConfig& cfg) : cfg_(cfg) {}
  // a command that passed the frame checks (checksum, counter, range) at time t
  void on_valid_command(double t, double throttle, double steering);
  // a frame that failed the checks: counted, never used
  void on_rejected_command() { ++rejected_; }
  // advance the watchdog to time t; returns the set-points for the actuators
  DbwOutput update(double t, double vx);

  DbwMode mode() const { return mode_; }
  int trips() const { return trips_; }
  int rejected() const { return rejected_; }
  double last_valid_time() const { return last_valid_; }
  double first_trip_time() const { return first_trip_; }       // < 0: never tripped
  double first_trip_latency() const { return first_latency_; }  // trip time - last valid command time
  double stopped_time() const { return stopped_; }              // first time at standstill in the safe state

 private:
  DbwConfig cfg_;
  DbwMode mode_ = DbwMode::kWaiting;
  double last_valid_ = -1.0, throttle_ = 0.0, steering_ = 0.0;
  int streak_ = 0, trips_ = 0, rejected_ = 0;
  double first_trip_ = -1.0, first_latency_ = -1.0, stopped_ = -1.0;
};

}  // namespace fsim
