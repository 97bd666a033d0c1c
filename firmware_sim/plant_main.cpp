// ddyn_sil_plant: the plant process of the SIL simulator. usage: ddyn_sil_plant CONFIG.json [--can IFACE]
// Plays the car on a SocketCAN interface (vcan0 by default) until the laps are done, the time is up,
// the car left the track or stopped in the safe state; writes plant_metrics.json, trajectory.csv
// and snapshot.json into the config's out_dir. Exit 0 on a finished run, 2 on bad input.
#include <csignal>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <iostream>

#include "fsim/plant_app.hpp"

int main(int argc, char** argv) {
  if (argc < 2 || std::strcmp(argv[1], "--help") == 0) {
    std::fprintf(stderr, "usage: %s CONFIG.json [--can IFACE]\n", argv[0]);
    return 2;
  }
  std::string iface = "vcan0";
  for (int i = 2; i + 1 < argc; ++i)
    if (std::strcmp(argv[i], "--can") == 0) iface = argv[i + 1];
  try {
    std::ifstream in(argv[1]);
    if (!in) throw std::runtime_error(std::string("cannot read config ") + argv[1]);
    const auto cfg = fsim::PlantAppConfig::from_json(nlohmann::json::parse(in));
    auto bus = fsim::open_socketcan(iface);
    fsim::PlantApp app(cfg, *bus);
    const auto res = app.run();
    std::printf("plant: %s after %.3f s simulated: %d lap(s)", res.end_reason.c_str(),
                res.metrics["sim_time"].get<double>(), res.metrics["laps_completed"].get<int>());
    for (double lt : res.metrics["lap_times"]) std::printf(" %.3f s", lt);
    std::printf(", %d violation(s)\n", res.metrics["violations"].get<int>());
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "ddyn_sil_plant: error: %s\n", e.what());
    return 2;
  }
}
