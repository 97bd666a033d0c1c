#include <cmath>

#include "ddyn_models.h"
#include "fsim/plant.hpp"
#include "test_util.hpp"

using fsim::Plant;
using fsim::State;

namespace {

State moving(double vx) {
  State x = State::Zero();
  x[fsim::kVx] = vx;
  return x;
}

Plant orca(const fsim::PlantEffects& fx = {}, double h = 1e-3) {
  return Plant(&ddyn_model_orca_1_43, fsim_test::orca_true(), fsim::ActuatorLimits{}, fx, h);
}

}  // namespace

// With the same 5 ms sub-step the plant's RK4 reproduces the generated RK4 step (4 x 5 ms) when the
// actuator rates are zero: both integrate the same generated model. Finer sub-steps converge to it.
TEST(Plant, AgreesWithGeneratedRk4Step) {
  Plant p = orca({}, 0.005), fine = orca({}, 0.0005);
  State x0 = moving(1.5);
  x0[fsim::kVy] = 0.05;
  x0[fsim::kOmega] = 0.8;
  x0[fsim::kThrottle] = 0.3;
  x0[fsim::kSteer] = 0.1;
  p.reset(x0);
  p.set_command(0.3, 0.1);  // held: rates zero, as in the generated step with u = 0
  p.advance(0.02);
  fine.reset(x0);
  fine.set_command(0.3, 0.1);
  fine.advance(0.02);
  State ref;
  const double u[2] = {0.0, 0.0};
  ddyn_model_work w{};
  ASSERT_EQ(ddyn_model_step(&ddyn_model_orca_1_43, DDYN_DISC_RK4, x0.data(), u, fsim_test::orca_true().data(),
                            ref.data(), &w),
            DDYN_OK);
  EXPECT_NEAR(p.time(), 0.02, 1e-12);
  for (int i = 0; i < DDYN_NX; ++i) {
    EXPECT_NEAR(p.state()[i], ref[i], 1e-12 * (1.0 + std::fabs(ref[i]))) << i;
    // RK4's error at 5 ms on this fast yaw mode is a few 1e-5: the sub-step matters
    EXPECT_NEAR(fine.state()[i], ref[i], 1e-4 * (1.0 + std::fabs(ref[i]))) << i;
  }
  // and it actually moved
  EXPECT_GT(p.state()[fsim::kX], 0.02);
}

TEST(Plant, ActuatorRangeAndRateLimits) {
  Plant p = orca();
  p.reset(moving(1.0));
  p.set_command(3.0, 1.0);  // beyond both ranges
  p.advance(0.01);
  // 5 rad/s for 10 ms: 0.05 rad; throttle 10 /s: 0.1
  EXPECT_NEAR(p.state()[fsim::kSteer], 0.05, 1e-9);
  EXPECT_NEAR(p.state()[fsim::kThrottle], 0.1, 1e-9);
  p.advance(0.2);
  EXPECT_DOUBLE_EQ(p.state()[fsim::kSteer], 0.35);
  EXPECT_DOUBLE_EQ(p.state()[fsim::kThrottle], 1.0);
  p.set_command(-5.0, -1.0);
  p.advance(0.5);
  EXPECT_DOUBLE_EQ(p.state()[fsim::kSteer], -0.35);
  EXPECT_DOUBLE_EQ(p.state()[fsim::kThrottle], -0.1);
  // non-finite set-points are ignored
  p.set_command(NAN, 0.0);
  p.advance(0.1);
  EXPECT_DOUBLE_EQ(p.state()[fsim::kSteer], -0.35);
}

TEST(Plant, SteerDelayShiftsTheResponse) {
  fsim::PlantEffects fx;
  fx.steer_delay = 0.04;
  Plant p = orca(fx);
  p.reset(moving(1.0));
  p.set_command(0.0, 0.2);
  p.advance(0.039);
  EXPECT_NEAR(p.state()[fsim::kSteer], 0.0, 1e-12);
  p.advance(0.02);  // moving for 19 ms at 5 rad/s
  EXPECT_NEAR(p.state()[fsim::kSteer], 0.095, 0.006);
}

TEST(Plant, ThrottleDelayShiftsTheResponse) {
  fsim::PlantEffects fx;
  fx.throttle_delay = 0.03;
  Plant p = orca(fx);
  p.reset(moving(1.0));
  p.set_command(0.5, 0.0);
  p.advance(0.029);
  EXPECT_NEAR(p.state()[fsim::kThrottle], 0.0, 1e-12);
  p.advance(0.1);
  EXPECT_NEAR(p.state()[fsim::kThrottle], 0.5, 1e-12);
}

TEST(Plant, SteerLagIsFirstOrder) {
  fsim::PlantEffects fx;
  fx.steer_lag = 0.05;
  Plant p = orca(fx);
  p.reset(moving(1.0));
  p.set_command(0.0, 0.02);  // small step: the rate limit never binds
  p.advance(0.05);
  EXPECT_NEAR(p.steer_target(), 0.02 * (1.0 - std::exp(-1.0)), 1e-6);
  EXPECT_NEAR(p.state()[fsim::kSteer], p.steer_target(), 1e-9);
}

TEST(Plant, MassOffsetScalesTheForcesOnly) {
  fsim::PlantEffects heavy;
  heavy.mass_offset = 0.25;
  Plant a = orca(), b = orca(heavy);
  State x = moving(1.0);
  x[fsim::kVy] = 0.1;
  x[fsim::kOmega] = 2.0;
  x[fsim::kThrottle] = 0.5;
  x[fsim::kSteer] = 0.1;
  const Eigen::Vector2d u(0.0, 0.0);
  const State da = a.derivative(x, u), db = b.derivative(x, u);
  const double vy_om = x[fsim::kVy] * x[fsim::kOmega], vx_om = x[fsim::kVx] * x[fsim::kOmega];
  EXPECT_NEAR(db[fsim::kVx] - vy_om, (da[fsim::kVx] - vy_om) / 1.25, 1e-12);
  EXPECT_NEAR(db[fsim::kVy] + vx_om, (da[fsim::kVy] + vx_om) / 1.25, 1e-12);
  EXPECT_DOUBLE_EQ(db[fsim::kOmega], da[fsim::kOmega]);
  EXPECT_DOUBLE_EQ(db[fsim::kX], da[fsim::kX]);
}

// Downforce: the derivative is the model's with the tyre peaks of the state's own speed, and zero is none
TEST(Plant, DownforceScalesTheTyrePeaksAtTheStatesSpeed) {
  fsim::PlantEffects df;
  df.downforce = 0.05;
  Plant a = orca(), b = orca(df);
  State x = moving(2.0);
  x[fsim::kVy] = 0.1;
  x[fsim::kOmega] = 1.0;
  x[fsim::kThrottle] = 0.4;
  x[fsim::kSteer] = 0.1;
  const Eigen::Vector2d u(0.0, 0.0);
  fsim::Coeffs c = fsim_test::orca_true();
  c[DDYN_MODEL_DF_INDEX] *= 1.0 + 0.05 * 4.0;
  c[DDYN_MODEL_DR_INDEX] *= 1.0 + 0.05 * 4.0;
  State want;
  ddyn_model_work work;
  ASSERT_EQ(ddyn_model_derivatives(&ddyn_model_orca_1_43, x.data(), u.data(), c.data(), want.data(), &work), DDYN_OK);
  const State db = b.derivative(x, u), da = a.derivative(x, u);
  for (int i = 0; i < DDYN_NX; ++i) EXPECT_NEAR(db[i], want[i], 1e-12 * (1.0 + std::abs(want[i])));
  EXPECT_GT(std::abs(db[fsim::kOmega] - da[fsim::kOmega]), 0.1);  // not blind: more grip, more yaw moment
  df.downforce = -1e-3;
  EXPECT_THROW(orca(df), std::invalid_argument);
}

// The road's bank adds g sin(bank) to dvy and nothing else (train/model/effects.py bank_angle, + to the left)
TEST(Plant, RoadBankAddsLateralGravity) {
  Plant p = orca();
  State x = moving(1.5);
  x[fsim::kVy] = 0.05;
  x[fsim::kOmega] = 0.8;
  x[fsim::kSteer] = 0.1;
  const Eigen::Vector2d u(0.2, -0.3);
  const State flat = p.derivative(x, u);
  p.set_road_bank(0.3);
  EXPECT_EQ(p.road_bank(), 0.3);
  const State banked = p.derivative(x, u);
  for (int i = 0; i < DDYN_NX; ++i) {
    EXPECT_NEAR(banked[i] - flat[i], i == fsim::kVy ? 9.81 * std::sin(0.3) : 0.0, 1e-12) << i;
  }
}

// The road's grade adds -g sin(grade) to dvx and nothing else (train/model/effects.py grade, + uphill)
TEST(Plant, RoadGradeAddsLongitudinalGravity) {
  Plant p = orca();
  State x = moving(1.5);
  x[fsim::kVy] = 0.05;
  x[fsim::kOmega] = 0.8;
  x[fsim::kSteer] = 0.1;
  const Eigen::Vector2d u(0.2, -0.3);
  const State level = p.derivative(x, u);
  p.set_road_grade(0.1);
  EXPECT_EQ(p.road_grade(), 0.1);
  const State uphill = p.derivative(x, u);
  for (int i = 0; i < DDYN_NX; ++i) {
    EXPECT_NEAR(uphill[i] - level[i], i == fsim::kVx ? -9.81 * std::sin(0.1) : 0.0, 1e-12) << i;
  }
}

TEST(Plant, RejectsBadConfiguration) {
  EXPECT_THROW(Plant(nullptr, fsim_test::orca_true(), {}, {}, 1e-3), std::invalid_argument);
  EXPECT_THROW(Plant(&ddyn_model_orca_1_43, fsim_test::orca_true(), {}, {}, 0.0), std::invalid_argument);
  fsim::PlantEffects bad;
  bad.steer_delay = -0.1;
  EXPECT_THROW(Plant(&ddyn_model_orca_1_43, fsim_test::orca_true(), {}, bad, 1e-3), std::invalid_argument);
}
