"""The canonical dataset: one in-memory type and one on-disk format.

On disk (documented in docs/dataset_format.md) a canonical dataset is a CSV text
file whose first line is `# ddyn-dataset 1`, followed by `# key: value` metadata
lines (sample_time, vehicle, source, ...), one header line naming the columns,
and one row per sample. The required columns, in this order, are COLUMNS; any
further columns are extras (e.g. noise-free truth `true_vx`, raw sensor data)
and are kept as they are.

Row k holds the state at time[k] and the input (dthrottle, dsteering) applied
from time[k] to time[k+1]. `segment` numbers contiguous runs: within a segment
time advances by exactly sample_time; a model never steps from one segment into
the next (rows dropped from a real log start a new segment).
"""
from __future__ import annotations

import hashlib
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ddyn.model.single_track import INPUT_NAMES, N_INPUT, N_STATE, STATE_NAMES

FORMAT_MAGIC = "# ddyn-dataset 1"
COLUMNS = ("time", "segment") + STATE_NAMES + INPUT_NAMES
UNITS = {
    "time": "s", "segment": "-", "x": "m", "y": "m", "yaw": "rad", "vx": "m/s", "vy": "m/s",
    "omega": "rad/s", "throttle": "-", "steering": "rad", "dthrottle": "1/s", "dsteering": "rad/s",
}
# relative tolerance on the sample time between consecutive rows of a segment
# (real logs store time stamps in float32-derived doubles: 0.04 s is 0.0399999619 s)
SAMPLE_TIME_RTOL = 1e-4


@dataclass
class Dataset:
    time: np.ndarray            # (N,) s
    segment: np.ndarray         # (N,) int64, non-decreasing
    states: np.ndarray          # (N, 8) STATE_NAMES
    inputs: np.ndarray          # (N, 2) INPUT_NAMES
    sample_time: float
    vehicle: str | None = None
    source: str = ""
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    metadata: dict[str, str] = field(default_factory=dict)

    def __post_init__(self):
        n = len(self.time)
        self.time = np.asarray(self.time, dtype=float)
        self.segment = np.asarray(self.segment, dtype=np.int64)
        self.states = np.asarray(self.states, dtype=float).reshape(n, N_STATE)
        self.inputs = np.asarray(self.inputs, dtype=float).reshape(n, N_INPUT)
        self.extras = {k: np.asarray(v, dtype=float).reshape(n) for k, v in self.extras.items()}

    def __len__(self) -> int:
        return len(self.time)

    def column(self, name: str) -> np.ndarray:
        if name == "time":
            return self.time
        if name == "segment":
            return self.segment
        if name in STATE_NAMES:
            return self.states[:, STATE_NAMES.index(name)]
        if name in INPUT_NAMES:
            return self.inputs[:, INPUT_NAMES.index(name)]
        return self.extras[name]

    def transition_index(self) -> np.ndarray:
        """Indices k whose successor k+1 is in the same segment (one-step training pairs)."""
        return np.flatnonzero(self.segment[1:] == self.segment[:-1])

    def subset(self, index: "np.ndarray | slice") -> "Dataset":
        if not isinstance(index, slice):
            index = np.asarray(index)
        return Dataset(self.time[index], self.segment[index], self.states[index], self.inputs[index],
                       self.sample_time, self.vehicle, self.source,
                       {k: v[index] for k, v in self.extras.items()}, dict(self.metadata))

    def content_hash(self) -> str:
        """SHA-256 of the numeric content (what a checkpoint records as its training data)."""
        h = hashlib.sha256()
        for a in (self.time, self.segment, self.states, self.inputs):
            h.update(np.ascontiguousarray(a).tobytes())
        for k in sorted(self.extras):
            h.update(k.encode())
            h.update(np.ascontiguousarray(self.extras[k]).tobytes())
        return h.hexdigest()


def write_canonical(ds: Dataset, path: str | Path) -> Path:
    """Write ds in the canonical CSV format (shortest decimal that round-trips each float64)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"sample_time": repr(float(ds.sample_time)), "vehicle": ds.vehicle or "", "source": ds.source,
            "units": ",".join(UNITS[c] for c in COLUMNS)}
    meta.update({k: v for k, v in ds.metadata.items() if k not in meta})
    names = list(COLUMNS) + list(ds.extras)
    table = np.column_stack([ds.column(c) for c in names]) if len(ds) else np.zeros((0, len(names)))
    buf = io.StringIO()
    buf.write(FORMAT_MAGIC + "\n")
    for k, v in meta.items():
        buf.write(f"# {k}: {' '.join(str(v).split())}\n")
    buf.write(",".join(names) + "\n")
    seg_col = names.index("segment")
    for row in table:
        buf.write(",".join(str(int(v)) if i == seg_col else repr(float(v)) for i, v in enumerate(row)) + "\n")
    path.write_text(buf.getvalue())
    return path
