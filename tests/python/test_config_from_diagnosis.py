"""From a diagnosis to the controller's configuration (issue 34 item 2; ddyn.sil.effects,
`ddyn sil run --effects-from D [--config-only]`): steer_delay becomes control.delay.steering, throttle_delay
control.delay.throttle, steer_lag control.lag.steering, mass_offset control.mass_offset (issue 34 item 1), every other
claimed effect is named and not applied, bad input is one line
naming the file and the key, and the controller refuses a configuration whose control.delay or control.lag was
edited after it was made from the diagnosis (controller.json `effects`)."""
from __future__ import annotations

import hashlib
import json
import subprocess

import pytest

from ddyn.cli import main
from ddyn.errors import DdynError
from ddyn.model.tracks import load_track
from ddyn.model.vehicle import load as load_vehicle
from ddyn.sil import run as sil
from ddyn.sil.effects import apply_to_config, controller_effects


def _diagnosis(folder, selected, values=None):
    """A minimal diagnosis.json as `ddyn gap diagnose` writes it (the keys the mapping reads)."""
    from ddyn.gap.candidates import MAIN_PARAM

    values = values or {}
    folder.mkdir(parents=True, exist_ok=True)
    d = {"schema": 1, "selected": selected, "verdict": "synthetic",
         "model": {"effects": [{"effect": e, "params": {MAIN_PARAM[e]: values.get(e, 0.04)}} for e in selected]},
         "candidates": []}
    (folder / "diagnosis.json").write_text(json.dumps(d))
    return folder


def test_a_steering_delay_becomes_control_delay_steering(tmp_path):
    d = _diagnosis(tmp_path / "D", ["steer_delay"], {"steer_delay": 0.041})
    fx = controller_effects(d)
    assert fx.delays == {"steer": 0.041} and fx.applied == ["steer_delay"] and fx.not_applied == []
    assert fx.sha256 == hashlib.sha256((d / "diagnosis.json").read_bytes()).hexdigest()
    cfg = apply_to_config({"vehicle": "orca_1_43", "control": {"period": 0.02}}, fx)
    assert cfg["control"] == {"period": 0.02, "delay": {"steering": 0.041, "throttle": 0.0},
                              "lag": {"steering": 0.0}, "mass_offset": 0.0, "downforce": 0.0}
    assert cfg["effects"] == {"diagnosis": str((d / "diagnosis.json").resolve()), "diagnosis_sha256": fx.sha256,
                              "delay": {"steering": 0.041, "throttle": 0.0}, "lag": {"steering": 0.0},
                              "mass_offset": 0.0, "downforce": 0.0}
    # the file itself works as well as its folder
    assert controller_effects(d / "diagnosis.json").delays == {"steer": 0.041}


def test_a_steering_lag_becomes_control_lag_steering(tmp_path):
    """A claimed steer_lag (without steer_delay) is the controller's control.lag.steering: its tau fitted alone
    when the diagnosis has it (not rounded to periods: a time constant), else the joint one."""
    d = _diagnosis(tmp_path / "D", ["steer_lag", "downforce"], {"steer_lag": 0.0365, "downforce": 0.08})
    fx = controller_effects(d, period=0.02)
    assert fx.lag == {"steer": 0.0365} and fx.delays == {} and fx.applied == ["steer_lag"]
    assert fx.not_applied == ["downforce: found 0.08, not applied: named after steer_lag (a downforce is applied "
                              "only when named first)"]
    assert fx.lines()[0].startswith("steer_lag: applied as control.lag.steering = 0.0365 s (joint fit)")
    raw = json.loads((d / "diagnosis.json").read_text())
    raw["candidates"] = [{"effect": "steer_lag", "params": {"tau": 0.051}}]
    (d / "diagnosis.json").write_text(json.dumps(raw))
    fx = controller_effects(d, period=0.02)
    assert fx.lag == {"steer": 0.051}
    assert fx.applied_estimates["steer_lag"] == {"alone": 0.051, "joint": 0.0365, "written": 0.051, "period": 0.02}
    cfg = apply_to_config({"vehicle": "orca_1_43", "control": {"period": 0.02}}, fx)
    assert cfg["control"]["lag"] == {"steering": 0.051} and cfg["effects"]["lag"] == {"steering": 0.051}
    assert cfg["control"]["delay"] == {"steering": 0.0, "throttle": 0.0}
    assert fx.summary()["controller_lag"] == {"steer": 0.051}
    raw["candidates"] = [{"effect": "steer_lag", "params": {"tau": 1.5}}]
    (d / "diagnosis.json").write_text(json.dumps(raw))
    with pytest.raises(DdynError, match="outside control.lag's 0..1 s"):
        controller_effects(d)


def test_unsupported_effects_are_named_not_applied(tmp_path):
    d = _diagnosis(tmp_path / "D", ["steer_lag", "steer_delay", "throttle_delay", "tire_wear"],
                   {"steer_lag": 0.06, "steer_delay": 0.02, "throttle_delay": 0.1, "tire_wear": 0.05})
    fx = controller_effects(d)
    assert fx.delays == {"steer": 0.02, "throttle": 0.1} and fx.applied == ["steer_delay", "throttle_delay"]
    assert fx.lag == {}
    # selected beside steer_delay the lag is not applied (the delay fitted alone carries the response)
    assert fx.not_applied[0].startswith("steer_lag: found 0.06, not applied: selected with steer_delay")
    assert fx.not_applied[1] == "tire_wear: not in the runtime" and len(fx.not_applied) == 2
    # a bank (bank_angle, bank_profile) is applied, the roll channel's named: test_sil_bank_effects.py
    nothing = controller_effects(_diagnosis(tmp_path / "E", []))
    assert nothing.delays == {} and nothing.applied == [] and nothing.not_applied == []


def test_a_mass_offset_becomes_control_mass_offset_and_an_edited_one_is_refused(tmp_path):
    """A mass_offset named first is the controller's control.mass_offset (the joint fit's fraction, not the one fitted
    alone); one named after another effect, or outside the controller's [-0.5, 1], is named and not applied; the controller accepts the file made
    from it and refuses it with control.mass_offset edited, naming effects.mass_offset."""
    d = _diagnosis(tmp_path / "D", ["mass_offset", "steer_lag"], {"mass_offset": 0.12, "steer_lag": 0.03})
    raw = json.loads((d / "diagnosis.json").read_text())
    raw["candidates"] = [{"effect": "mass_offset", "params": {"fraction": 0.15}}]
    (d / "diagnosis.json").write_text(json.dumps(raw))
    fx = controller_effects(d, period=0.02)
    assert fx.mass_offset == 0.12 and fx.applied == ["mass_offset", "steer_lag"] and fx.not_applied == []
    assert fx.applied_estimates["mass_offset"] == {"alone": 0.15, "joint": 0.12, "written": 0.12}
    assert "mass_offset: applied as control.mass_offset = 0.12 (joint fit; fitted alone 0.15)" in fx.lines()
    cfg = apply_to_config({"vehicle": "orca_1_43", "control": {"period": 0.02}}, fx)
    assert cfg["control"]["mass_offset"] == 0.12 and cfg["effects"]["mass_offset"] == 0.12
    bins = sil.build_binaries(None)
    orca = load_vehicle("orca_1_43")
    spec = sil.SilSpec.true_car(orca, load_track("ethzMobil"), controller_lag=fx.lag,
                                controller_mass_offset=fx.mass_offset, effects_from=fx.summary())
    path = sil.write_controller_files(spec, sil.raceline_table(spec.track, orca), tmp_path, str(tmp_path))
    written = json.loads(path.read_text())
    assert written["control"]["mass_offset"] == 0.12 and written["effects"]["mass_offset"] == 0.12

    def check(c):
        path.write_text(json.dumps(c))
        return subprocess.run([str(bins / "ddyn_controller"), "--check", str(path)], capture_output=True, text=True)

    ok = check(written)
    assert ok.returncode == 0, ok.stderr
    written["control"]["mass_offset"] = 0.3
    bad = check(written)
    assert bad.returncode == 2 and "effects.mass_offset" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
    del written["effects"]
    for value in (-0.6, 1.5, "heavy"):
        written["control"]["mass_offset"] = value
        bad = check(written)
        assert bad.returncode == 2 and "control.mass_offset" in bad.stderr, value
    # outside the range: named, not applied
    raw["model"]["effects"][0]["params"]["fraction"] = -0.7
    (d / "diagnosis.json").write_text(json.dumps(raw))
    fx = controller_effects(d)
    assert fx.mass_offset == 0.0 and fx.applied == ["steer_lag"]
    assert fx.not_applied == ["mass_offset: found -0.7, not applied: outside the controller's control.mass_offset "
                              "range [-0.5, 1]"]
    # named after another effect: not applied
    fx = controller_effects(_diagnosis(tmp_path / "E", ["steer_delay", "mass_offset"],
                                       {"steer_delay": 0.06, "mass_offset": -0.11}))
    assert fx.mass_offset == 0.0 and fx.applied == ["steer_delay"]
    assert fx.not_applied == ["mass_offset: found -0.11, not applied: named after steer_delay (a mass offset is "
                              "applied only when named first)"]
    # the command line: the same range, and not beside --effects-from
    assert main(["sil", "run", "--controller-mass-offset", "2", "--config-only", "--out", str(tmp_path / "x")]) == 2
    assert main(["sil", "run", "--effects-from", str(d), "--controller-mass-offset", "0.1", "--config-only",
                 "--out", str(tmp_path / "x")]) == 2


def test_a_downforce_named_first_becomes_control_downforce_and_an_edited_one_is_refused(tmp_path):
    """A downforce named first is the controller's control.downforce (its k of the joint fit); named after another
    effect or outside [0, 0.5] it is named and not applied; the controller accepts the file made from it and
    refuses it with control.downforce edited, naming effects.downforce, or out of range."""
    d = _diagnosis(tmp_path / "D", ["downforce", "steer_delay"], {"downforce": 0.021, "steer_delay": 0.04})
    fx = controller_effects(d, period=0.02)
    assert fx.downforce == 0.021 and fx.applied == ["downforce", "steer_delay"] and fx.not_applied == []
    assert "downforce: applied as control.downforce = 0.021 (joint fit)" in fx.lines()
    cfg = apply_to_config({"vehicle": "orca_1_43", "control": {"period": 0.02}}, fx)
    assert cfg["control"]["downforce"] == 0.021 and cfg["effects"]["downforce"] == 0.021
    bins = sil.build_binaries(None)
    orca = load_vehicle("orca_1_43")
    spec = sil.SilSpec.true_car(orca, load_track("ethzMobil"), controller_delays=fx.delays,
                                controller_downforce=fx.downforce, effects_from=fx.summary())
    path = sil.write_controller_files(spec, sil.raceline_table(spec.track, orca), tmp_path, str(tmp_path))
    written = json.loads(path.read_text())
    assert written["control"]["downforce"] == 0.021 and written["effects"]["downforce"] == 0.021

    def check(c):
        path.write_text(json.dumps(c))
        return subprocess.run([str(bins / "ddyn_controller"), "--check", str(path)], capture_output=True, text=True)

    ok = check(written)
    assert ok.returncode == 0, ok.stderr
    written["control"]["downforce"] = 0.05
    bad = check(written)
    assert bad.returncode == 2 and "effects.downforce" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
    del written["effects"]
    for value in (-0.01, 0.6, "lots"):
        written["control"]["downforce"] = value
        bad = check(written)
        assert bad.returncode == 2 and "control.downforce" in bad.stderr, value
    # outside the range, or named second: named, not applied
    fx = controller_effects(_diagnosis(tmp_path / "E", ["downforce"], {"downforce": 0.8}))
    assert fx.downforce == 0.0 and fx.applied == []
    assert fx.not_applied == ["downforce: found 0.8, not applied: outside the controller's control.downforce range "
                              "[0, 0.5]"]
    fx = controller_effects(_diagnosis(tmp_path / "F", ["steer_lag", "downforce"], {"downforce": 0.02}))
    assert fx.downforce == 0.0 and fx.applied == ["steer_lag"]
    # the command line: the same range, and not beside --effects-from
    assert main(["sil", "run", "--controller-downforce", "0.7", "--config-only", "--out", str(tmp_path / "x")]) == 2
    assert main(["sil", "run", "--effects-from", str(d), "--controller-downforce", "0.1", "--config-only",
                 "--out", str(tmp_path / "x")]) == 2


def test_a_throttle_delay_becomes_control_delay_throttle(tmp_path):
    """A claimed throttle_delay is the controller's control.delay.throttle: fitted alone when the diagnosis has
    it, to the nearest whole control period (87 ms acts as 4 periods of 20 ms, 0.08 s), beside the steering delay
    when both are claimed; the record carries it, so the controller checks it like the steering's."""
    d = _diagnosis(tmp_path / "D", ["throttle_delay", "downforce"], {"throttle_delay": 0.066, "downforce": 0.1})
    fx = controller_effects(d)
    assert fx.delays == {"throttle": 0.066} and fx.applied == ["throttle_delay"] and fx.lag == {}
    assert fx.not_applied == ["downforce: found 0.1, not applied: named after throttle_delay (a downforce is "
                              "applied only when named first)"]
    raw = json.loads((d / "diagnosis.json").read_text())
    raw["candidates"] = [{"effect": "throttle_delay", "params": {"delay": 0.087}}]
    (d / "diagnosis.json").write_text(json.dumps(raw))
    fx = controller_effects(d, period=0.02)
    assert fx.delays["throttle"] == pytest.approx(0.08) and "steer" not in fx.delays
    assert fx.applied_estimates["throttle_delay"] == {"alone": 0.087, "joint": 0.066,
                                                      "written": fx.delays["throttle"], "period": 0.02}
    assert fx.lines()[0].startswith("throttle_delay: applied as control.delay.throttle = 0.08 s (fitted alone "
                                    "0.087 s, joint 0.066 s, to whole periods of 0.02 s)")
    cfg = apply_to_config({"vehicle": "orca_1_43", "control": {"period": 0.02}}, fx)
    assert cfg["control"]["delay"] == {"steering": 0.0, "throttle": pytest.approx(0.08)}
    assert cfg["effects"]["delay"] == cfg["control"]["delay"] and cfg["control"]["lag"] == {"steering": 0.0}
    assert fx.summary()["controller_delays"] == {"throttle": pytest.approx(0.08)}
    # both delays claimed: each to its own channel, each rounded
    both = controller_effects(_diagnosis(tmp_path / "B", ["steer_delay", "throttle_delay"],
                                         {"steer_delay": 0.041, "throttle_delay": 0.109}), period=0.02)
    assert both.delays == {"steer": pytest.approx(0.04), "throttle": pytest.approx(0.1)}
    assert both.applied == ["steer_delay", "throttle_delay"] and both.not_applied == []
    raw["candidates"][0]["params"]["delay"] = 1.2
    (d / "diagnosis.json").write_text(json.dumps(raw))
    with pytest.raises(DdynError, match="throttle_delay delay = 1.2 s is outside control.delay's 0..1 s"):
        controller_effects(d)


def test_the_sil_controller_reads_a_throttle_delay_from_a_diagnosis(tmp_path):
    """`ddyn sil run --effects-from D --config-only` writes the claimed throttle delay, rounded, into the SIL's
    controller.json, and the controller accepts the file (its effects.delay matches control.delay)."""
    d = _diagnosis(tmp_path / "D", ["throttle_delay"], {"throttle_delay": 0.095})
    out = tmp_path / "cfg"
    assert main(["sil", "run", "--effects-from", str(d), "--config-only", "--out", str(out)]) == 0
    cfg = json.loads((out / "controller.json").read_text())
    assert cfg["control"]["delay"] == {"steering": 0.0, "throttle": pytest.approx(0.1)}
    assert cfg["effects"]["delay"] == cfg["control"]["delay"]
    bins = sil.build_binaries(None)
    ok = subprocess.run([str(bins / "ddyn_controller"), "--check", str(out / "controller.json")],
                        capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    assert json.loads(ok.stdout)["control"]["delay"]["throttle"] == pytest.approx(0.1)


@pytest.mark.parametrize("content, says", [
    (None, "no such file"),
    ("not json", "not a diagnosis: not JSON"),
    ("[1, 2]", "not an object"),
    (json.dumps({"model": {"effects": []}}), "no key 'selected'"),
    (json.dumps({"selected": ["steer_delay"], "model": {"effects": []}}),
     "model.effects: no estimate of the selected effect 'steer_delay'"),
    (json.dumps({"selected": ["warp_drive"], "model": {"effects": []}}), "selected[0]: unknown effect 'warp_drive'"),
    (json.dumps({"selected": ["steer_delay"], "model": {"effects": [{"effect": "steer_delay",
                                                                     "params": {"delay": "soon"}}]}}),
     "model.effects[0].params.delay: expected a finite number"),
    (json.dumps({"selected": ["steer_delay"], "model": {"effects": [{"effect": "steer_delay",
                                                                     "params": {"delay": 3.0}}]}}),
     "outside control.delay's 0..1 s"),
])
def test_bad_input_is_one_line_naming_the_file_and_key(tmp_path, content, says):
    d = tmp_path / "D"
    d.mkdir()
    if content is not None:
        (d / "diagnosis.json").write_text(content)
    with pytest.raises(DdynError) as e:
        controller_effects(d)
    msg = str(e.value)
    assert "\n" not in msg and says in msg and "diagnosis.json" in msg


def test_the_command_writes_the_configuration_and_names_what_it_cannot_apply(tmp_path, capsys):
    d = _diagnosis(tmp_path / "D", ["steer_delay", "steer_lag"], {"steer_delay": 0.041, "steer_lag": 0.05})
    out = tmp_path / "cfg"
    assert main(["sil", "run", "--effects-from", str(d), "--config-only", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "steer_lag: found 0.05, not applied: selected with steer_delay" in printed and "not driven" in printed
    cfg = json.loads((out / "controller.json").read_text())
    assert cfg["control"]["delay"] == {"steering": 0.04, "throttle": 0.0}   # 41 ms: two periods of 20 ms
    assert cfg["effects"]["diagnosis_sha256"] == hashlib.sha256((d / "diagnosis.json").read_bytes()).hexdigest()
    assert (out / "raceline.csv").is_file() and not (out / "sil_metrics.json").exists()
    # bad input: one line, exit 2
    assert main(["sil", "run", "--effects-from", str(tmp_path / "nope"), "--config-only", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "nope: no such file" in err and len(err.splitlines()) == 1
    assert main(["sil", "run", "--effects-from", str(d), "--controller-delays", "steer=0.02", "--config-only",
                 "--out", str(out)]) == 2
    assert main(["sil", "run", "--effects-from", str(d), "--controller-lag", "steer=0.02", "--config-only",
                 "--out", str(out)]) == 2


def test_the_controller_refuses_a_configuration_edited_after_it_was_made(tmp_path):
    """The SIL's controller.json made from a diagnosis passes the controller's check; its control.delay edited,
    the same file is refused naming effects.delay."""
    bins = sil.build_binaries(None)
    orca = load_vehicle("orca_1_43")
    d = _diagnosis(tmp_path / "D", ["steer_delay"], {"steer_delay": 0.04})
    fx = controller_effects(d)
    spec = sil.SilSpec.true_car(orca, load_track("ethzMobil"), controller_delays=fx.delays,
                                effects_from=fx.summary())
    table = sil.raceline_table(spec.track, orca)
    path = sil.write_controller_files(spec, table, tmp_path, str(tmp_path))
    cfg = json.loads(path.read_text())
    assert cfg["control"]["delay"] == {"steering": 0.04, "throttle": 0.0}
    assert cfg["effects"]["diagnosis_sha256"] == fx.sha256
    ok = subprocess.run([str(bins / "ddyn_controller"), "--check", str(path)], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    cfg["control"]["delay"]["steering"] = 0.06
    path.write_text(json.dumps(cfg))
    bad = subprocess.run([str(bins / "ddyn_controller"), "--check", str(path)], capture_output=True, text=True)
    assert bad.returncode == 2
    assert "effects.delay" in bad.stderr and fx.sha256[:12] in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


def test_the_controller_refuses_an_edited_lag_and_a_bad_one(tmp_path):
    """A configuration made from a diagnosis claiming steer_lag passes the controller's check; control.lag edited,
    it is refused naming effects.lag; a control.lag outside 0..1 s or not a number is one line naming the key."""
    bins = sil.build_binaries(None)
    orca = load_vehicle("orca_1_43")
    fx = controller_effects(_diagnosis(tmp_path / "D", ["steer_lag"], {"steer_lag": 0.05}))
    spec = sil.SilSpec.true_car(orca, load_track("ethzMobil"), controller_delays=fx.delays, controller_lag=fx.lag,
                                effects_from=fx.summary())
    path = sil.write_controller_files(spec, sil.raceline_table(spec.track, orca), tmp_path, str(tmp_path))
    cfg = json.loads(path.read_text())
    assert cfg["control"]["lag"] == {"steering": 0.05} and cfg["effects"]["lag"] == {"steering": 0.05}

    def check(c):
        path.write_text(json.dumps(c))
        return subprocess.run([str(bins / "ddyn_controller"), "--check", str(path)], capture_output=True, text=True)

    ok = check(cfg)
    assert ok.returncode == 0, ok.stderr
    assert json.loads(ok.stdout)["control"]["lag"]["steering"] == 0.05
    cfg["control"]["lag"]["steering"] = 0.1
    bad = check(cfg)
    assert bad.returncode == 2
    assert "effects.lag" in bad.stderr and fx.sha256[:12] in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
    del cfg["effects"]
    for value in (-0.01, 1.5, "fast"):
        cfg["control"]["lag"]["steering"] = value
        bad = check(cfg)
        assert bad.returncode == 2, value
        assert "control.lag" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1, bad.stderr


def test_the_delay_is_the_one_fitted_alone_to_the_nearest_period(tmp_path):
    """With steer_lag claimed beside it the joint fit splits the delay (the runtime carries only the delay): the
    value written is the steering delay fitted alone, rounded to the nearest whole control period when the period
    is known (what the runtime does with it: 57 ms acts as 3 periods of 20 ms)."""
    d = _diagnosis(tmp_path / "D", ["steer_delay", "steer_lag"], {"steer_delay": 0.0286, "steer_lag": 0.02})
    raw = json.loads((d / "diagnosis.json").read_text())
    raw["candidates"] = [{"effect": "steer_delay", "params": {"delay": 0.057}},
                         {"effect": "steer_lag", "params": {"tau": 0.05}}]
    (d / "diagnosis.json").write_text(json.dumps(raw))
    assert controller_effects(d).delays == {"steer": 0.057}
    fx = controller_effects(d, period=0.02)
    assert fx.delays["steer"] == pytest.approx(0.06)
    assert fx.applied_estimates["steer_delay"] == {"alone": 0.057, "joint": 0.0286, "written": fx.delays["steer"],
                                                   "period": 0.02}
    assert fx.estimates == {"steer_delay": 0.0286, "steer_lag": 0.02}
    assert "fitted alone 0.057 s, joint 0.0286 s" in fx.lines()[0]
    raw["candidates"][0]["params"]["delay"] = None
    (d / "diagnosis.json").write_text(json.dumps(raw))
    with pytest.raises(DdynError, match=r"candidates\[0\]\.params\.delay: expected a finite number"):
        controller_effects(d)
