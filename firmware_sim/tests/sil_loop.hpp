// The SIL loop in one process: the plant application on one end of a memory CAN link, the
// controller's CAN node (firmware_sim/controller, the c_src runtime) on the other. Only encoded
// frames cross the link, exactly as over vcan; the plant runs free (no pacing) and the node runs
// one period per GNSS_Position frame, as the controller process does.
#pragma once

#include <memory>

#include "controller_node.h"
#include "fsim/plant_app.hpp"
#include "test_util.hpp"

extern "C" const ddyn_net_tables ddyn_net_weights;

namespace fsim_test {

inline fsim::PlantAppConfig orca_sil_config() {
  fsim::PlantAppConfig c;
  c.vehicle = "orca_1_43";
  c.coeffs = orca_true();
  c.track_dir = shared_data() + "/tracks";
  c.track = "ethzMobil";
  c.footprint = {0.1, 0.05, 0.029, 0.033};
  c.realtime_factor = -1.0;
  c.laps = 1;
  c.max_time = 20.0;
  c.snapshot_period = 0.0;
  c.out_dir = ::testing::TempDir();
  // rates of can/ddyn_dbw.dbc's cycle times
  const double rates[DDYN_MEAS_COUNT] = {50, 50, 100, 100, 100, 100};
  for (int k = 0; k < DDYN_MEAS_COUNT; ++k) c.sensors[k].rate = rates[k];
  c.sensors[DDYN_MEAS_GNSS_POSITION].noise_std = {0.002, 0.002};
  c.sensors[DDYN_MEAS_HEADING].noise_std = {0.01, 0.0};
  c.sensors[DDYN_MEAS_YAW_RATE].noise_std = {0.05, 0.0};
  c.sensors[DDYN_MEAS_WHEEL_SPEED].noise_std = {0.01, 0.01};
  c.sensors[DDYN_MEAS_ACCELERATION].noise_std = {0.1, 0.1};
  c.sensors[DDYN_MEAS_STEERING].noise_std = {0.002, 0.0};
  return c;
}

struct SilLoop {
  fsim::MemoryLink link;
  fsim::MemoryBus plant_end{link, true};
  std::unique_ptr<fsim::PlantApp> app;
  std::unique_ptr<ddyn_sil_node> node = std::make_unique<ddyn_sil_node>();
  bool controller_alive = true;
  long periods = 0;

  explicit SilLoop(fsim::PlantAppConfig cfg) {
    const fsim::Track track = fsim::Track::load(cfg.track_dir, cfg.track);
    // start on the centre line's first point, heading along it, at 0.1 m/s
    const fsim::Vec2 p = track.position(0.0);
    cfg.start = fsim::State::Zero();
    cfg.start << p.x(), p.y(), track.heading_at(0.0), 0.1, 0, 0, 0, 0;
    app = std::make_unique<fsim::PlantApp>(cfg, plant_end);
    ddyn_ctrl_config cc;
    const ddyn_vehicle_model* model = ddyn_model_find("orca_1_43");
    ddyn_ctrl_default_config(model, &cc);
    for (int i = 0; i < DDYN_NC; ++i) cc.c_nominal[i] = cfg.coeffs[i];
    // the filter's measurement noise: the sensors' own
    for (int k = 0; k < DDYN_MEAS_COUNT; ++k)
      for (int i = 0; i < DDYN_MEAS_MAX_DIM; ++i) {
        const double sd = cfg.sensors[k].noise_std[i];
        cc.r_diag[k][i] = sd > 0.0 ? sd * sd : 1e-8;
      }
    const int stale[DDYN_DBW_FRAME_COUNT] = {0, 3, 3, 3, 3, 3, 3};
    double x0[DDYN_NX];
    for (int i = 0; i < DDYN_NX; ++i) x0[i] = cfg.start[i];
    if (ddyn_sil_node_init(node.get(), model, &ddyn_net_weights, &cc, x0, 0.02, stale) != DDYN_OK)
      throw std::runtime_error("node init failed");
    // the centre line as the raceline: 1 m/s, the room to the bounds less half the car's width
    const auto& pts = track.center().points();
    const int n = std::min<int>(static_cast<int>(pts.size()), DDYN_MPC_MAX_TRACK_POINTS);
    std::vector<double> x(n), y(n), v(n, 1.0), wl(n), wr(n);
    for (int i = 0; i < n; ++i) {
      x[i] = pts[i].x();
      y[i] = pts[i].y();
      const auto pr = track.project(pts[i]);
      wl[i] = pr.half_width_left - 0.025;
      wr[i] = pr.half_width_right - 0.025;
    }
    if (ddyn_ctrl_set_track(&node->ctl, n, x.data(), y.data(), v.data(), wl.data(), wr.data()) != DDYN_OK)
      throw std::runtime_error("set_track failed");
  }

  // one plant period, then the controller node reads what arrived and answers a position frame
  bool step() {
    const bool more = app->step();
    auto& q = link.a_to_b;
    while (!q.empty()) {
      const fsim::CanFrame f = q.front();
      q.pop_front();
      if (!controller_alive) continue;
      const int runs = ddyn_sil_node_on_frame(node.get(), f.id, f.data.data(), f.dlc);
      for (int r = 0; r < runs; ++r) {
        ddyn_sil_period per;
        ddyn_sil_node_period(node.get(), &per);
        ++periods;
        fsim::CanFrame cmd;
        cmd.id = per.can_id;
        cmd.dlc = 8;
        std::copy(per.data, per.data + 8, cmd.data.begin());
        link.b_to_a.push_back(cmd);
      }
    }
    return more;
  }
};

}  // namespace fsim_test
