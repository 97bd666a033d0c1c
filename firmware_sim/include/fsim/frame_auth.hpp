// fsim/frame_auth.hpp - the SecOC-style frame authentication (ddyn/dbw.h, c_src/src/dbw_auth.c) for the
// simulator's side of the bus: sign the frames a node sends (an authenticator frame right after each)
// and hold the frames it relies on until their authenticator verifies. The cryptography and the
// freshness logic are the runtime's (ddyn_dbw_auth_*), not re-written here.
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <string>

#include "fsim/can_codec.hpp"

extern "C" {
#include "ddyn/dbw.h"
}

namespace fsim {

class FrameAuth {
 public:
  enum class Verdict { kPassThrough, kHeld, kAccepted, kForged, kReplay, kStale };

  // `monitored`: bit per ddyn_dbw_frame of the frames this node must see authenticated
  FrameAuth(const uint8_t key[DDYN_DBW_AUTH_KEY_LEN], uint32_t monitored);
  // the key file named by `configured`, else by $DDYN_DBW_KEY_FILE; none: std::nullopt (authentication
  // off). A file that cannot be read as a key throws std::runtime_error naming it and why.
  static std::optional<FrameAuth> from_key_file(const std::string& configured, uint32_t monitored);

  // the authenticator of frame f (a frame of the protocol this node sends); f.id must be a protocol frame
  CanFrame sign(const CanFrame& f);
  // one received frame at time t (s): a monitored protected frame is held (kHeld); an authenticator is
  // verified and, accepted, its frame written to *released (kAccepted); anything else kPassThrough
  Verdict on_frame(const CanFrame& f, double t, CanFrame* released);
  // held frames whose authenticator did not come in time, dropped (counted as stale)
  int expire(double t);

  // The freshness values that must survive a reset (AUTOSAR SecOC's freshness value manager keeps them
  // in non-volatile memory): per ddyn_dbw_frame the next value this node sends, and the last value it
  // accepted from its peer (valid or not yet seen). Saved in the plant's snapshot (PlantApp::snapshot).
  struct Freshness {
    std::array<uint64_t, DDYN_DBW_FRAME_COUNT> tx{};
    std::array<uint64_t, DDYN_DBW_FRAME_COUNT> rx{};
    std::array<bool, DDYN_DBW_FRAME_COUNT> rx_valid{};
  };
  Freshness freshness() const;
  // After a restart from a snapshot: each transmit value is put back advanced by tx_margin, since the
  // node kept sending (and its peer kept accepting) after the snapshot was written; a value reused
  // would be refused as a replay. The receive values are put back as they were (a peer's value only
  // grows, so its next frame is newer; commands captured before the snapshot stay refused as replays).
  void restore_freshness(const Freshness& saved, uint64_t tx_margin);

  long accepted() const { return accepted_; }
  long forged() const { return forged_; }
  long replayed() const { return replayed_; }
  long stale() const { return stale_; }

 private:
  ddyn_dbw_auth auth_{};
  uint32_t monitored_ = 0;
  std::array<uint64_t, DDYN_DBW_FRAME_COUNT> tx_freshness_{};
  std::array<uint8_t, 3> tx_counter_{};
  long accepted_ = 0, forged_ = 0, replayed_ = 0, stale_ = 0;
};

}  // namespace fsim
