// Helpers shared by the firmware_sim tests.
#pragma once

#include <gtest/gtest.h>

#include <cstdlib>
#include <fstream>
#include <string>

#include "ddyn_models.h"
#include "ddyn_test_vehicles.h"
#include "fsim/plant.hpp"

namespace fsim_test {

// The shared data folder: $DDYN_SHARED_DATA, else the default the build was configured with.
inline std::string shared_data() {
  const char* env = std::getenv("DDYN_SHARED_DATA");
  return env ? std::string(env) : std::string(DDYN_SHARED_DATA_DEFAULT);
}

inline bool have_tracks() {
  return std::ifstream(shared_data() + "/tracks/ethzMobil_center.txt").good();
}

#define FSIM_REQUIRE_TRACKS()                                                                              \
  do {                                                                                                     \
    if (!fsim_test::have_tracks())                                                                         \
      GTEST_SKIP() << "SKIPPED LOUDLY: track data missing under " << fsim_test::shared_data()             \
                   << "/tracks (set DDYN_SHARED_DATA)";                                                    \
  } while (0)

// the paper's ORCA 1:43 car: the true coefficients of train/vehicles/orca_1_43.json (generated header)
inline fsim::Coeffs orca_true() {
  static const double c[] = DDYN_TEST_ORCA_1_43_TRUE_COEFFS;
  static_assert(sizeof c / sizeof c[0] == 17, "17 coefficients");
  return Eigen::Map<const fsim::Coeffs>(c);
}

}  // namespace fsim_test
