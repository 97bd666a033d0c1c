#include "fsim/plant_app.hpp"

#include <chrono>
#include <cmath>
#include <cstdlib>
#include <cstdio>
#include <fstream>
#include <stdexcept>
#include <thread>

#include "ddyn_models.h"

extern "C" {
#include "ddyn_can.h"
}

namespace fsim {
namespace {

const char* kSensorNames[DDYN_MEAS_COUNT] = DDYN_MEAS_NAMES;

// Frame authentication across a restart (docs/sil.md): the snapshot holds the transmit freshness values
// as they were when it was written, but the plant went on sending until it died (up to one snapshot
// period, 50 ms: 5 frames of a 100 Hz identifier, a few more with the start-up re-sends), and the
// controller accepted those. A restarted plant therefore resumes each value this far ahead, so none is
// sent twice (a reused value is a replay to the controller). 1024 frames is 10 s of a 100 Hz frame:
// far more than a snapshot period, and far below half the 22-bit freshness window (2^21) inside which
// the controller reconstructs the full value as newer; the values skipped cost nothing.
constexpr uint64_t kFreshnessResumeMargin = 1024;

double wall_now() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

const ddyn_vehicle_model* find_model(const std::string& name) {
  const ddyn_vehicle_model* m = ddyn_model_find(name.c_str());
  if (m == nullptr) throw std::runtime_error("no generated model for vehicle '" + name + "' (run ddyn codegen model)");
  return m;
}

// DBW_Status fault bits (can/ddyn_dbw.dbc): 0 timeout, 1 counter, 2 checksum, 3 range
uint8_t fault_bit(CommandCheck c) {
  switch (c) {
    case CommandCheck::kRepeatedCounter:
    case CommandCheck::kStaleCounter: return 1u << 1;
    case CommandCheck::kBadChecksum: return 1u << 2;
    case CommandCheck::kOutOfRange: return 1u << 3;
    default: return 0;
  }
}

template <typename T>
void get_if(const nlohmann::json& j, const char* key, T& v) {
  if (j.contains(key)) v = j.at(key).get<T>();
}

}  // namespace

PlantAppConfig PlantAppConfig::from_json(const nlohmann::json& j) {
  PlantAppConfig c;
  get_if(j, "vehicle", c.vehicle);
  const auto coeffs = j.at("coefficients").get<std::vector<double>>();
  if (coeffs.size() != DDYN_NC) throw std::runtime_error("config: coefficients must have 17 values");
  for (int i = 0; i < DDYN_NC; ++i) c.coeffs[i] = coeffs[i];
  if (j.contains("limits")) {
    const auto& l = j.at("limits");
    get_if(l, "throttle_min", c.limits.throttle_min);
    get_if(l, "throttle_max", c.limits.throttle_max);
    get_if(l, "steer_min", c.limits.steer_min);
    get_if(l, "steer_max", c.limits.steer_max);
    get_if(l, "dthrottle_max", c.limits.dthrottle_max);
    get_if(l, "dsteer_max", c.limits.dsteer_max);
  }
  if (j.contains("effects")) {
    const auto& e = j.at("effects");
    for (auto it = e.begin(); it != e.end(); ++it) {
      const double v = it.value().get<double>();
      if (it.key() == "steer_delay") c.effects.steer_delay = v;
      else if (it.key() == "throttle_delay") c.effects.throttle_delay = v;
      else if (it.key() == "steer_lag") c.effects.steer_lag = v;
      else if (it.key() == "mass_offset") c.effects.mass_offset = v;
      else if (it.key() == "downforce") c.effects.downforce = v;
      else if (it.key() == "yaw_rate_bias") c.effects.yaw_rate_bias = v;
      else throw std::runtime_error("config: effect '" + it.key() + "' is not offered by the plant "
                                    "(steer_delay, throttle_delay, steer_lag, mass_offset, downforce, yaw_rate_bias)");
    }
  }
  get_if(j, "substep", c.substep);
  c.track_dir = j.at("track_dir").get<std::string>();
  get_if(j, "track", c.track);
  if (j.contains("road_bank")) {
    c.road_bank = j.at("road_bank").get<std::vector<double>>();
    for (double b : c.road_bank)
      if (!std::isfinite(b) || std::fabs(b) >= 1.5707963267948966)
        throw std::runtime_error("config: road_bank must hold finite angles within +-pi/2 rad");
  }
  if (j.contains("road_grade")) {
    c.road_grade = j.at("road_grade").get<std::vector<double>>();
    for (double g : c.road_grade)
      if (!std::isfinite(g) || std::fabs(g) >= 1.5707963267948966)
        throw std::runtime_error("config: road_grade must hold finite angles within +-pi/2 rad");
  }
  if (j.contains("footprint")) {
    c.footprint.length = j.at("footprint").at("length").get<double>();
    c.footprint.width = j.at("footprint").at("width").get<double>();
  }
  const auto start = j.at("start").get<std::vector<double>>();
  if (start.size() != DDYN_NX) throw std::runtime_error("config: start must have 8 values");
  for (int i = 0; i < DDYN_NX; ++i) c.start[i] = start[i];
  get_if(j, "laps", c.laps);
  get_if(j, "max_time", c.max_time);
  get_if(j, "max_off_track", c.max_off_track);
  get_if(j, "realtime_factor", c.realtime_factor);
  get_if(j, "lockstep_timeout", c.lockstep_timeout);
  get_if(j, "start_timeout", c.start_timeout);
  get_if(j, "status_rate", c.status_rate);
  get_if(j, "seed", c.seed);
  get_if(j, "out_dir", c.out_dir);
  get_if(j, "log_period", c.log_period);
  get_if(j, "resume", c.resume);
  get_if(j, "snapshot_period", c.snapshot_period);
  get_if(j, "crash_at", c.crash_at);
  for (int k = 0; k < DDYN_MEAS_COUNT; ++k) {
    c.sensors[k].enabled = false;
    if (!j.contains("sensors") || !j.at("sensors").contains(kSensorNames[k])) continue;
    const auto& s = j.at("sensors").at(kSensorNames[k]);
    c.sensors[k].enabled = true;
    get_if(s, "rate", c.sensors[k].rate);
    if (s.contains("noise")) {
      const auto n = s.at("noise").get<std::vector<double>>();
      for (size_t i = 0; i < n.size() && i < DDYN_MEAS_MAX_DIM; ++i) c.sensors[k].noise_std[i] = n[i];
    }
    get_if(s, "silent_from", c.sensors[k].silent_from);
    get_if(s, "silent_until", c.sensors[k].silent_until);
  }
  if (j.contains("dbw")) {
    get_if(j.at("dbw"), "deadline", c.dbw.deadline);
    get_if(j.at("dbw"), "rearm_count", c.dbw.rearm_count);
    get_if(j.at("dbw"), "stop_speed", c.dbw.stop_speed);
  }
  c.dbw.brake_throttle = c.limits.throttle_min;
  if (j.contains("auth")) get_if(j.at("auth"), "key_file", c.auth_key_file);
  if (j.contains("faults")) {
    get_if(j.at("faults"), "drop", c.faults.drop);
    get_if(j.at("faults"), "delay_max", c.faults.delay_max);
    get_if(j.at("faults"), "corrupt", c.faults.corrupt);
  }
  const ddyn_vehicle_model* m = find_model(c.vehicle);
  c.footprint.lf = m->known[1];
  c.footprint.lr = m->known[2];
  return c;
}

PlantApp::PlantApp(const PlantAppConfig& cfg, Bus& bus)
    : cfg_(cfg),
      bus_(bus),
      track_(Track::load(cfg.track_dir, cfg.track)),
      plant_(find_model(cfg.vehicle), cfg.coeffs, cfg.limits, cfg.effects, cfg.substep),
      sensors_(cfg.sensors, cfg.effects.yaw_rate_bias, cfg.seed),
      dbw_(cfg.dbw),
      monitor_(track_, cfg.footprint),
      auth_(FrameAuth::from_key_file(cfg.auth_key_file, DDYN_DBW_MONITOR_DBW_UNIT)),
      fault_rng_(cfg.seed * 7919u + 17u) {
  if (!cfg.road_bank.empty() && static_cast<int>(cfg.road_bank.size()) != track_.center().size())
    throw std::runtime_error("config: road_bank has " + std::to_string(cfg.road_bank.size()) +
                             " values, the track's centre line " + std::to_string(track_.center().size()) + " points");
  if (!cfg.road_grade.empty() && static_cast<int>(cfg.road_grade.size()) != track_.center().size())
    throw std::runtime_error("config: road_grade has " + std::to_string(cfg.road_grade.size()) +
                             " values, the track's centre line " + std::to_string(track_.center().size()) + " points");
  plant_.reset(cfg.start, 0.0);
  if (!cfg.resume.empty()) restore(cfg.resume);
  monitor_.update(plant_.time(), plant_.state()[kX], plant_.state()[kY], plant_.state()[kYaw]);
  t_start_ = plant_.time();
  wall_start_ = wall_now();
}

bool PlantApp::answered_position(const CanFrame& f) {
  // the controller answers a position frame only when it is newer than the last one it used (counter
  // 1..8 ahead, mod 16); an older one overtaken on a delaying bus is refused, so lock-step must not
  // wait for an answer to it (another command would then answer it, one period late)
  const int counter = (f.data[6] >> 4) & 0x0F;
  if (last_position_counter_ >= 0) {
    const int step = (counter - last_position_counter_ + 16) % 16;
    if (step == 0 || step > 8) return false;
  }
  last_position_counter_ = counter;
  return true;
}

bool PlantApp::faulty(CanFrame& f, std::vector<Held>& queue, double t, long& dropped, long& corrupted, bool* damaged) {
  // the same draws whatever the fault settings, so a run's noise does not depend on them
  const double u_drop = uni_(fault_rng_), u_corrupt = uni_(fault_rng_), u_delay = uni_(fault_rng_);
  if (u_drop < cfg_.faults.drop) {
    ++dropped;
    return false;
  }
  if (u_corrupt < cfg_.faults.corrupt) {
    f.data[7] ^= 0x5A;
    ++corrupted;
    if (damaged) *damaged = true;
  }
  const double delay = cfg_.faults.delay_max * u_delay;
  if (delay > 0.0) {
    queue.push_back({t + delay, f});
    return false;
  }
  return true;
}

void PlantApp::handle_command(const CanFrame& in, double t) {
  CanFrame f = in;
  if (auth_) {
    // only a command whose authenticator verifies reaches the DBW unit; forged, replayed and stale
    // ones are counted (metrics "auth") and dropped, and do not touch the unit
    switch (auth_->on_frame(in, t, &f)) {
      case FrameAuth::Verdict::kAccepted: break;
      case FrameAuth::Verdict::kPassThrough: break;  // a damaged command (the decoder refuses it) or not ours
      default: return;
    }
  }
  if (f.id != DDYN_CAN_DBW_COMMAND_FRAME_ID) return;  // other nodes' frames
  DbwCommand cmd;
  const CommandCheck check = decoder_.decode(f, cmd);
  if (check == CommandCheck::kOk) {
    ++commands_ok_;
    dbw_.on_valid_command(t, cmd.throttle, cmd.steering);
  } else {
    ++rejected_[static_cast<int>(check)];
    dbw_.on_rejected_command();
  }
}

void PlantApp::emit(double t_prev, double t) {
  meas_.clear();
  sensors_.sample(plant_, t_prev, t, meas_);
  std::vector<CanFrame> out;
  const Measurement* acc = nullptr;
  for (const auto& m : meas_)
    if (m.kind == DDYN_MEAS_ACCELERATION) acc = &m;
  const Measurement* gnss = nullptr;
  for (const auto& m : meas_) {
    switch (m.kind) {
      case DDYN_MEAS_YAW_RATE:
        out.push_back(encoder_.imu(m.value[0], acc ? acc->value[0] : 0.0, acc ? acc->value[1] : 0.0));
        break;
      case DDYN_MEAS_WHEEL_SPEED:
        out.push_back(encoder_.wheel_speeds(m.value[0], m.value[1]));
        break;
      case DDYN_MEAS_STEERING: {
        const double rate = (plant_.steer_target() - plant_.state()[kSteer]) / cfg_.substep;
        out.push_back(encoder_.steering(m.value[0], std::clamp(rate, -cfg_.limits.dsteer_max, cfg_.limits.dsteer_max)));
        break;
      }
      case DDYN_MEAS_HEADING:
        out.push_back(encoder_.gnss_heading(m.value[0]));
        break;
      case DDYN_MEAS_GNSS_POSITION:
        gnss = &m;
        break;
      default:
        break;
    }
  }
  // DBW_Status at its own rate
  const double period = 1.0 / cfg_.status_rate;
  if (std::floor(t / period + 1e-9) > std::floor(t_prev / period + 1e-9)) {
    const int mode = dbw_.mode() == DbwMode::kActive ? DDYN_CAN_DBW_STATUS_MODE_AUTONOMOUS_CHOICE
                     : dbw_.mode() == DbwMode::kSafeStop ? DDYN_CAN_DBW_STATUS_MODE_SAFE_STOP_CHOICE
                                                         : DDYN_CAN_DBW_STATUS_MODE_STANDBY_CHOICE;
    uint8_t faults = dbw_.trips() > 0 ? 1u : 0u;
    for (int c = 0; c < 7; ++c)
      if (rejected_[c] > 0) faults |= fault_bit(static_cast<CommandCheck>(c));
    out.push_back(encoder_.status(plant_.state()[kThrottle], mode, dbw_.mode() == DbwMode::kActive, faults));
  }
  // the position frame goes last: the controller's step follows it
  if (gnss) out.push_back(encoder_.gnss_position(gnss->value[0], gnss->value[1]));
  last_sent_.clear();
  for (auto& f : out) {
    bool damaged = false;
    // a damaged position frame gets no answer: no lock-step wait for it
    if (send_pair(f, t, &damaged) && f.id == DDYN_CAN_GNSS_POSITION_FRAME_ID && !damaged)
      gnss_sent_ = answered_position(f);
  }
}

bool PlantApp::send_pair(CanFrame f, double t, bool* damaged) {
  // the authenticator is computed over the frame as sent, before the bus may damage it
  std::optional<CanFrame> a;
  if (auth_) a = auth_->sign(f);
  const size_t held_before = tx_held_.size();
  if (faulty(f, tx_held_, t, tx_dropped_, tx_corrupted_, damaged)) {
    bus_.send(f);
    last_sent_.push_back(f);
    ++frames_sent_;
    if (a) {
      bus_.send(*a);
      last_sent_.push_back(*a);
      ++frames_sent_;
    }
    return true;
  }
  if (a && tx_held_.size() > held_before) {
    tx_held_.push_back({tx_held_.back().release, *a});  // delayed with its frame, released right after it
  }
  return false;
}

bool PlantApp::step() {
  if (ended_) return false;
  const double t = plant_.time();
  gnss_sent_ = false;
  // 1. commands in (with the bus faults), then the ones held back whose time has come
  CanFrame f;
  while (bus_.receive(f, 0)) {
    ++frames_received_;
    if (f.id == DDYN_CAN_DBW_COMMAND_FRAME_ID) controller_quiet_ = false;
    if (auth_ && ddyn_dbw_is_authenticator_id(f.id)) {
      // an authenticator shares the fate of the frame before it (the pair is one transmission)
      if (last_rx_fate_.sent) handle_command(f, t);
      else if (last_rx_fate_.held) rx_held_.push_back({last_rx_fate_.release, f});
      continue;
    }
    const size_t held_before = rx_held_.size();
    last_rx_fate_ = Fate{};
    last_rx_fate_.sent = faulty(f, rx_held_, t, rx_dropped_, rx_corrupted_);
    if (!last_rx_fate_.sent && rx_held_.size() > held_before) {
      last_rx_fate_.held = true;
      last_rx_fate_.release = rx_held_.back().release;
    }
    if (last_rx_fate_.sent) handle_command(f, t);
  }
  for (size_t i = 0; i < rx_held_.size();) {
    if (rx_held_[i].release <= t) {
      handle_command(rx_held_[i].frame, t);
      rx_held_.erase(rx_held_.begin() + static_cast<long>(i));
    } else {
      ++i;
    }
  }
  if (auth_) auth_->expire(t);  // commands whose authenticator never came: stale, dropped
  // 2. the DBW unit drives the actuators
  const DbwOutput out = dbw_.update(t, plant_.state()[kVx]);
  plant_.set_command(out.throttle, out.steering);
  plant_.set_hold(out.hold);
  // 3. physics (the road's bank at the car's track position, held over the sub-step)
  if (!cfg_.road_bank.empty()) plant_.set_road_bank(track_.interpolate(cfg_.road_bank, monitor_.s()));
  if (!cfg_.road_grade.empty()) plant_.set_road_grade(track_.interpolate(cfg_.road_grade, monitor_.s()));
  plant_.advance(cfg_.substep);
  const double t1 = plant_.time();
  const State& x = plant_.state();
  monitor_.update(t1, x[kX], x[kY], x[kYaw]);
  if (dbw_.mode() == DbwMode::kActive) {
    sum_speed_dt_ += std::hypot(x[kVx], x[kVy]) * cfg_.substep;
    time_driving_ += cfg_.substep;
  }
  // 4. sensors and feedback out; held-back frames whose time has come
  emit(t, t1);
  for (size_t i = 0; i < tx_held_.size();) {
    if (tx_held_[i].release <= t1) {
      bus_.send(tx_held_[i].frame);
      ++frames_sent_;
      const CanFrame& h = tx_held_[i].frame;
      if (h.id == DDYN_CAN_GNSS_POSITION_FRAME_ID && dbc_checksum(h.id, h.data.data()) == h.data[7])
        gnss_sent_ = gnss_sent_ || answered_position(h);
      tx_held_.erase(tx_held_.begin() + static_cast<long>(i));
    } else {
      ++i;
    }
  }
  // 5. records
  if (t1 - last_log_ >= cfg_.log_period - 1e-9) {
    last_log_ = t1;
    const auto& r = monitor_.result();
    trajectory_.push_back({t1, x[kX], x[kY], x[kYaw], x[kVx], x[kVy], x[kOmega], x[kThrottle], x[kSteer],
                           r.progress, monitor_.clearance(), static_cast<double>(dbw_.mode()),
                           static_cast<double>(monitor_.laps_completed()), out.steering});
  }
  if (cfg_.snapshot_period > 0.0 && t1 - last_snapshot_ >= cfg_.snapshot_period - 1e-9) {
    last_snapshot_ = t1;
    snapshot(t1);
  }
  if (cfg_.crash_at >= 0.0 && t1 >= cfg_.crash_at && cfg_.resume.empty()) {
    // fault scenario: the plant process dies; what it logged so far and its last snapshot survive
    write_trajectory();
    std::fflush(nullptr);
    std::_Exit(3);
  }
  // 6. end of the run
  if (monitor_.laps_completed() >= cfg_.laps) end_reason_ = "laps_completed";
  else if (t1 >= cfg_.max_time) end_reason_ = "max_time";
  else if (monitor_.clearance() < -cfg_.max_off_track) end_reason_ = "left_the_track";
  else if (dbw_.stopped_time() >= 0.0 && t1 - dbw_.stopped_time() > 0.5) end_reason_ = "safe_stop";
  ended_ = !end_reason_.empty();
  // 7. pacing: real time (scaled), or lock-step with the controller after each position frame
  if (cfg_.realtime_factor > 0.0) {
    const double due = wall_start_ + (t1 - t_start_) / cfg_.realtime_factor;
    const double now = wall_now();
    if (due > now) std::this_thread::sleep_for(std::chrono::duration<double>(due - now));
  } else if (cfg_.realtime_factor == 0.0 && gnss_sent_ && !controller_quiet_) {
    // until the first command the controller may still be starting (seconds in an emulated guest) and
    // may have missed this period's frames: a car on a rolling start would coast off the track if the
    // plant went on without it, so the first wait is up to start_timeout and the frames are sent again
    // every half second (a controller that got them counts a repeated counter and ignores them)
    const bool starting = commands_ok_ == 0 && cfg_.start_timeout > 0.0;
    const double deadline = wall_now() + (starting ? std::max(cfg_.lockstep_timeout, cfg_.start_timeout)
                                                   : cfg_.lockstep_timeout);
    double resend = wall_now() + 0.5;
    bool got = false;
    while (!got) {
      const double now = wall_now();
      const double left = deadline - now;
      if (left <= 0.0) break;
      const double slice = starting ? std::min(left, std::max(resend - now, 0.0)) : left;
      if (!bus_.receive(f, static_cast<long>(slice * 1e6))) {
        if (!starting) break;
        if (wall_now() >= resend) {
          for (const auto& g : last_sent_) bus_.send(g);
          frames_sent_ += static_cast<long>(last_sent_.size());
          resend = wall_now() + 0.5;
        }
        continue;
      }
      ++frames_received_;
      // with authentication the answer is complete with the command's authenticator, which follows it
      got = f.id == (auth_ ? ddyn_dbw_auth_id(DDYN_DBW_FRAME_COMMAND) : DDYN_CAN_DBW_COMMAND_FRAME_ID);
      // handled at the start of the next period, like any frame that arrived during this one
      if (faulty(f, rx_held_, t1, rx_dropped_, rx_corrupted_)) rx_held_.push_back({t1, f});
    }
    if (!got) {
      // a controller that does not answer within the timeout is gone or hung: stop waiting for it
      // (a late answer would pair every later command with the wrong period) until it speaks again
      ++lockstep_timeouts_;
      controller_quiet_ = true;
    }
  }
  wall_elapsed_ = wall_now() - wall_start_;
  return !ended_;
}

nlohmann::json PlantApp::metrics() const {
  const auto& r = monitor_.result();
  nlohmann::json j;
  j["end_reason"] = end_reason_;
  j["sim_time"] = plant_.time();
  j["wall_time"] = wall_elapsed_;
  j["laps_completed"] = monitor_.laps_completed();
  j["lap_times"] = r.lap_times;
  j["violations"] = r.violations;
  j["time_outside"] = r.time_outside;
  j["worst_clearance"] = r.worst_clearance;
  j["progress"] = r.progress;
  j["distance"] = r.distance;
  j["average_speed"] = time_driving_ > 0.0 ? sum_speed_dt_ / time_driving_ : 0.0;
  j["lap_average_speed"] = nlohmann::json::array();
  // average speed of a lap: the centre line's length over the lap time (as the paper's table)
  for (double lt : r.lap_times) j["lap_average_speed"].push_back(track_.length() / lt);
  j["track_length"] = track_.length();
  j["dbw"] = {{"trips", dbw_.trips()},
              {"first_trip_time", dbw_.first_trip_time()},
              {"first_trip_latency", dbw_.first_trip_latency()},
              {"stopped_time", dbw_.stopped_time()},
              {"deadline", cfg_.dbw.deadline},
              {"commands_ok", commands_ok_},
              {"rejected", {{"wrong_length", rejected_[1]}, {"bad_checksum", rejected_[2]},
                            {"repeated_counter", rejected_[3]}, {"out_of_range", rejected_[4]},
                            {"not_enabled", rejected_[5]}, {"stale_counter", rejected_[6]}}}};
  j["bus"] = {{"frames_sent", frames_sent_}, {"frames_received", frames_received_},
              {"tx_dropped", tx_dropped_}, {"tx_corrupted", tx_corrupted_},
              {"rx_dropped", rx_dropped_}, {"rx_corrupted", rx_corrupted_},
              {"lockstep_timeouts", lockstep_timeouts_}};
  j["auth"] = {{"enabled", auth_.has_value()},
               {"accepted", auth_ ? auth_->accepted() : 0L},
               {"forged", auth_ ? auth_->forged() : 0L},
               {"replayed", auth_ ? auth_->replayed() : 0L},
               {"stale", auth_ ? auth_->stale() : 0L}};
  j["effects"] = {{"steer_delay", cfg_.effects.steer_delay}, {"throttle_delay", cfg_.effects.throttle_delay},
                  {"steer_lag", cfg_.effects.steer_lag}, {"mass_offset", cfg_.effects.mass_offset},
                  {"downforce", cfg_.effects.downforce},
                  {"yaw_rate_bias", cfg_.effects.yaw_rate_bias}};
  j["road_bank"] = !cfg_.road_bank.empty();
  j["road_grade"] = !cfg_.road_grade.empty();
  j["footprint"] = {{"length", cfg_.footprint.length}, {"width", cfg_.footprint.width}};
  return j;
}

void PlantApp::snapshot(double t) const {
  const auto& r = monitor_.result();
  nlohmann::json j;
  j["t"] = t;
  j["state"] = std::vector<double>(plant_.state().data(), plant_.state().data() + DDYN_NX);
  j["s"] = monitor_.s();
  j["lap_start_time"] = monitor_.lap_start_time();
  j["lap_times"] = r.lap_times;
  j["violations"] = r.violations;
  j["time_outside"] = r.time_outside;
  j["worst_clearance"] = r.worst_clearance;
  j["progress"] = r.progress;
  j["distance"] = r.distance;
  if (auth_) {
    // SecOC freshness values survive a reset (non-volatile in a real ECU): a restarted plant that sent
    // from 0 again would have every frame refused as a replay by the controller (docs/sil.md)
    const FrameAuth::Freshness fr = auth_->freshness();
    j["auth_freshness"] = {{"tx", fr.tx}, {"rx", fr.rx}, {"rx_valid", fr.rx_valid}};
  }
  // write-then-rename: a killed plant leaves a whole snapshot behind
  const std::string path = cfg_.out_dir + "/snapshot.json", tmp = path + ".tmp";
  {
    std::ofstream o(tmp);
    o << j.dump();
  }
  std::rename(tmp.c_str(), path.c_str());
}

void PlantApp::restore(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error("cannot read snapshot " + path);
  const nlohmann::json j = nlohmann::json::parse(in);
  const auto sv = j.at("state").get<std::vector<double>>();
  State x;
  for (int i = 0; i < DDYN_NX; ++i) x[i] = sv.at(i);
  const double t = j.at("t").get<double>();
  plant_.reset(x, t);
  LapMonitorResult r;
  r.lap_times = j.at("lap_times").get<std::vector<double>>();
  r.violations = j.at("violations").get<int>();
  r.time_outside = j.at("time_outside").get<double>();
  r.worst_clearance = j.at("worst_clearance").get<double>();
  r.progress = j.at("progress").get<double>();
  r.distance = j.at("distance").get<double>();
  monitor_.restore(t, x[kX], x[kY], j.at("s").get<double>(), j.at("lap_start_time").get<double>(), r);
  if (auth_ && j.contains("auth_freshness")) {
    const auto& a = j.at("auth_freshness");
    FrameAuth::Freshness fr;
    fr.tx = a.at("tx").get<decltype(fr.tx)>();
    fr.rx = a.at("rx").get<decltype(fr.rx)>();
    fr.rx_valid = a.at("rx_valid").get<decltype(fr.rx_valid)>();
    auth_->restore_freshness(fr, kFreshnessResumeMargin);
  }
}

PlantRunResult PlantApp::run() {
  while (step()) {
  }
  PlantRunResult res;
  res.end_reason = end_reason_;
  res.metrics = metrics();
  std::ofstream(cfg_.out_dir + "/plant_metrics.json") << res.metrics.dump(2) << "\n";
  write_trajectory();
  return res;
}

void PlantApp::write_trajectory() const {
  std::FILE* out = std::fopen((cfg_.out_dir + "/trajectory.csv").c_str(), cfg_.resume.empty() ? "w" : "a");
  if (out == nullptr) throw std::runtime_error("cannot write " + cfg_.out_dir + "/trajectory.csv");
  if (cfg_.resume.empty())
    std::fprintf(out, "t,x,y,yaw,vx,vy,omega,throttle,steering,progress,clearance,dbw_mode,laps,steer_cmd\n");
  for (const auto& row : trajectory_) {
    for (size_t i = 0; i < row.size(); ++i) std::fprintf(out, i ? ",%.9g" : "%.9g", row[i]);
    std::fputc('\n', out);
  }
  std::fclose(out);
}

}  // namespace fsim
