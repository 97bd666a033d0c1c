"""ddyn.gap: the evidence counts effective rows (DiagnosisConfig.evidence_rows), so coloured sensor noise does not
pay a spurious effect that a white-noise log of the same car would not; and a claim that is stopped says by what
(its decision level or its family's evidence margin)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ddyn.errors import DdynError
from ddyn.gap import config as CFG, limits as L, problem as P, selection as SEL
from ddyn.model import vehicle as vehicles

ORCA = vehicles.load("orca_1_43")
CANDIDATES = ("mass_offset", "steer_delay", "throttle_delay", "downforce", "yaw_rate_bias")


def _ar1(rng, n: int, rho: float, sd: float) -> np.ndarray:
    e, w = np.zeros(n), rng.standard_normal(n) * sd * np.sqrt(1.0 - rho ** 2)
    for i in range(1, n):
        e[i] = rho * e[i - 1] + w[i]
    return e


def _with_noise(ds, rho: float, seed: int):
    """The log with AR(1) noise of twice the car's sensor noise on vx, vy, omega (rho 0: white)."""
    rng = np.random.default_rng(seed)
    st = ds.states.copy()
    for j, k in ((3, "vx"), (4, "vy"), (5, "omega")):
        st[:, j] += _ar1(rng, len(st), rho, 2.0 * ORCA.sensor_noise_std[k])
    return dataclasses.replace(ds, states=st)


@pytest.fixture(scope="module")
def clean_log(shared_data):
    from ddyn.data.simulate import simulate

    return simulate(ORCA, "ethzMobil", laps=12.0, seed=21, noise_scale=0.0, progress=False, effects=None)


@pytest.fixture(scope="module")
def delayed_log(shared_data):
    from ddyn.data.simulate import simulate

    return simulate(ORCA, "ethzMobil", laps=12.0, seed=21, noise_scale=0.0, progress=False,
                    effects="throttle_delay=0.04")


def test_the_row_weight_is_the_ar1_effective_sample_size():
    rng = np.random.default_rng(0)
    n = 40000
    res = np.column_stack([_ar1(rng, n, 0.6, 1.0), rng.standard_normal(n), np.diff(rng.standard_normal(n + 1))])
    prob = P.Problem.__new__(P.Problem)
    prob.set_row_weight(res)
    # AR(1) 0.6: (1 - 0.6) / (1 + 0.6) = 0.25; white: 1; differenced white (lag-1 correlation -0.5): not above 1
    assert prob.row_weight[0] == pytest.approx(0.25, abs=0.02)
    assert prob.row_weight[1] == pytest.approx(1.0, abs=0.03) and prob.row_weight[2] == 1.0
    prob.set_row_weight(np.column_stack([np.ones(10), np.arange(10.0), np.zeros(10)]))   # constant and trend
    assert np.all(prob.row_weight > 0) and prob.row_weight[0] == 1.0 and prob.row_weight[2] == 1.0


def test_a_stated_limit_rises_as_the_effective_rows_fall():
    g = np.array([1e-3, 2e-3, 0.0])
    full = L.limit(0.04, g, 3000, 0.0)
    quarter = L.limit(0.04, g, 3000, 0.0, weight=np.array([0.25, 0.25, 1.0]))
    assert full is not None and quarter is not None and quarter > 1.5 * full


def test_a_bad_evidence_rows_setting_is_refused_naming_it(tmp_path):
    with pytest.raises(DdynError, match="evidence_rows"):
        CFG.DiagnosisConfig(evidence_rows="sometimes")
    f = tmp_path / "d.toml"
    f.write_text('[diagnosis]\nevidence_rows = "every"\n')
    with pytest.raises(DdynError, match=r"d\.toml \[diagnosis\]: evidence_rows") as e:
        CFG.load_config(f)
    assert "\n" not in str(e.value)


def _diagnose(ds, mode: str) -> dict:
    return SEL.diagnose(ds, P.nominal_from_vehicle(ORCA, ds), candidates=CANDIDATES, max_effects=1, max_starts=50,
                        evidence_rows=mode)


def test_coloured_noise_pays_a_mass_offset_only_when_every_row_counts(clean_log):
    """Effect-free, noise correlated 0.9 from row to row: counted as independent rows a mass offset pays (it
    follows the noise's persistence in the yaw rate) and is claimed; counted as effective rows nothing pays. The
    same log with white noise: nothing pays either way, and the weights are 1."""
    coloured = _with_noise(clean_log, 0.9, seed=3)
    spurious = _diagnose(coloured, "independent")
    assert spurious["selected"] == ["mass_offset"] and spurious["candidates"][0]["delta_bic"] < -10
    effective = _diagnose(coloured, "effective")
    w = effective["method"]["evidence_rows"]["weight_per_channel"]
    assert w["omega"] < 0.2 and w["vy"] < 0.3
    assert effective["selected"] == [] and all(c["delta_bic"] > 0 for c in effective["candidates"])
    white = _with_noise(clean_log, 0.0, seed=3)
    assert _diagnose(white, "independent")["selected"] == []
    d = _diagnose(white, "effective")
    assert d["selected"] == [] and d["method"]["evidence_rows"]["weight_per_channel"] == {"vx": 1.0, "vy": 1.0,
                                                                                          "omega": 1.0}


def test_a_real_delay_is_still_found_under_coloured_noise(delayed_log):
    d = _diagnose(_with_noise(delayed_log, 0.9, seed=3), "effective")
    assert d["selected"] == ["throttle_delay"]
    assert d["candidates"][0]["params"]["delay"] == pytest.approx(0.04, abs=0.01)


def test_a_claim_stopped_by_its_family_margin_says_so_not_that_it_is_below_its_limit(delayed_log):
    """The 40 ms delay is above its decision level (half the 40 ms that matters) but its family's margin per
    held-out row is set beyond its evidence: the verdict names the margin, not a detection limit it clears."""
    d = SEL.diagnose(delayed_log, P.nominal_from_vehicle(ORCA, delayed_log), candidates=("throttle_delay",),
                     max_effects=1, max_starts=50, decision_levels={"throttle_delay": 0.5},
                     family_margins_per_row={"throttle_delay": 10.0})
    assert d["selected"] == [] and d["below_limit"]["blocked_by"] == "margin"
    assert "short of the dBIC" in d["verdict"] and "below its detection limit" not in d["verdict"]
    low = SEL.diagnose(delayed_log, P.nominal_from_vehicle(ORCA, delayed_log), candidates=("throttle_delay",),
                       max_effects=1, max_starts=50, decision_levels={"throttle_delay": 3.0})
    assert low["below_limit"]["blocked_by"] == "level" and "below its detection limit" in low["verdict"]
