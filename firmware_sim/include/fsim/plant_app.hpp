// fsim/plant_app.hpp - the plant process: plant + sensors + DBW unit + lap monitor on a CAN bus,
// with fault injection on the bus, real-time pacing or lock-step with the controller, and the
// run's metrics, trajectory and state snapshots as files. Configured by one JSON document (written
// by `ddyn sil run`, format in docs/sil.md).
#pragma once

#include <nlohmann/json.hpp>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include "fsim/bus.hpp"
#include "fsim/dbw_unit.hpp"
#include "fsim/frame_auth.hpp"
#include "fsim/lap_monitor.hpp"
#include "fsim/plant.hpp"
#include "fsim/sensors.hpp"
#include "fsim/track.hpp"

namespace fsim {

// Faults injected on the bus by the plant, in both directions (the plant knows the simulated time).
struct BusFaults {
  double drop = 0.0;       // fraction of frames lost
  double delay_max = 0.0;  // s: each frame is held back uniformly in [0, delay_max]
  double corrupt = 0.0;    // fraction of frames whose checksum byte is damaged
};

struct PlantAppConfig {
  std::string vehicle = "orca_1_43";
  Coeffs coeffs = Coeffs::Zero();
  ActuatorLimits limits;
  PlantEffects effects;
  double substep = 1e-3;      // s: RK4 sub-step and the plant's loop period
  std::string track_dir, track = "ethzMobil";
  // the road's bank per centre-line point of the track (rad, + to the left; "road_bank"): the plant
  // drives with g sin(bank) at the car's track position; empty: a flat road
  std::vector<double> road_bank;
  // the road's grade per centre-line point (rad, + uphill in the direction of travel; "road_grade"): the
  // plant drives with -g sin(grade) at the car's track position; empty: a level road
  std::vector<double> road_grade;
  Footprint footprint;
  State start = State::Zero();
  int laps = 1;
  double max_time = 60.0;     // s of simulated time
  double max_off_track = 0.5; // m: a corner this far outside ends the run
  double realtime_factor = 1.0;    // > 0: paced at this multiple of real time; 0: lock-step;
                                   // < 0: free-running (in-process tests drive both sides)
  double start_timeout = 0.0;      // s (wall): the same wait before the first command (a starting controller); 0: lockstep_timeout
  double lockstep_timeout = 3.0;   // s (wall): lock-step wait for a command after a GNSS frame; after
                                   // one timeout no more waits until a command arrives again
  std::array<SensorConfig, DDYN_MEAS_COUNT> sensors{};
  double status_rate = 100.0;      // Hz: DBW_Status
  unsigned seed = 1;
  DbwConfig dbw;
  BusFaults faults;
  std::string out_dir = ".";
  double log_period = 0.01;        // s between trajectory rows
  std::string resume;              // snapshot to resume from (plant restart)
  double snapshot_period = 0.05;   // s between state snapshots (0: none)
  double crash_at = -1.0;          // s: fault scenario, the process ends abruptly (exit 3) here
  // frame authentication (docs/can.md): the key file ("auth": {"key_file": PATH}, else
  // $DDYN_DBW_KEY_FILE); none: off. With a key the plant signs every frame it sends and applies
  // only commands whose authenticator verifies.
  std::string auth_key_file;

  static PlantAppConfig from_json(const nlohmann::json& j);
};

struct PlantRunResult {
  std::string end_reason;
  nlohmann::json metrics;
};

class PlantApp {
 public:
  PlantApp(const PlantAppConfig& cfg, Bus& bus);
  // one plant period; false when the run has ended (reason in end_reason())
  bool step();
  PlantRunResult run();  // until the end; writes plant_metrics.json, trajectory.csv in out_dir
  void write_trajectory() const;
  nlohmann::json metrics() const;

  const Plant& plant() const { return plant_; }
  const DbwUnit& dbw() const { return dbw_; }
  const LapMonitor& monitor() const { return monitor_; }
  const Track& track() const { return track_; }
  const std::string& end_reason() const { return end_reason_; }

 private:
  struct Held {
    double release;
    CanFrame frame;
  };
  // the bus faults on one frame: false when it is dropped or held back; *damaged when its checksum was hit
  bool answered_position(const CanFrame& f);  // a position frame the controller will answer (lock-step)
  bool faulty(CanFrame& f, std::vector<Held>& queue, double t, long& dropped, long& corrupted, bool* damaged = nullptr);
  void handle_command(const CanFrame& f, double t);
  // the bus faults on a pair (frame + its authenticator): the authenticator shares its frame's fate;
  // true when the frame went out now (not dropped, not held back)
  bool send_pair(CanFrame f, double t, bool* damaged);
  void emit(double t_prev, double t);
  void snapshot(double t) const;
  void restore(const std::string& path);
  void log_row(std::FILE* out) const;

  PlantAppConfig cfg_;
  Bus& bus_;
  Track track_;
  Plant plant_;
  SensorSuite sensors_;
  DbwUnit dbw_;
  LapMonitor monitor_;
  CommandDecoder decoder_;
  FeedbackEncoder encoder_;
  std::optional<FrameAuth> auth_;
  struct Fate {
    bool sent = true;
    bool held = false;
    double release = 0.0;
  } last_rx_fate_;  // what the bus did to the last received frame (its authenticator follows it)
  std::mt19937_64 fault_rng_;
  std::uniform_real_distribution<double> uni_{0.0, 1.0};
  std::vector<Held> rx_held_, tx_held_;
  std::vector<Measurement> meas_;
  long frames_sent_ = 0, frames_received_ = 0, commands_ok_ = 0, lockstep_timeouts_ = 0;
  long rx_dropped_ = 0, rx_corrupted_ = 0, tx_dropped_ = 0, tx_corrupted_ = 0;
  std::array<long, 7> rejected_{};
  bool gnss_sent_ = false, ended_ = false, controller_quiet_ = false;
  int last_position_counter_ = -1;  // the last position frame lock-step waited for (answered_position)
  std::vector<CanFrame> last_sent_;  // this period's frames, sent again while the controller is starting
  std::string end_reason_;
  double wall_start_ = 0.0, t_start_ = 0.0, last_log_ = -1e9, last_snapshot_ = -1e9, wall_elapsed_ = 0.0;
  double sum_speed_dt_ = 0.0, time_driving_ = 0.0;
  std::vector<std::array<double, 14>> trajectory_;
};

}  // namespace fsim
