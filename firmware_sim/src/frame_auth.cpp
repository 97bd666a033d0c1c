#include "fsim/frame_auth.hpp"

#include <cmath>
#include <stdexcept>

extern "C" {
#include "dbw_auth_key.h"
}

namespace fsim {
namespace {

uint64_t to_us(double t) { return t > 0.0 ? static_cast<uint64_t>(std::llround(t * 1e6)) : 0u; }

int stream_of(uint32_t auth_id) {
  return auth_id == ddyn_dbw_auth_id(DDYN_DBW_FRAME_COMMAND) ? 0 : auth_id == ddyn_dbw_auth_id(DDYN_DBW_FRAME_STEERING) ? 1 : 2;
}

}  // namespace

FrameAuth::FrameAuth(const uint8_t key[DDYN_DBW_AUTH_KEY_LEN], uint32_t monitored) : monitored_(monitored) {
  ddyn_dbw_auth_init(&auth_, key, 0u);
}

std::optional<FrameAuth> FrameAuth::from_key_file(const std::string& configured, uint32_t monitored) {
  const char* path = ddyn_dbw_auth_key_path(configured.c_str());
  if (path == nullptr) return std::nullopt;
  uint8_t key[DDYN_DBW_AUTH_KEY_LEN];
  const char* why = nullptr;
  if (ddyn_dbw_auth_read_key_file(path, key, &why) != DDYN_OK)
    throw std::runtime_error(std::string("drive-by-wire key file ") + path + ": " + (why ? why : "unreadable"));
  FrameAuth a(key, monitored);
  for (auto& b : key) b = 0;
  return a;
}

CanFrame FrameAuth::sign(const CanFrame& f) {
  const int frame = ddyn_dbw_frame_of_id(f.id);
  if (frame < 0) throw std::logic_error("FrameAuth::sign: not a frame of the protocol");
  const ddyn_dbw_frame fr = static_cast<ddyn_dbw_frame>(frame);
  CanFrame a;
  a.id = ddyn_dbw_auth_id(fr);
  a.dlc = 8;
  const int k = stream_of(a.id);
  (void)ddyn_dbw_auth_sign(&auth_, fr, f.data.data(), tx_freshness_[frame], tx_counter_[k], a.data.data());
  tx_counter_[k] = static_cast<uint8_t>((tx_counter_[k] + 1u) % 16u);
  ++tx_freshness_[frame];
  return a;
}

FrameAuth::Freshness FrameAuth::freshness() const {
  Freshness s;
  for (unsigned i = 0; i < DDYN_DBW_FRAME_COUNT; ++i) {
    s.tx[i] = tx_freshness_[i];
    s.rx[i] = auth_.rx_freshness[i];
    s.rx_valid[i] = auth_.rx_freshness_valid[i];
  }
  return s;
}

void FrameAuth::restore_freshness(const Freshness& saved, uint64_t tx_margin) {
  for (unsigned i = 0; i < DDYN_DBW_FRAME_COUNT; ++i) {
    tx_freshness_[i] = saved.tx[i] > UINT64_MAX - tx_margin ? UINT64_MAX : saved.tx[i] + tx_margin;
    auth_.rx_freshness[i] = saved.rx[i];
    auth_.rx_freshness_valid[i] = saved.rx_valid[i];
  }
}

FrameAuth::Verdict FrameAuth::on_frame(const CanFrame& f, double t, CanFrame* released) {
  if (ddyn_dbw_is_authenticator_id(f.id)) {
    ddyn_dbw_frame frame = DDYN_DBW_FRAME_COUNT;
    uint8_t data[8];
    uint64_t t_data = 0;
    const ddyn_dbw_failure kind = ddyn_dbw_auth_verify(&auth_, f.id, f.data.data(), f.dlc, to_us(t), &frame, data, &t_data);
    if (kind == DDYN_DBW_FAIL_COUNT) {
      ++accepted_;
      if (released) {
        released->id = ddyn_dbw_frame_id(frame);
        released->dlc = 8;
        std::copy(data, data + 8, released->data.begin());
      }
      return Verdict::kAccepted;
    }
    // an authenticator for a frame this node does not monitor (another node's pair) is not its business
    if (static_cast<unsigned>(frame) < DDYN_DBW_FRAME_COUNT && !(monitored_ & (1u << frame))) return Verdict::kPassThrough;
    if (kind == DDYN_DBW_FAIL_AUTH_REPLAY) {
      ++replayed_;
      return Verdict::kReplay;
    }
    if (kind == DDYN_DBW_FAIL_AUTH_STALE) {
      ++stale_;
      return Verdict::kStale;
    }
    ++forged_;
    return Verdict::kForged;
  }
  const int frame = ddyn_dbw_frame_of_id(f.id);
  // only a good frame is held: a damaged one is the decoder's to refuse and count
  if (frame < 0 || !(monitored_ & (1u << frame)) || f.dlc != 8 || dbc_checksum(f.id, f.data.data()) != f.data[7])
    return Verdict::kPassThrough;
  if (ddyn_dbw_auth_hold(&auth_, static_cast<ddyn_dbw_frame>(frame), f.data.data(), to_us(t))) ++stale_;
  return Verdict::kHeld;
}

int FrameAuth::expire(double t) {
  const int n = static_cast<int>(ddyn_dbw_auth_expire(&auth_, to_us(t), nullptr));
  stale_ += n;
  return n;
}

}  // namespace fsim
