"""Calibration and tuning on a plant nobody told the twin (the stated ranges): the emulator draws its
plant within its stated ranges from a seed; the drawn values stay in its log, read here only to judge."""

import json

import numpy as np
import pytest

from random_plant import drawn_plant, emulator_args, held_out_improved
from twin.cli import main as vrscroll
from twin.device.spec import load_spec
from twin.formats.run import read_run
from twin.device.variation import SPREAD
from twin.hil.calibration import trace_rmse
from twin.hil.mirror import mirror
from twin.link.serial_link import Link


def _json(capsys, *args):
    assert vrscroll(list(args)) == 0, capsys.readouterr().err
    return json.loads(capsys.readouterr().out)


def calibrate_and_tune_on_a_drawn_plant(seed, emulator, tmp_path, capsys):
    spec = load_spec()
    emu = emulator(*emulator_args(seed))
    truth = drawn_plant(emu)
    with Link(emu.port) as link:  # wake the device: from its limp boot pose to flat, allowing for its difference
        assert mirror(link, spec, np.zeros(spec.n_hinges), tolerance_deg=30.0).ok
    train, hold = tmp_path / "train", tmp_path / "hold"
    # the calibration scenario, for the gains the device has (read from it), and a held-out one
    for name, s in (("train", 0), ("hold", 1)):
        assert vrscroll(["scenario", str(tmp_path / f"{name}.toml"), "--serial", emu.port,
                         "--seed", str(s)]) == 0
        assert vrscroll(["hil", str(tmp_path / f"{name}.toml"), "--serial", emu.port, "--out", str(tmp_path / name),
                         "--tolerance-deg", "30"]) == 0
    capsys.readouterr()
    cal = _json(capsys, "calibrate", str(train), "--holdout", str(hold), "--device", "drawn", "--json", "-")
    assert cal["device_profile"] == "drawn"
    assert any(e["value"] != e["prior"] for e in cal["parameters"].values()), cal["parameters"]
    for p, e in cal["parameters"].items():
        assert e["low"] <= e["value"] <= e["high"] and e["low"] < e["high"], (p, e)  # (at a bound of the search)
        if e["identifiable"]:  # within 20 % of the truth
            assert e["value"] == pytest.approx(truth[p], rel=0.2), (p, e, truth[p])
        else:  # fitted loosely (its interval wider than x(1 -+ 0.15)), or left at its prior: its prior range open
            lo, hi = (e["prior"] * r for r in SPREAD[p])
            assert e["low"] <= lo * (1 + 1e-9) and e["high"] >= hi * (1 - 1e-9), (p, e)
    # held-out error: at least half of what can go is gone, or the rest is at the floor (held_out_improved)
    h = cal["holdout"]
    run = read_run(hold, spec)
    floor = trace_rmse(run, spec.replace(**{k: v for k, v in truth.items() if k != "supply_voltage"}), spec)
    floor = float(np.sqrt(np.mean(floor ** 2)))
    assert held_out_improved(h, floor, spec), (h, floor)
    # tuned on the calibrated twin over its intervals, pushed to the device: the overshoot limit holds and
    # the device settles within 15 % of the twin's prediction on every hinge
    tuned = _json(capsys, "tune", "--population", "16", "--generations", "5", "--threads", "2",
                  "--serial", emu.port, "--log", str(tmp_path / "tune.jsonl"), "--json", "-")
    assert tuned["device_profile"] == "drawn"
    for r in tuned["device"]:
        assert r["device_overshoot_deg"] <= 1.0, tuned["device"]
        assert r["device_settle_s"] == pytest.approx(r["twin_settle_s"], rel=0.15), tuned["device"]
    return cal, tuned, truth, floor


# slow, and not yet reliable enough for the default suite: seed 1 failed 2 of its last 3 runs (once a pushed
# gain overshot 1.2 deg against the 1 deg limit); docs/tuning-hil-calibration.md "Measured"
@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_calibration_and_tuning_on_drawn_plants(seed, emulator, tmp_path, capsys):
    calibrate_and_tune_on_a_drawn_plant(seed, emulator, tmp_path, capsys)
