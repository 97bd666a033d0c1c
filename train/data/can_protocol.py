"""The drive-by-wire CAN protocol in Python, read from the same DBC as the C (can/ddyn_dbw.dbc).

cantools packs and unpacks the signals; this module adds the two rules the DBC states in its
comment and c_src/src/dbw.c implements: the 4-bit rolling Counter (+1 modulo 16 per identifier)
and the Checksum byte, CRC-8/SAE-J1850 (crccheck's Crc8SaeJ1850) over the identifier as two
little-endian bytes and data bytes 0-6. Decoding checks what the C checks, in the same order,
and names the defect with the C's failure names (docs/can.md).

The SecOC-style authenticator frames (SecOC_Controller/_DBW/_Sensors, docs/can.md) are messages of
the DBC like the others; auth_mac() and authenticator() compute them as c_src/src/dbw_auth.c does
(keyed BLAKE2b with an 8-byte digest, hashlib's, truncated to 24 bits), e.g. to sign or check a log.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cantools
from crccheck.crc import Crc8SaeJ1850

from ddyn.errors import DdynError

REPO = Path(__file__).resolve().parents[2]
DBC_PATH = REPO / "can" / "ddyn_dbw.dbc"
ID_BLOCK_BASE, ID_BLOCK_MASK = 0x100, 0x7C0
FRAME_LEN = 8
COUNTER_MODULO = 16


@lru_cache(maxsize=4)
def database(path: str | Path = DBC_PATH):
    try:
        return cantools.database.load_file(str(path), strict=True)
    except (OSError, cantools.database.Error) as e:
        raise DdynError(f"{path}: cannot load the DBC file: {e}") from e


def checksum(frame_id: int, data: bytes) -> int:
    return Crc8SaeJ1850.calc(bytes((frame_id & 0xFF, (frame_id >> 8) & 0xFF)) + bytes(data[:7]))


AUTH_KEY_LEN, AUTH_MAC_BITS, AUTH_FRESHNESS_BITS = 32, 24, 22
# the authenticator message of each protected frame's sender
AUTHENTICATOR_OF = {0x100: "SecOC_Controller", 0x110: "SecOC_DBW", 0x111: "SecOC_DBW", 0x112: "SecOC_DBW",
                    0x120: "SecOC_Sensors", 0x130: "SecOC_Sensors", 0x131: "SecOC_Sensors"}


def auth_mac(key: bytes, frame_id: int, data: bytes, freshness: int) -> int:
    """The 24-bit MAC of one frame: the first 24 bits of keyed BLAKE2b (8-byte digest) over the identifier
    (2 bytes LE), the 8 data bytes and the full freshness value (8 bytes LE), as c_src/src/dbw_auth.c."""
    if len(key) != AUTH_KEY_LEN or len(data) != FRAME_LEN:
        raise DdynError(f"auth_mac: a {AUTH_KEY_LEN}-byte key and {FRAME_LEN} data bytes, not {len(key)} and {len(data)}")
    msg = frame_id.to_bytes(2, "little") + bytes(data) + (freshness & (2**64 - 1)).to_bytes(8, "little")
    d = hashlib.blake2b(msg, key=bytes(key), digest_size=8).digest()
    return (d[0] << 16) | (d[1] << 8) | d[2]


def authenticator(key: bytes, frame_id: int, data: bytes, freshness: int, counter: int, db=None) -> tuple[int, bytes]:
    """(identifier, 8 data bytes) of the authenticator frame that follows frame (frame_id, data)."""
    name = AUTHENTICATOR_OF.get(frame_id)
    if name is None:
        raise DdynError(f"identifier 0x{frame_id:03X} is not a protected frame of the DBC")
    return encode(name, {"AuthenticatedId": frame_id - ID_BLOCK_BASE,
                         "Freshness": freshness % (1 << AUTH_FRESHNESS_BITS),
                         "Mac": auth_mac(key, frame_id, data, freshness)}, counter, db)


def encode(name: str, signals: dict[str, float], counter: int, db=None) -> tuple[int, bytes]:
    """(identifier, 8 data bytes) of message `name`; every signal must be given and in range
    (cantools' strict encoding raises otherwise, as the C refuses)."""
    db = db or database()
    msg = db.get_message_by_name(name)
    values = dict(signals, Counter=counter % COUNTER_MODULO, Checksum=0)
    try:
        data = bytearray(msg.encode(values, strict=True, scaling=True))
    except (cantools.database.EncodeError, KeyError, ValueError) as e:
        raise DdynError(f"{name}: cannot encode {signals}: {e}") from e
    data[7] = checksum(msg.frame_id, data)
    return msg.frame_id, bytes(data)


class FrameError(Exception):
    """A frame that fails a check; `kind` is the C side's failure name."""

    def __init__(self, kind: str, message: str):
        super().__init__(message)
        self.kind = kind


@dataclass
class Decoded:
    name: str
    frame_id: int
    counter: int
    signals: dict[str, float]


def decode(frame_id: int, data: bytes, db=None) -> Decoded | None:
    """Decode one frame with the C's checks; None for identifiers outside the protocol's block
    (not ours), FrameError for unknown_frame, bad_length, checksum and range."""
    db = db or database()
    if frame_id > 0x7FF or (frame_id & ID_BLOCK_MASK) != ID_BLOCK_BASE:
        return None
    try:
        msg = db.get_message_by_frame_id(frame_id)
    except KeyError:
        raise FrameError("unknown_frame", f"identifier 0x{frame_id:03X} is not in the DBC") from None
    if len(data) != FRAME_LEN:
        raise FrameError("bad_length", f"{msg.name}: {len(data)} data bytes, expected {FRAME_LEN}")
    if data[7] != checksum(frame_id, data):
        raise FrameError("checksum", f"{msg.name}: checksum 0x{data[7]:02X}, expected 0x{checksum(frame_id, data):02X}")
    raw = msg.decode(bytes(data), decode_choices=False, scaling=False)
    values = {}
    for sig in msg.signals:
        phys = raw[sig.name] * sig.scale + sig.offset
        lo, hi = sig.minimum, sig.maximum
        # compare raw integers as the C does (phys bounds to raw, rounding to the nearest step)
        if lo is not None and raw[sig.name] < round((lo - sig.offset) / sig.scale):
            raise FrameError("range", f"{msg.name}.{sig.name} = {phys} below {lo}")
        if hi is not None and raw[sig.name] > round((hi - sig.offset) / sig.scale):
            raise FrameError("range", f"{msg.name}.{sig.name} = {phys} above {hi}")
        values[sig.name] = float(phys)
    counter = int(values.pop("Counter"))
    values.pop("Checksum")
    return Decoded(msg.name, frame_id, counter, values)
