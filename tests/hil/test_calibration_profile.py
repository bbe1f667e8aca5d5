"""Calibration and tuning on plants nobody told the twin (issue 20): the emulator draws its plant within its
stated ranges from a seed, each hinge its own values and the effects the twin leaves out; the drawn values stay
in its log, read here only to judge (twin.hil.calibration_verdict.judged: every interval against the drawn value, every value
called identifiable within 15 % of it; the held-out criterion against the twin given the drawn shared values)."""

import json

import numpy as np
import pytest

from twin.cli import main as vrscroll
from twin.device.spec import load_spec
from twin.formats.profile import select_profile
from twin.formats.run import read_run
from twin.hil.calibration import trace_rmse
from twin.hil.calibration_verdict import held_out_improved, judged
from twin.hil.mirror import mirror
from twin.link.drawn_plant import drawn_hinges, drawn_plant, emulator_args
from twin.link.serial_link import Link

COVERAGE = 0.95  # of (seed, hinge, parameter) intervals must hold the drawn value
SETTLE_AGREEMENT = 0.15  # the device settles within this share of the twin's prediction, every hinge
# how much each suite spends on a plant: the held-out scenario's cycles, calibrate's and tune's search options,
# and how many plants tune must push to at least (it refuses where no gains keep the limit on every plant of the
# intervals: 4 of 20 in each of two slow runs). The slow test's are the commands' defaults (tune's a larger search
# than its default); the default suite's are smaller so that two plants fit its time: what is judged is that the
# calibrated twin predicts the device and the pushed gains keep the limit, not how good the gains are. With two
# plants, a refusal on both can happen (a named refusal is a pass), so there the push is not required.
SLOW = {"hold_cycles": 2, "calibrate": [], "tune": ["--population", "16", "--generations", "5"], "min_pushed": 10}
DEFAULT = {"hold_cycles": 1, "calibrate": ["--population", "16", "--generations", "6"],
           "tune": ["--population", "8", "--generations", "3"], "min_pushed": 0}


def _json(capsys, *args):
    assert vrscroll(list(args)) == 0, capsys.readouterr().err
    return json.loads(capsys.readouterr().out)


def calibrated_on_a_drawn_plant(seed, emulator, folder, capsys, effort: dict) -> tuple[dict, list[str]]:
    """Record the calibration scenario and a held-out one on the plant drawn from `seed`, calibrate per hinge
    into a device profile, tune on it and push the gains (effort: SLOW or DEFAULT). Tuning pushes only gains
    that keep every limit on every plant of the calibrated intervals; where none do, it must say which limit it
    broke on which plant and which parameter's range set the worst case, and push nothing ("refused" in the
    tally). Returns the judged tally and what failed in words (a value called identifiable off the drawn one, the
    held-out criterion, a refusal that does not say why, pushed gains that overshoot the limit or settle off the
    twin's prediction by more than SETTLE_AGREEMENT)."""
    spec = load_spec()
    folder.mkdir()
    assert vrscroll(["device", "select", "none"]) == 0  # a new device: not the last seed's profile (its gains)
    emu = emulator(*emulator_args(seed))
    truth, hinges = drawn_plant(emu), drawn_hinges(emu)
    # the calibration scenario (2 cycles, 7.5 s), for the gains the device has (read from it), and a held-out one
    with Link(emu.port) as link:  # wake the device: from its limp boot pose to flat, allowing for its difference
        assert mirror(link, spec, np.zeros(spec.n_hinges), tolerance_deg=30.0).ok
    for name, s, cycles in (("train", 0, 2), ("hold", 1, effort["hold_cycles"])):
        assert vrscroll(["scenario", str(folder / f"{name}.toml"), "--serial", emu.port, "--seed", str(s),
                         "--cycles", str(cycles)]) == 0
        assert vrscroll(["hil", str(folder / f"{name}.toml"), "--serial", emu.port, "--out", str(folder / name),
                         "--tolerance-deg", "30"]) == 0
    capsys.readouterr()
    device = f"drawn{seed}"
    cal = _json(capsys, "calibrate", str(folder / "train"), "--holdout", str(folder / "hold"), "--device", device,
                "--per-hinge", *effort["calibrate"], "--json", "-")
    # each hinge's own values kept in the profile where they predict the held-out run no worse than the shared
    fit, kept = cal["per_hinge_fit"], select_profile(device).hinges
    shared_rms, own_rms = (float(np.sqrt(np.mean([r[k] ** 2 for r in fit["holdout"]])))
                           for k in ("rmse_shared_deg", "rmse_per_hinge_deg"))
    assert fit["kept"] == (kept is not None) == (own_rms <= shared_rms + 1e-4), (fit["kept"], shared_rms, own_rms)
    for row, own in zip(fit["hinges"], kept or []):
        assert all(getattr(own, p) == pytest.approx(e["value"]) for p, e in row["parameters"].items())
    tally = judged(cal, hinges, truth)
    failed = [f"seed {seed}: {m}" for m in tally.pop("misses") if "identifiable" in m]
    floor = trace_rmse(read_run(folder / "hold", spec),
                       spec.replace(**{k: v for k, v in truth.items() if k != "supply_voltage"}), spec)
    floor = float(np.sqrt(np.mean(floor ** 2)))
    if not held_out_improved(cal["holdout"], floor, spec):
        failed.append(f"seed {seed}: held-out {cal['holdout']['overall_before_deg']} -> "
                      f"{cal['holdout']['overall_after_deg']} deg, floor {floor:.4f}")
    # tuned on the calibrated twin over its intervals, pushed to the device where they keep every limit
    rc = vrscroll(["tune", "--device", device, *effort["tune"], "--threads", "2", "--serial", emu.port,
                   "--json", str(folder / "tune.json")])
    tuned = json.loads((folder / "tune.json").read_text())
    tally["refused"] = int(rc != 0)
    if rc != 0 and not (tuned["limits_broken"] and tuned["worst_case_range"] and "device" not in tuned):
        failed.append(f"seed {seed}: tune failed ({rc}) without naming the limit it broke and the range")
    for r in tuned.get("device", []):
        if r["device_overshoot_deg"] > 1.0:
            failed.append(f"seed {seed}: hinge {r['hinge']} overshoots {r['device_overshoot_deg']} deg")
        if abs(r["device_settle_s"] / r["twin_settle_s"] - 1) > SETTLE_AGREEMENT:
            failed.append(f"seed {seed}: hinge {r['hinge']} settles in {r['device_settle_s']} s, the twin "
                          f"predicted {r['twin_settle_s']} s")
    emu.stop()  # (one emulator at a time: each runs in real time)
    return tally, failed


def judge_seeds(seeds, emulator, tmp_path, capsys, effort: dict) -> None:
    """Every seed's plant calibrated and tuned: the intervals hold the drawn values COVERAGE of the time over
    all of them, gains were pushed to at least effort's min_pushed, and nothing in `calibrated_on_a_drawn_plant`'s
    list failed on any."""
    total, failed = {}, []
    for seed in seeds:
        tally, why = calibrated_on_a_drawn_plant(seed, emulator, tmp_path / f"seed{seed}", capsys, effort)
        total = {k: total.get(k, 0) + v for k, v in tally.items()}
        failed += why
    print(f"over {len(seeds)} drawn plants: {total}")  # (with -s: how many intervals held, tunings refused)
    assert total["hold"] >= COVERAGE * total["intervals"], total
    assert len(seeds) - total["refused"] >= effort["min_pushed"], total
    assert not failed, failed


@pytest.mark.slow  # 199 s of the default suite's 576 on 2 cores (2026-11-27, quiet): the suite's 600 s budget;
# the twenty-plant test below and issue 36's identification tests (two drawn plants) stay
def test_calibration_and_tuning_on_two_drawn_plants(emulator, tmp_path, capsys):
    """Issue 20's criteria on two plants: plants drawn with each hinge's own speed, friction, damping and
    inertia, cogging at any phase, friction ripple and warming windings, never told to the twin. With less
    effort than the slow test's (DEFAULT)."""
    judge_seeds((21, 22), emulator, tmp_path, capsys, DEFAULT)


@pytest.mark.slow
def test_calibration_and_tuning_on_twenty_drawn_plants(emulator, tmp_path, capsys):
    judge_seeds(range(1, 21), emulator, tmp_path, capsys, SLOW)
