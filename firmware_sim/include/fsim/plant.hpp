// fsim/plant.hpp - the car: the one vehicle model (generated C, c_src/generated) integrated with
// RK4 on fine sub-steps as the "true" plant, behind rate- and range-limited actuators, with the
// unmodelled effects that map onto plant-side transforms of the generated model.
//
// The generated model's state carries the actual throttle and steering; its inputs are their
// rates. Here the actuators turn set-points into those rates: each actuator moves toward its
// (clamped) set-point as fast as its rate limit allows.
//
// Effects offered (all off by default; definitions as in train/model/effects.py):
//   steer_delay, throttle_delay  the actuator sees the set-point commanded `delay` s ago
//   steer_lag                    first-order lag (tau) between the set-point and the steering servo's target
//   mass_offset                  the true mass is m (1 + fraction): the generated accelerations' force
//                                part is scaled by 1 / (1 + fraction) (Iz, lf, lr unchanged)
//   downforce                    k (s^2/m^2): the tyres' peak forces D_f, D_r times 1 + k vx^2 at the
//                                state's own speed (ddyn_model_downforce)
//   yaw_rate_bias                the gyro reads omega + bias (sensor side: see sensors.hpp)
// The road's bank (set_road_bank, the world's, not an effect: the track's own banking at the car's
// track position, PlantApp's road_bank) adds the lateral gravity g sin(bank) to dvy (+ to the left), as
// train/model/effects.py's bank_angle and ddyn.plants.commonroad_st define it. The road's grade
// (set_road_grade, likewise the world's: PlantApp's road_grade) adds the longitudinal gravity -g sin(grade)
// to dvx (+ uphill), as train/model/effects.py's grade.
// The others of train/model/effects.py (grade, combined slip, tyre relaxation and wear)
// change the tyre or gravity terms inside the model and would need generated C; not offered.
#pragma once

#include <Eigen/Core>
#include <deque>

#include "ddyn/model.h"

namespace fsim {

using State = Eigen::Matrix<double, DDYN_NX, 1>;
using Coeffs = Eigen::Matrix<double, DDYN_NC, 1>;
enum StateIndex { kX = 0, kY, kYaw, kVx, kVy, kOmega, kThrottle, kSteer };

struct ActuatorLimits {
  double throttle_min = -0.1, throttle_max = 1.0;
  double steer_min = -0.35, steer_max = 0.35;
  double dthrottle_max = 10.0;  // 1/s
  double dsteer_max = 5.0;      // rad/s
};

struct PlantEffects {
  double steer_delay = 0.0;     // s
  double throttle_delay = 0.0;  // s
  double steer_lag = 0.0;       // s (time constant)
  double mass_offset = 0.0;     // fraction
  double downforce = 0.0;       // s^2/m^2
  double yaw_rate_bias = 0.0;   // rad/s (applied by the sensors)
};

class Plant {
 public:
  // substep: RK4 step (s); the model is evaluated by ddyn_model_derivatives.
  Plant(const ddyn_vehicle_model* model, const Coeffs& coeffs, const ActuatorLimits& limits,
        const PlantEffects& effects, double substep);

  void reset(const State& x0, double t0 = 0.0);
  // new set-points at the current time (clamped to the actuator ranges)
  void set_command(double throttle, double steering);
  // integrate over dt (a whole number of sub-steps, the last one shortened if needed)
  void advance(double dt);
  // standstill brake: while held the car does not move (velocities zero); actuators still move
  void set_hold(bool hold) { held_ = hold; }
  bool held() const { return held_; }
  // the road's bank (rad, + tilting the road so that gravity pulls to the left) from now on
  void set_road_bank(double bank) { road_bank_ = bank; }
  double road_bank() const { return road_bank_; }
  // the road's grade (rad, + uphill in the direction of travel) from now on
  void set_road_grade(double grade) { road_grade_ = grade; }
  double road_grade() const { return road_grade_; }

  const State& state() const { return x_; }
  double time() const { return t_; }
  const ddyn_vehicle_model* model() const { return model_; }
  const Coeffs& coeffs() const { return c_; }
  const ActuatorLimits& limits() const { return limits_; }
  const PlantEffects& effects() const { return fx_; }
  // continuous-time derivative of the true plant (the generated model plus the downforce, the mass offset
  // and the bank)
  State derivative(const State& x, const Eigen::Vector2d& u);
  // set-points the actuators currently chase (after delay and lag)
  double throttle_target() const { return throttle_target_; }
  double steer_target() const { return steer_lagged_; }

 private:
  struct Setpoint {
    double t, throttle, steering;
  };
  double delayed(double delay, bool steering) const;
  void substep(double h);

  const ddyn_vehicle_model* model_;
  Coeffs c_;
  ActuatorLimits limits_;
  PlantEffects fx_;
  double h_;
  State x_ = State::Zero();
  double t_ = 0.0;
  std::deque<Setpoint> history_;  // set-points, oldest first (kept as long as the delays need)
  double throttle_target_ = 0.0, steer_lagged_ = 0.0;
  bool held_ = false;
  double road_bank_ = 0.0;
  double road_grade_ = 0.0;
  ddyn_model_work work_{};
};

}  // namespace fsim
