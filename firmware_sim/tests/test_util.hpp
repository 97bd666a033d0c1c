// Helpers shared by the firmware_sim tests.
#pragma once

#include <gtest/gtest.h>

#include <cstdlib>
#include <fstream>
#include <string>

#include "ddyn_models.h"
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

// the paper's ORCA 1:43 car (train/vehicles/orca_1_43.json true_coefficients)
inline fsim::Coeffs orca_true() {
  fsim::Coeffs c;
  c << 5.579, 1.2, 0.192, -0.083, -0.0013, 0.00043, 5.3852, 1.2691, 0.1737, -0.019, -0.00376, 0.00091, 0.287,
      0.0545, 0.0518, 0.00035, 2.78e-05;
  return c;
}

}  // namespace fsim_test
