"""The diagnosis's settings as one validated object, read from a TOML or JSON file.

`DiagnosisConfig` holds every setting `diagnose()` takes besides the log and the nominal. Each field says its
default and why. A config is immutable and passed explicitly: to `diagnose()`, into every benchmark case (so a
process-pool or Dask worker diagnoses with exactly the settings of the run), and recorded in diagnosis.json and in
a calibration. Nothing here is a module global that a run assigns.

A file holds the diagnosis's settings under `[diagnosis]` (or at its top level when it has no tables), and a
benchmark's own settings under `[benchmark]` (`BenchmarkConfig`). Unknown keys, wrong types and out-of-range values
are refused with one line naming the file and the key. The shipped files in `ddyn/gap/configs/` load by name
(`--config dbw`).
"""
from __future__ import annotations

import json
import math
import tomllib
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

from ddyn.errors import DdynError
from ddyn.gap import candidates as C
from ddyn.model import effects as E
from ddyn.model.single_track import COEFF_NAMES

CONFIG_DIR = Path(__file__).resolve().parent / "configs"
FIT_MODES = ("one-step", "smoothed", "output-error", "mixed")
# "mixed" without a list: the steering delay's value is fitted one-step (the effect whose output-error minimum lies
# furthest from the truth on the CommonRoad plant's sweeps, docs/gap.md)
ONE_STEP_IN_MIXED = ("steer_delay",)
EVIDENCE_MODES = ("one-step", "multistep", "endpoint")
EVIDENCE_ROWS = ("independent", "effective")
MULTISTEP_DEFAULT_STEPS = 25
# the key of detection limits for every effect without an entry of its own ({"*": None}: only the effects a
# calibration measured a threshold for are ever claimed)
ANY_OTHER = "*"
# The first effect added and the runner-up of its round with evidence closer than this (dBIC) are not told apart by
# the data: "not worth more than a bare mention" on Kass & Raftery's scale of BIC differences, a textbook constant,
# not tuned here. With detection limits such a first effect is reported, not claimed (the tie veto; the calibration
# applies the same rule to recorded runs).
AMBIGUITY_DBIC = 2.0


def parse_fit_spec(text: str | None) -> tuple[str, tuple[str, ...]]:
    """(fit mode, effects fitted one-step in "mixed") of a fit spec: a FIT_MODES name, or "mixed:EFFECT,..."."""
    text = (text or "one-step").strip()
    mode, _, rest = text.partition(":")
    if mode not in FIT_MODES or (rest and mode != "mixed"):
        raise DdynError(f"unknown fit {text!r}; expected {', '.join(FIT_MODES)} or mixed:EFFECT,...")
    if mode != "mixed":
        return mode, ()
    effects = tuple(e.strip() for e in rest.split(",") if e.strip()) if rest else ONE_STEP_IN_MIXED
    bad = [e for e in effects if e not in C.ALL]
    if bad or not effects:
        raise DdynError(f"fit {text}: unknown effect(s) {', '.join(bad) or '(none given)'}")
    return mode, effects


def parse_evidence_spec(text: str | None) -> tuple[int, bool]:
    """"one-step" -> (0, False); "multistep[:N]" -> (N, False); "endpoint[:N]" -> (N, True), N >= 2."""
    if text in (None, "", "one-step"):
        return 0, False
    name, _, n = str(text).partition(":")
    if name not in ("multistep", "endpoint"):
        raise DdynError(f"unknown evidence {text!r}; expected one-step, multistep[:N] or endpoint[:N]")
    try:
        steps = int(n) if n else MULTISTEP_DEFAULT_STEPS
    except ValueError:
        raise DdynError(f"evidence {text!r}: N must be an integer") from None
    if steps < 2:
        raise DdynError(f"evidence {text!r}: N must be >= 2 (N = 1 is the one-step evidence)")
    return steps, name == "endpoint"


@dataclass(frozen=True)
class DiagnosisConfig:
    """How `diagnose()` fits, scores and claims. The defaults are the plain method on a log whose commands ramp
    between samples (the project's simulator); `configs/dbw.toml` is the one for drive-by-wire logs."""

    # Share of the log (by time) the effects are fitted on; the rest is held out and scores them. 0.6 leaves
    # enough held-out rows for the evidence of a one-parameter effect on a 60 s log.
    fit_fraction: float = 0.6
    # The candidate effects tried ("default": the eleven one-parameter effects the benchmarks calibrated;
    # "extended": those plus the bank/grade profiles, the channel readings and the drivetrain, opt-in because on
    # the independent plant the drivetrain candidates find the plant's own power limit on every log).
    candidates: tuple[str, ...] = E.EFFECT_NAMES
    # Nominal coefficients refitted (as factors) under every hypothesis, "none" included: an effect must explain
    # more than a re-identified tyre peak force.
    refit: tuple[str, ...] = ("Df", "Dr")
    # At most this many effects are added by the greedy selection.
    max_effects: int = 3
    # Rounds of the greedy search beyond max_effects that may add an effect which pays but is not claimed (kept as
    # a nuisance so the search goes on past it). 0 with max_effects 1: round one only (what a calibration reads).
    max_unclaimed: int = 2
    # Rollout start points for the multi-step (ADE/FDE) figures; a cap on the cost, not a statistic.
    max_starts: int = 400
    # The log's commands were held between samples (a drive-by-wire unit) while the model ramps them: every
    # hypothesis gets half a sample of delay on both commands (true), half the command period the log's own step
    # structure shows ("steps": a unit slower than the log holds m samples, m/2 of lag), or the hold delay fitted
    # on the nominal ("estimate"; on the plant families it read 0 or its bound, nothing between, and a
    # delay's estimate took the difference: steps is what the family calibration uses).
    hold: bool | str = False
    # What the fit compares (FIT_MODES): one-step predictions, from smoothed states (errors in variables),
    # output-error rollouts, or "mixed[:EFFECTS]" (output error, those effects' values fitted one-step).
    fit: str = "one-step"
    # What the held-out evidence scores: "one-step", "multistep[:N]" or "endpoint[:N]" rollouts (uncalibrated
    # experiments for slow longitudinal effects).
    evidence: str = "one-step"
    # How many rows the one-step evidence counts per channel (EVIDENCE_ROWS): "independent", every held-out row
    # (the plain BIC); "effective", each channel's rows times (1 - r) / (1 + r), r the lag-1 autocorrelation of the
    # refitted nominal's held-out residuals (ddyn.gap.problem.Problem.set_row_weight): coloured noise and slow
    # drifts make neighbouring rows alike, and counted as independent they give a spurious candidate evidence
    # that grows with the log.
    evidence_rows: str = "effective"
    # The mass_offset candidate scales the yaw inertia with the mass (a heavier car with load-proportional tyre
    # forces: with Df, Dr refitted it changes only the longitudinal response).
    mass_inertia: bool = False
    # A known steering servo in the nominal (a DBW data sheet's first-order time constant, s); steer_lag then
    # estimates the servo, steer_delay what comes on top. 0: none.
    steer_servo: float = 0.0
    # Effects the nominal itself has, {effect: main parameter} (e.g. a data sheet's power_limit in W); a hypothesis
    # of the same effect replaces the value.
    nominal_effects: dict = field(default_factory=dict)
    # The no-gap gate: select nothing when the refitted nominal's held-out error is at most this many times the
    # estimated noise floor. None: off (no calibration has kept it).
    gate: float | None = None
    # Evidence margin: an effect is added only when dBIC < -min_evidence. 0: the plain extended-BIC rule; a
    # calibration sets the margin that leaves <= 5 % of its effect-free logs with a selection.
    min_evidence: float = 0.0
    # The part of the margin that grows with the log: the margin is min_evidence + min_evidence_per_row x the
    # held-out rows. A plant mismatch's spurious gain grows with the rows, so a margin calibrated on short logs
    # and held constant lets it through on long ones (ddyn.gap.limits). 0: a constant margin.
    min_evidence_per_row: float = 0.0
    # A margin per held-out row of each effect family on top ({family: margin per row}; "*": every other): what a
    # family must pay before it is claimed, beyond the margin every effect pays to enter the model. A plant's
    # systematic mismatch pays as one or two families (a mass offset, a downforce), not as all of them, so a
    # travelling calibration sets each family's own (ddyn.gap.benchmark.lofo). None: none.
    family_margins_per_row: dict | None = None
    # Limits of detection {effect family: smallest |estimate| claimed, or None: never claimed; "*": every other}.
    # An effect that pays with a size below its limit, or whose runner-up is within 2 dBIC, is reported, not
    # claimed. None: no limits (a calibration sets its decision levels).
    detection_limits: dict | None = None
    # Decision levels that travel: {effect family: share of the family's size that matters (ddyn.gap.limits.SIZES)
    # a claimed estimate must reach, or None: never claimed; "*": every other}. Used for families without an
    # absolute detection_limits entry. None: off.
    decision_levels: dict | None = None

    def __post_init__(self):
        _validate(self)

    @classmethod
    def from_dict(cls, raw: dict, where: str = "config") -> "DiagnosisConfig":
        """From a mapping of field names (a file's [diagnosis] table); every key checked, errors name it."""
        if not isinstance(raw, dict):
            raise DdynError(f"{where}: expected a table of settings, got {type(raw).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(raw) - known)
        if unknown:
            raise DdynError(f"{where}: unknown key(s) {', '.join(unknown)}; expected some of {', '.join(sorted(known))}")
        try:
            return cls(**{k: _coerce(k, v) for k, v in raw.items()})
        except DdynError as e:
            raise DdynError(f"{where}: {e}") from None

    @classmethod
    def from_file(cls, path: str | Path) -> "DiagnosisConfig":
        return load_config(path)[0]

    def to_dict(self) -> dict:
        """JSON-ready (tuples as lists): what diagnosis.json, results.json and calibrations record."""
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    def with_(self, **changes) -> "DiagnosisConfig":
        """A copy with these fields replaced (file forms accepted: "extended" candidates, gate 0, ...)."""
        unknown = sorted(set(changes) - {f.name for f in fields(self)})
        if unknown:
            raise DdynError(f"unknown setting(s) {', '.join(unknown)}")
        return replace(self, **{k: _coerce(k, v) for k, v in changes.items()})


def _coerce(key: str, value):
    """A file's value into the field's form: lists to tuples, 'default'/'extended' candidate sets, gate 0 or
    'off' to None, 'none' refit to ()."""
    if key == "candidates":
        if value in ("default", None):
            return E.EFFECT_NAMES
        if value == "extended":
            return C.ALL
        if isinstance(value, str):
            return tuple(v.strip() for v in value.split(",") if v.strip())
    if key == "refit":
        if value in ("none", "", None):
            return ()
        if isinstance(value, str):
            return tuple(v.strip() for v in value.split(",") if v.strip())
    if key in ("candidates", "refit") and isinstance(value, list):
        return tuple(value)
    if key == "gate" and (value in ("off", None) or (isinstance(value, (int, float)) and not isinstance(value, bool)
                                                      and value == 0)):
        return None     # 0 or "off": no gate (a negative ratio is refused by the validation)
    if key == "nominal_effects" and isinstance(value, str):
        return {e.effect: float(e.value) for e in E.parse_effects(value)}
    return value


def _number(name: str, value, lo: float | None = None, hi: float | None = None, integer: bool = False) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (integer and not isinstance(value, int)):
        raise DdynError(f"{name}: expected {'an integer' if integer else 'a number'}, got {value!r}")
    if not math.isfinite(value) or (lo is not None and value < lo) or (hi is not None and value > hi):
        raise DdynError(f"{name}: {value!r} is outside [{lo}, {hi}]")


def _validate(c: DiagnosisConfig) -> None:
    _number("fit_fraction", c.fit_fraction, 0.05, 0.95)
    for name, pool in (("candidates", C.ALL), ("refit", COEFF_NAMES)):
        value = getattr(c, name)
        if not isinstance(value, tuple) or not all(isinstance(v, str) for v in value):
            raise DdynError(f"{name}: expected a list of names, got {value!r}")
        bad = [v for v in value if v not in pool]
        if bad:
            raise DdynError(f"{name}: unknown {', '.join(bad)}; expected some of {', '.join(pool)}")
    if not c.candidates:
        raise DdynError("candidates: at least one effect to try")
    _number("max_effects", c.max_effects, 1, 10, integer=True)
    _number("max_starts", c.max_starts, 1, 10 ** 6, integer=True)
    _number("max_unclaimed", c.max_unclaimed, 0, 10, integer=True)
    if c.hold not in (True, False, "estimate", "steps"):
        raise DdynError(f"hold: expected true, false, \"steps\" or \"estimate\", got {c.hold!r}")
    parse_fit_spec(c.fit) if isinstance(c.fit, str) else _bad("fit", c.fit, "a string")
    parse_evidence_spec(c.evidence) if isinstance(c.evidence, str) else _bad("evidence", c.evidence, "a string")
    if c.evidence_rows not in EVIDENCE_ROWS:
        _bad("evidence_rows", c.evidence_rows, " or ".join(f'"{m}"' for m in EVIDENCE_ROWS))
    if not isinstance(c.mass_inertia, bool):
        _bad("mass_inertia", c.mass_inertia, "true or false")
    _number("steer_servo", c.steer_servo, 0.0, 1.0)
    if not isinstance(c.nominal_effects, dict):
        _bad("nominal_effects", c.nominal_effects, "a table {effect: value}")
    for eff, v in c.nominal_effects.items():
        if eff not in E.ALL_EFFECTS:
            raise DdynError(f"nominal_effects: unknown effect {eff!r}; expected one of {', '.join(E.ALL_EFFECTS)}")
        _number(f"nominal_effects.{eff}", v)
    if c.gate is not None:
        _number("gate", c.gate, 0.0)
    _number("min_evidence", c.min_evidence, 0.0)
    _number("min_evidence_per_row", c.min_evidence_per_row, 0.0)
    for key in ("detection_limits", "decision_levels", "family_margins_per_row"):
        table = getattr(c, key)
        if table is None:
            continue
        if not isinstance(table, dict):
            _bad(key, table, "a table {effect: value or null}")
        for eff, v in table.items():
            if eff not in C.ALL and eff not in C.FAMILY.values() and eff != ANY_OTHER:
                raise DdynError(f"{key}: unknown effect {eff!r}")
            if v is not None:
                _number(f"{key}.{eff}", v, 0.0)


def _bad(name: str, value, expected: str):
    raise DdynError(f"{name}: expected {expected}, got {value!r}")


@dataclass(frozen=True)
class BenchmarkConfig:
    """A benchmark run's own settings (`ddyn gap benchmark`), beside the diagnosis's."""

    # The nominal the CommonRoad plants are diagnosed with: the plant's parameters mapped onto the model
    # ("mapped", its vehicle file) or fitted on an effect-free log of the plant ("identified").
    nominal: str = "mapped"
    # Every log carries the plant's pitch (roll) channel and the diagnosis may read the grade (bank) from it.
    pitch_channel: bool = False
    roll_channel: bool = False
    # Only the cases of these hidden effects (same case numbers and seeds as the whole plan); empty: all.
    effects: tuple[str, ...] = ()
    # The own-model benchmark's vehicles.
    vehicles: tuple[str, ...] = ("orca_1_43", "av21")

    def __post_init__(self):
        if self.nominal not in ("mapped", "identified"):
            raise DdynError(f"nominal: expected \"mapped\" or \"identified\", got {self.nominal!r}")
        for name in ("pitch_channel", "roll_channel"):
            if not isinstance(getattr(self, name), bool):
                _bad(name, getattr(self, name), "true or false")
        for name in ("effects", "vehicles"):
            v = getattr(self, name)
            if not isinstance(v, tuple) or not all(isinstance(x, str) for x in v):
                _bad(name, v, "a list of names")

    @classmethod
    def from_dict(cls, raw: dict, where: str = "config") -> "BenchmarkConfig":
        if not isinstance(raw, dict):
            raise DdynError(f"{where}: expected a table of settings, got {type(raw).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(raw) - known)
        if unknown:
            raise DdynError(f"{where}: unknown key(s) {', '.join(unknown)}; expected some of {', '.join(sorted(known))}")
        vals = {k: tuple(v) if isinstance(v, list) else tuple(x.strip() for x in v.split(",") if x.strip())
                if k in ("effects", "vehicles") and isinstance(v, str) else v for k, v in raw.items()}
        try:
            return cls(**vals)
        except DdynError as e:
            raise DdynError(f"{where}: {e}") from None

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


def config_path(name_or_path: str | Path) -> Path:
    """A shipped config's name (configs/NAME.toml) or a file's path."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    shipped = CONFIG_DIR / f"{name_or_path}.toml"
    if shipped.is_file():
        return shipped
    names = ", ".join(sorted(f.stem for f in CONFIG_DIR.glob("*.toml")))
    raise DdynError(f"config {name_or_path}: no such file, nor a shipped config ({names})")


def read_table(path: str | Path) -> dict:
    """A TOML or JSON file's top-level table, errors naming the file."""
    p = config_path(path)
    try:
        text = p.read_text()
        raw = json.loads(text) if p.suffix == ".json" else tomllib.loads(text)
    except (OSError, UnicodeDecodeError) as e:
        raise DdynError(f"{p}: cannot read: {e}") from None
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as e:
        raise DdynError(f"{p}: not valid {'JSON' if p.suffix == '.json' else 'TOML'}: {e}") from None
    if not isinstance(raw, dict):
        raise DdynError(f"{p}: expected a table at the top level, got {type(raw).__name__}")
    return raw


def load_config(path: str | Path | None) -> tuple[DiagnosisConfig, BenchmarkConfig]:
    """(diagnosis, benchmark) settings of a file: its [diagnosis] and [benchmark] tables, or a flat table of
    diagnosis settings; None: the defaults."""
    if path is None:
        return DiagnosisConfig(), BenchmarkConfig()
    p = config_path(path)
    raw = read_table(p)
    tables = {k for k, v in raw.items() if isinstance(v, dict) and k in ("diagnosis", "benchmark")}
    if tables:
        extra = sorted(set(raw) - {"diagnosis", "benchmark", "description"})
        if extra:
            raise DdynError(f"{p}: unknown key(s) {', '.join(extra)}; expected the tables [diagnosis], [benchmark]")
        return (DiagnosisConfig.from_dict(raw.get("diagnosis", {}), f"{p} [diagnosis]"),
                BenchmarkConfig.from_dict(raw.get("benchmark", {}), f"{p} [benchmark]"))
    flat = {k: v for k, v in raw.items() if k != "description"}
    return DiagnosisConfig.from_dict(flat, str(p)), BenchmarkConfig()
