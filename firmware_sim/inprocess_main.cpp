// ddyn_sil_inprocess: the same plant and controller node in ONE process, frames through memory.
// usage: ddyn_sil_inprocess PLANT.json CONTROLLER.json
//
// CONTROLLER.json is ddyn_controller's configuration (controller/controller_config.h), read by the
// same parser; its CAN, real-time and telemetry.lcm_url settings do not apply here (no socket, no
// scheduling, no LCM), the rest does, including the checkpoint check and control.prepare (the MPC's
// preparation after each command, as in ddyn_controller).
//
// Not the SIL path (that is two processes over vcan): a development and measurement aid. It runs
// at the host's native speed with no emulator in between, so its controller loop times are those
// of this machine's CPU, and it needs no vcan. Lock-step by construction: one controller period per
// position frame. Writes the same files as the two processes (plant_metrics.json, trajectory.csv,
// controller_metrics.json, controller_log.csv). A restarting plant is not supported here.
//
// Frame authentication (docs/can.md): the plant signs and verifies with PLANT.json's key ("auth":
// {"key_file"}, else $DDYN_DBW_KEY_FILE), the controller node with CONTROLLER.json's (can.key_file,
// else $DDYN_DBW_KEY_FILE) exactly as in ddyn_controller: the plant's frames reach the node's
// checks only once their authenticator verifies (receive time: the plant's simulated time), and
// each command goes out with its authenticator. --inject-forged-steering T0:T1 plays an attacker
// on the bus from T0 to T1 s of simulated time: after every genuine command it sends a forged
// DBW_Command (full steering left, full throttle, the next counter, a valid CRC) with an
// authenticator made without the key; the plant's metrics count what its DBW unit refused ("auth")
// and the lap's violations, controller_metrics.json "auth" the controller's side and the count of
// forged commands sent.
#include <algorithm>
#include <chrono>
#include <deque>
#include <cmath>
#include <string>
#include <cstdio>
#include <fstream>
#include <memory>
#include <vector>

#include "controller_config.h"
#include "fsim/plant_app.hpp"

extern "C" const ddyn_net_tables ddyn_net_weights;

namespace {

double now_s() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

uint64_t sim_us(double t) { return t > 0.0 ? static_cast<uint64_t>(std::llround(t * 1e6)) : 0u; }

}  // namespace

// the attacker's frames: a forged command (valid counter and CRC) and an authenticator without the key
void forged_steering(uint8_t counter, std::deque<fsim::CanFrame>& q) {
  ddyn_dbw_signals s{};
  s.command.throttle = 1.0;
  s.command.brake = 0.0;
  s.command.steering = 0.6;
  s.command.enable = true;
  s.command.mode = DDYN_DBW_MODE_AUTONOMOUS;
  fsim::CanFrame f, a;
  f.id = ddyn_dbw_frame_id(DDYN_DBW_FRAME_COMMAND);
  f.dlc = 8;
  (void)ddyn_dbw_encode(DDYN_DBW_FRAME_COMMAND, &s, counter, f.data.data());
  uint8_t guess[DDYN_DBW_AUTH_KEY_LEN];
  for (unsigned i = 0; i < DDYN_DBW_AUTH_KEY_LEN; ++i) guess[i] = static_cast<uint8_t>(0xA5u ^ i);
  a.id = ddyn_dbw_auth_id(DDYN_DBW_FRAME_COMMAND);
  a.dlc = 8;
  // a freshness value ahead of any the controller has used, so that only the MAC can refuse it
  (void)ddyn_dbw_auth_encode(guess, DDYN_DBW_FRAME_COMMAND, f.data.data(), (1u << 20) + counter, counter, a.data.data());
  q.push_back(f);
  q.push_back(a);
}

int main(int argc, char** argv) {
  double inject_from = -1.0, inject_to = -1.0;
  if (argc == 5 && std::string(argv[3]) == "--inject-forged-steering" &&
      std::sscanf(argv[4], "%lf:%lf", &inject_from, &inject_to) == 2 && inject_from >= 0.0 && inject_to > inject_from) {
    argc = 3;
  }
  if (argc != 3) {
    std::fprintf(stderr, "usage: %s PLANT.json CONTROLLER.json [--inject-forged-steering T0:T1]\n", argv[0]);
    return 2;
  }
  try {
    std::ifstream in(argv[1]);
    if (!in) throw std::runtime_error(std::string("cannot read config ") + argv[1]);
    auto cfg = fsim::PlantAppConfig::from_json(nlohmann::json::parse(in));
    if (cfg.crash_at >= 0.0) throw std::runtime_error("a restarting plant needs the two-process run");
    cfg.realtime_factor = -1.0;  // free-running: this loop drives both sides
    auto setup = std::make_unique<ddyn_app_config>();
    char err[DDYN_APP_ERROR_LEN];
    if (!ddyn_app_config_read(argv[2], setup.get(), err)) {
      std::fprintf(stderr, "ddyn_sil_inprocess: %s\n", err);
      return 2;
    }
    auto node = std::make_unique<ddyn_sil_node>();
    if (ddyn_app_node_init(node.get(), setup.get(), &ddyn_net_weights) != DDYN_OK) return 2;

    fsim::MemoryLink link;
    fsim::MemoryBus plant_end(link, true);
    fsim::PlantApp app(cfg, plant_end);
    long injected = 0;
    if (setup->log[0] == '\0') throw std::runtime_error("the configuration names no telemetry.log");
    std::FILE* log = std::fopen(setup->log, "w");
    if (log == nullptr) throw std::runtime_error(std::string("cannot write ") + setup->log);
    std::fprintf(log, "step,wall,start,loop_us,prepare_us,status,trigger,safe,stale,overrun,throttle_cmd,steering_cmd,"
                      "x,y,yaw,vx,vy,omega,throttle,steering,P0,P1,P2,P3,P4,P5,P6,P7," DDYN_SIL_LOG_READINGS_HEADER "\n");
    std::vector<double> loop_us, prep_us;
    std::array<long, DDYN_CTRL_STATUS_BITS> status_count{};
    long misses = 0;
    bool alive = true;
    const double wall0 = now_s();
    while (app.step()) {
      auto& q = link.a_to_b;
      const double t_bus = app.plant().time();
      while (!q.empty()) {
        fsim::CanFrame f = q.front();
        q.pop_front();
        if (!alive) continue;
        // the node authenticates (can.key_file): a frame is held until its authenticator verifies
        const int runs = ddyn_sil_node_on_frame_at(node.get(), f.id, f.data.data(), f.dlc, sim_us(t_bus));
        for (int r = 0; r < runs && alive; ++r) {
          if (node->steps == setup->die_at_step) {
            alive = false;  // the controller "dies": no more commands
            continue;
          }
          ddyn_sil_period per;
          const double t0 = now_s();
          ddyn_sil_node_period(node.get(), &per);
          const double t1 = now_s();
          // as ddyn_controller: the preparation for the next period once the command is out
          if (setup->prepare) (void)ddyn_ctrl_prepare(&node->ctl);
          const double t2 = now_s();
          loop_us.push_back((t1 - t0) * 1e6);
          prep_us.push_back((t2 - t1) * 1e6);
          const bool overrun = (t1 - t0) > setup->period;
          misses += overrun ? 1 : 0;
          for (int k = 0; k < DDYN_CTRL_STATUS_BITS; ++k) status_count[k] += (per.out.status >> k) & 1u;
          std::fprintf(log, "%ld,%.6f,%.9f,%.2f,%.2f,%u,1,%d,%d,%d,%.6f,%.6f", node->steps - 1, t1 - wall0, t0 - wall0,
                       loop_us.back(),
                       prep_us.back(), static_cast<unsigned>(per.out.status), per.safe, per.stale, overrun ? 1 : 0,
                       per.throttle, per.steering);
          for (int k = 0; k < DDYN_NX; ++k) std::fprintf(log, ",%.6g", per.out.x_est[k]);
          for (int k = 0; k < DDYN_NX; ++k) std::fprintf(log, ",%.6g", node->ctl.ekf.P[k * DDYN_NX + k]);
          double raw[DDYN_SIL_LOG_READINGS];
          ddyn_sil_log_readings(&per, raw);
          for (double r : raw) std::fprintf(log, ",%.6g", r);
          std::fputc('\n', log);
          fsim::CanFrame cmd;
          cmd.id = per.can_id;
          cmd.dlc = 8;
          std::copy(per.data, per.data + 8, cmd.data.begin());
          link.b_to_a.push_back(cmd);
          if (per.has_auth) {
            fsim::CanFrame a;
            a.id = per.auth_can_id;
            a.dlc = 8;
            std::copy(per.auth_data, per.auth_data + 8, a.data.begin());
            link.b_to_a.push_back(a);
          }
          if (t_bus >= inject_from && t_bus <= inject_to) {
            forged_steering(static_cast<uint8_t>((cmd.data[6] >> 4) + 1u), link.b_to_a);
            ++injected;
          }
        }
      }
    }
    std::fclose(log);
    app.run();  // already ended: writes the plant's files
    std::vector<double> sorted = loop_us;
    std::sort(sorted.begin(), sorted.end());
    const size_t n = sorted.size();
    nlohmann::json m;
    m["steps"] = node->steps;
    m["period"] = setup->period;
    m["loop_us"] = {{"median", n ? sorted[n / 2] : 0.0},
                    {"p99", n ? sorted[static_cast<size_t>(0.99 * static_cast<double>(n - 1))] : 0.0},
                    {"max", n ? sorted[n - 1] : 0.0}};
    std::sort(prep_us.begin(), prep_us.end());
    m["prepare_us"] = {{"median", n ? prep_us[n / 2] : 0.0},
                       {"p99", n ? prep_us[static_cast<size_t>(0.99 * static_cast<double>(n - 1))] : 0.0},
                       {"max", n ? prep_us[n - 1] : 0.0}};
    m["overruns"] = {{"periods", misses}, {"skipped_deadlines", 0}};
    m["deadline_misses"] = misses;
    m["safe_steps"] = node->safe_steps;
    m["timer_steps"] = 0;
    m["first_safe_latency"] = -1.0;
    m["first_stale_latency"] = -1.0;
    m["frames"] = {{"ok", node->frames_ok}, {"lost", node->frames_lost}, {"repeated_counter", node->repeated_counter},
                   {"late", node->late}, {"unknown_id", node->unknown_id}, {"bad_length", node->bad_length},
                   {"checksum", node->checksum}, {"range", node->range}, {"send_failed", 0}};
    nlohmann::json counts;
    for (int k = 0; k < DDYN_CTRL_STATUS_BITS; ++k) counts[ddyn_ctrl_status_name(1u << k)] = status_count[k];
    m["status_counts"] = counts;
    static const char* const names[DDYN_MEAS_COUNT] = DDYN_MEAS_NAMES;
    for (int k = 0; k < DDYN_MEAS_COUNT; ++k) {
      m["sensor_rejected"][names[k]] = node->ctl.rejected_count[k];
      m["sensor_nonfinite"][names[k]] = node->ctl.nonfinite_count[k];
    }
    m["fixed_coefficients"] = setup->fixed != 0;
    m["checkpoint_hash"] = ddyn_net_weights.checkpoint_sha256 != nullptr ? ddyn_net_weights.checkpoint_sha256 : "";
    m["where"] = "in-process (host CPU, frames through memory)";
    m["auth"] = {{"enabled", node->auth_on != 0},
                 {"accepted", node->auth_accepted},
                 {"forged", node->auth_forged},
                 {"replayed", node->auth_replayed},
                 {"stale", node->auth_stale},
                 {"forged_commands_injected", injected}};
    if (alive) std::ofstream(setup->metrics) << m.dump(2) << "\n";  // a dead controller writes nothing
    std::printf("in-process: %s, %zu controller periods, loop median %.0f us\n", app.end_reason().c_str(), n,
                n ? sorted[n / 2] : 0.0);
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "ddyn_sil_inprocess: error: %s\n", e.what());
    return 2;
  }
}
