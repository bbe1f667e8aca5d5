"""Tuning on the twin, HIL comparison runs and calibration, against the device emulator on a pty."""

import dataclasses
import json
import math
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from controllers.encoder import target_counts
from controllers.pid import PidGains
from twin.cli import main as vrscroll
from twin.device.spec import load_spec
from twin.formats.gains import read_gains, write_gains
from twin.formats.run import read_run, write_run_meta
from twin.formats.scenario import write_scenario
from twin.formats.trace import TraceWriter, read_trace
from twin.hil.calibration import trace_rmse
from twin.hil.calibration_verdict import held_out_improved
from twin.hil.compare import compare
from twin.hil.device_gains import device_gains
from twin.hil.identification import SHOWN_BY
from twin.hil.mirror import device_step
from twin.hil.shared_plant import (ALIKE, SHARED_BACKLASH_DEG, SHARED_PLANT, SHARED_SCALES, record_soft,
                                   shared_truth, training_scenario)
from twin.link import protocol as P
from twin.link.serial_link import Link
from twin.records.gains import Gains
from twin.sim.batch import TwinBatch
from twin.sim.gate import check_move
from twin.sim.replay import twin_at_start
from twin.sim.response import move_report, step_metrics
from twin.sim.twin import Twin
from twin.device.variation import tolerance_ranges
from twin.tuning.tuner import RobustEvaluator, TuneGoal, chains, step_report, tune

ROOT = Path(__file__).resolve().parents[2]

@pytest.fixture(scope="module")
def tuned():
    spec = load_spec()
    goal = TuneGoal()
    return spec, goal, tune(spec, goal, population=24, generations=5, nthread=2)


def test_tuned_gains_beat_the_spec_defaults_on_the_twin(tuned, tmp_path):
    spec, goal, result = tuned
    before, _ = step_report(spec, PidGains.from_spec(spec), goal)
    after, _ = step_report(spec, result.gains, goal)
    limit = math.degrees(goal.max_overshoot)
    assert np.all(after.settle_time < before.settle_time), (before, after)
    assert np.all(np.degrees(after.overshoot) <= np.maximum(np.degrees(before.overshoot), limit) + 1e-9), (before, after)
    # robust: the worst of the five plants also keeps the overshoot limit
    assert np.all(np.degrees(result.overshoot) <= limit) and np.all(np.isfinite(result.settle))
    assert np.all(result.peak_current <= spec.driver_peak_current) and np.all(result.cost < goal.duration)
    # and the gate lets the tuned step through, unmodified
    gate = check_move(spec, np.zeros(spec.n_hinges), np.full(spec.n_hinges, goal.step), result.gains)
    assert gate.passed, gate.text()
    path = tmp_path / "gains.json"
    write_gains(path, Gains(result.gains, {"test": True}))
    assert read_gains(path, spec.n_hinges) == Gains(result.gains, {"test": True})
    assert json.loads(path.read_text())["units"]["kp"] == "duty/count"


def test_the_two_chains_of_hinges_do_not_move_each_other(spec):
    """What lets the tuner search each chain on its own: the root flap is held. Mechanically the chains are
    independent (a stiff pack); through the shared pack's sag they move each other a little."""
    left, right = chains(spec)
    base = PidGains.from_spec(spec)
    other = [base.replace(kp=base.kp * 3.0) if k in right else base for k in range(spec.n_hinges)]
    for pack_resistance in (0.0, spec.pack_resistance):
        batch = TwinBatch(2, spec.replace(pack_resistance=pack_resistance), nthread=1)
        batch.set_gains([[base] * spec.n_hinges, other])  # the second simulation: another kp on the right chain only
        angle = batch.run(np.full(spec.n_hinges, math.radians(30.0)), 0.4)["angle"]
        right_moved = np.abs(angle[:, 0, right] - angle[:, 1, right]).max()
        assert right_moved > 1e-3
        left_moved = np.abs(angle[:, 0, left] - angle[:, 1, left]).max()
        assert left_moved < (1e-9 if pack_resistance == 0 else 0.2 * right_moved)


def test_tune_command_writes_a_gains_file(tmp_path, capsys):
    out = tmp_path / "g.json"
    assert vrscroll(["tune", "--population", "8", "--generations", "2", "--threads", "2", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "spec defaults" in text and "tuned" in text and out.exists() and "every limit kept on every plant" in text
    assert vrscroll(["tune", "--tolerance-pct", "150"]) == 2
    # a limit out of reach: the gains are written, each hinge that breaks it named, and the exit status says so
    assert vrscroll(["tune", "--population", "6", "--generations", "1", "--threads", "2", "--out", str(out),
                     "--max-overshoot-deg", "0.05"]) == 1
    text = capsys.readouterr().out
    meta = json.loads(out.read_text())["meta"]
    assert "NOT KEPT" in text and meta["limits_broken"]
    # and says which interval's end sets each broken hinge's worst case, and which experiment shows that value
    said = next(ln for ln in text.splitlines() if ln.startswith("its worst case set by "))
    for broken in meta["limits_broken"]:
        row = meta["worst_case_range"][int(broken.split(":")[0].split()[1])]
        assert f"{row['parameter']} at the {row['end']} end of its interval" in said, (said, row)
        assert SHOWN_BY[row["parameter"]] in said


def test_tune_command_with_port_pushes_the_gains_and_runs_the_step_on_the_device(emulator, tmp_path, capsys):
    spec = load_spec()
    emu = emulator()
    out, log = tmp_path / "g.json", tmp_path / "tune.jsonl"
    assert vrscroll(["tune", "--population", "8", "--generations", "2", "--threads", "2", "--out", str(out),
                     "--serial", emu.port, "--log", str(log)]) == 0
    text = capsys.readouterr().out
    gains = read_gains(out, spec.n_hinges).hinges
    # the device got every hinge's tuned gains, and holds them
    pushed = {e["hinge"]: e["gains"] for e in emu.events("rx") if e["msg"] == "SET_GAINS"}
    assert pushed == {k: dataclasses.asdict(P.Gains.from_pid(g)) for k, g in enumerate(gains)}
    with Link(emu.port) as link:
        assert [link.get_gains(k) for k in range(spec.n_hinges)] == [P.Gains.from_pid(g) for g in gains]
    # then ran the same step (flat, then 30 deg on every hinge) and printed its metrics beside the twin's; the
    # gains were pushed at flat, once the move there (from wherever the device stood, with the gains it held) was
    # done: the tuner checked its limits on the step from flat, not on that move
    heard = [(e["msg"], e.get("counts")) for e in emu.events("rx") if e["msg"] in ("SET_TARGETS", "SET_GAINS")]
    assert heard[-1] == ("SET_TARGETS", target_counts(spec, np.full(spec.n_hinges, math.radians(30.0))).tolist())
    first_gains = heard.index(("SET_GAINS", None))
    assert heard[first_gains - 1] == ("SET_TARGETS", [0] * spec.n_hinges), heard
    assert [m for m, _ in heard[first_gains:-1]] == ["SET_GAINS"] * spec.n_hinges, heard
    assert f"device at {emu.port}: settled: settle time" in text
    lines = text.splitlines()
    head = next(i for i, ln in enumerate(lines) if "device settle s" in ln and "twin settle s" in ln)
    rows = [ln.split() for ln in lines[head + 1:head + 1 + spec.n_hinges]]
    assert [int(r[0]) for r in rows] == list(range(spec.n_hinges))
    assert all(0 < float(r[1]) < 0.5 and 0 < float(r[2]) < 0.5 for r in rows)  # device and twin settle, s


def test_the_twin_predicts_a_step_from_the_integral_the_device_holds(emulator):
    """Within the hold band the PID's duty is off and its integral frozen, at what it was when the hinge came
    in: a device at rest holds an integral set by how it came there, and the next step starts from it. On
    the twin's own plant (--ideal), after a history that winds it (the boot sag lifted to flat, a step out
    and back), the twin started with the integral STATE reports predicts the step on every hinge; started
    empty, the hanging hinges' came out 10-13 % slower than the device's. The device's settle time is read from
    its telemetry frames (2 ms apart at mirror's 500 Hz): one frame's time is allowed beside the 5 %."""
    spec = load_spec()
    emu = emulator("--ideal", "--no-warming")
    targets = np.full(spec.n_hinges, math.radians(30))
    band = math.degrees(spec.settle_band * spec.rad_per_count)
    goal = math.degrees(round(targets[0] / spec.rad_per_count) * spec.rad_per_count)
    time.sleep(0.5)  # limp at boot: the flaps beside the root sag
    with Link(emu.port) as link:
        assert device_step(link, spec, targets)[3].ok  # lifted to flat from the sag, then out
        t, deg, start, res = device_step(link, spec, targets)  # back to flat, then out again
    assert res.ok, res.message
    assert np.abs(start.integral).max() > 0.01  # what the hanging hinges hold their weight with
    twin = twin_at_start(spec, PidGains.from_spec(spec), start)
    pred = move_report(spec, twin.move_to(targets, max_time=1.0, stop_when_settled=False)).settle_time
    dev = [step_metrics(t, deg[:, k], goal, band, hold=spec.settle_hold).settle_time for k in range(spec.n_hinges)]
    frame = 1.0 / spec.max_telemetry_rate  # s: the device's settle time is known to a telemetry frame
    assert np.allclose(dev, pred, rtol=0.05, atol=frame), (dev, pred, np.round(np.array(dev) / pred - 1, 3))


def test_tuned_gains_on_the_emulator_settle_as_the_twin_predicts(tuned, emulator, tmp_path):
    spec, goal, result = tuned
    emu = emulator()
    targets = np.full(spec.n_hinges, goal.step)
    with Link(emu.port) as link:
        for k, g in enumerate(result.gains):
            link.set_gains(g, hinge=k)
        t, deg, start, res = device_step(link, spec, targets)
    assert res.ok, res.message
    twin = twin_at_start(spec, result.gains, start)
    pred = move_report(spec, twin.move_to(targets, max_time=1.5, stop_when_settled=False))
    band = math.degrees(spec.settle_band * spec.rad_per_count)
    tgt = math.degrees(round(goal.step / spec.rad_per_count) * spec.rad_per_count)
    dev = [step_metrics(t, deg[:, k], tgt, band).settle_time for k in range(spec.n_hinges)]
    twin_s = pred.settle_time
    assert abs(np.mean(dev) - np.mean(twin_s)) <= 0.25 * np.mean(twin_s), (dev, twin_s)


def test_hil_interrupted_half_way_keeps_both_traces(emulator, tmp_path):
    emu = emulator()
    scen = tmp_path / "steps.toml"
    write_scenario(scen, training_scenario(3.0, 1.0, 2.0))
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "twin.cli", "hil", str(scen), "--serial", emu.port, "--out", str(out)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    # kill it once it has played half of the 3 s scenario
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if line.startswith("t=") and float(line[2:].split()[0]) >= 1.5:
            break
    proc.send_signal(signal.SIGKILL)
    proc.wait(5)
    proc.stdout.close()
    dev, tw = read_trace(out / "device.csv"), read_trace(out / "twin.csv")
    assert 1.4 <= dev.time[-1] < 2.9 and 1.4 <= tw.time[-1] < 2.9
    assert abs(dev.time[-1] - tw.time[-1]) < 0.1  # the twin keeps up with the device
    assert len(dev.time) > 400 and dev.n_hinges == 6
    meta = json.loads((out / "run.json").read_text())
    assert meta["status"] == "running" and len(meta["changes"]) >= 2
    rows = compare(load_spec(), dev, tw,
                   [c["t_s"] for c in meta["changes"]])
    assert all(r["rmse_deg"] < 2.0 for r in rows)


def test_hil_command_writes_report(emulator, tmp_path, capsys):
    emu = emulator()
    scen = tmp_path / "s.toml"
    write_scenario(scen, training_scenario(1.2, 0.4, 0.8))
    out = tmp_path / "run"
    assert vrscroll(["hil", str(scen), "--serial", emu.port, "--out", str(out)]) == 0
    report = (out / "report.md").read_text()
    assert "| hinge | RMSE deg" in report and "![hinge 5](hinge5.png)" in report
    assert all((out / f"hinge{k}.png").stat().st_size > 1000 for k in range(6))
    metrics = json.loads((out / "metrics.json").read_text())
    assert all(m["rmse_deg"] < 1.5 and abs(m["lag_s"]) <= 0.01 for m in metrics)


def test_hil_warns_when_the_device_did_not_follow_the_twin(emulator, tmp_path, capsys):
    """A zero confirmed while the flaps hung from the root flap (bring-up on the emulator as it starts, not lying
    flat): a fold to -40 deg takes hinges 2-3 past where the flaps can go, the device leaves the twin, and `hil`
    says so, naming those hinges and what to check, rather than only writing its report."""
    emu = emulator()
    time.sleep(1.0)  # the flaps beside the root sag while nothing drives them
    assert vrscroll(["zero", "--serial", emu.port]) == 0
    (tmp_path / "fold.toml").write_text('name = "fold"\nduration_s = 0.3\n[[step]]\nt_s = 0.0\n'
                                        'angles_deg = [-40, -40, -40, -40, -40, -40]\n')
    capsys.readouterr()
    assert vrscroll(["hil", str(tmp_path / "fold.toml"), "--serial", emu.port, "--out", str(tmp_path / "run"),
                     "--tolerance-deg", "90"]) == 0
    err = capsys.readouterr().err
    assert "did not follow the twin on hinge(s)" in err and "vrscroll zero" in err, err
    far = [r["hinge"] for r in json.loads((tmp_path / "run" / "metrics.json").read_text()) if r["rmse_deg"] > 5.0]
    assert {2, 3} <= set(far) and all(f"{k} (" in err for k in far), (far, err)
    # calibrating on it says the same before it fits
    assert vrscroll(["calibrate", str(tmp_path / "run"), "--generations", "1", "--population", "4",
                     "--out", str(tmp_path / "cal.toml")]) == 0
    err = capsys.readouterr().err
    assert "warning:" in err and "did not follow the twin on hinge(s)" in err, err


def test_gear_damping_shows_in_the_motion(spec):
    """The drive train fixes the motor constant by the datasheet's no-load point, so gear damping is
    a loss of its own: more of it slows the hinges (before, K followed the damping and the motion hid it)."""
    soft = PidGains.from_spec(spec).replace(kp=0.015, ki=0.05, kd=0.0003)
    traces = []
    for plant in (spec, spec.replace(gear_damping=spec.gear_damping * 1.6)):
        twin = Twin(plant, soft)
        traces.append(twin.move_to(np.radians([30, 20, 10, 10, 20, 30]), max_time=0.8, stop_when_settled=False))
    assert not np.array_equal(traces[0].counts, traces[1].counts)
    assert np.degrees(np.abs(traces[0].true_angle - traces[1].true_angle).max()) > 0.1


# slow until calibration's intervals hold on every recording (issue 20): in four CI-style runs of 2026-11-26 it
# failed twice, once on the floor check (since loosened to what floor_deg documents) and once because the
# speed's interval, x0.764 .. x0.889, missed the drawn x0.75 (the warming windings load onto speed)
@pytest.mark.slow
def test_calibration_recovers_the_emulators_plant(emulator, tmp_path, capsys):
    spec = load_spec()
    # known to the test, not to the calibration (latency stays on); soft gains, another recipe than the
    # calibration scenario's (tests/hil/test_calibration_profile.py). Every hinge alike, no cogging, no ripple,
    # windings that do not warm: a plant the shared fit can represent (the twin's nominal cogging within what
    # calibration bounds). With its windings warming, this fit has called a wrong rotor inertia (x1.80 for x1.3)
    # identifiable; with its hinges drawn apart, x2.07: what issue 20 asked calibration to stop doing
    # (tests/hil/test_calibration_profile.py).
    truth = SHARED_SCALES | {"backlash": math.radians(SHARED_BACKLASH_DEG) / spec.backlash}
    emu = emulator(*SHARED_PLANT, *ALIKE)
    train, hold, cal = record_soft(emu, spec, tmp_path)
    capsys.readouterr()
    assert vrscroll(["calibrate", str(train), "--holdout", str(hold), "--out", str(cal), "--json",
                     str(tmp_path / "cal.json")]) == 0
    res = json.loads((tmp_path / "cal.json").read_text())
    # printed for a person: each value and its one interval in the spec file's unit (the backlash in deg, as the
    # command line gives it), no Hessian
    text = capsys.readouterr().out
    [line] = [ln for ln in text.splitlines() if ln.strip().startswith("backlash ")]
    assert line.count(" deg") == 2 and "interval" in line and "singular values of" not in text
    for name, scale in truth.items():  # what it reports as identifiable, within 20 % of the truth
        if res["parameters"][name]["identifiable"]:
            assert res["scales"][name] == pytest.approx(scale, rel=0.2), res["parameters"]
    # the top speed is what this scenario shows best: its interval holds the truth (fitted within 20 % of it on
    # most recordings; on about one in four, since the emulator's windings warm and its timing varies, the
    # runs show it less and its interval widens to say so)
    speed = res["parameters"]["no_load_speed"]
    assert speed["low"] <= spec.no_load_speed * truth["no_load_speed"] <= speed["high"], speed
    # held-out trace error (RMS over every frame of every hinge): at least half of what can go is gone, or the
    # rest is at the floor the emulator's own values leave (twin/hil/calibration_verdict.py)
    h = res["holdout"]
    truth_replay = trace_rmse(read_run(hold, spec), shared_truth(spec), spec)  # per hinge, deg: the twin given the truth
    floor = float(np.sqrt(np.mean(truth_replay ** 2)))
    assert held_out_improved(h, floor, spec), (h, floor)
    # per hinge: the RMSE splits into the floor the encoder and link set and what no parameter explains; the
    # floor estimated from the run alone is near what the truth itself leaves (an estimate: where twin and device
    # agree within a count their roundings agree too, and the truth's replay was 0.106 deg where it said 0.129)
    for rows in (res["per_hinge"], h["per_hinge"]):
        assert [r["hinge"] for r in rows] == list(range(spec.n_hinges))
        for r in rows:
            left = math.sqrt(max(r["rmse_deg"] ** 2 - r["floor_deg"] ** 2, 0.0))
            assert r["unexplained_deg"] == pytest.approx(left, abs=1e-3) and r["rmse_deg"] > 0
    for r, truth_deg in zip(h["per_hinge"], truth_replay):
        assert 0.1 < r["floor_deg"] <= truth_deg + 0.03, (r, truth_deg)
    assert "what no parameter explains" in text
    calibrated = load_spec(cal)
    assert calibrated.no_load_speed == pytest.approx(res["parameters"]["no_load_speed"]["value"], rel=1e-4)
    assert "calibrated from" in cal.read_text()



ONE_STEP = """name = "one"
duration_s = 1.0
[[step]]
t_s = 0.0
angles_deg = [30, 30, 30, 30, 30, 30]
"""


def _device_gains(port):
    with Link(port) as link:
        return device_gains(link, 6)


def _gains_file(path, spec, **hinge_changes):
    """A gains file of the spec's gains, hinge k's changed by hinge_changes {k: {key: value or None to drop}}."""
    write_gains(path, Gains([PidGains.from_spec(spec)] * spec.n_hinges))
    doc = json.loads(path.read_text())
    for k, change in hinge_changes.items():
        for key, value in change.items():
            if value is None:
                del doc["hinges"][int(k[1:])][key]
            else:
                doc["hinges"][int(k[1:])][key] = value
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("change, message", [
    ({"h0": {"kp": 1000}}, "hinge 0: kp = 1000 is outside the bounds the firmware takes"),
    ({"h2": {"ki": None}}, r"hinges\[2\]: missing key 'ki'"),
    # once: hinges 0-2 got the new gains before the device refused hinge 3's
    ({"h0": {"kp": 0.05}, "h1": {"kp": 0.05}, "h2": {"kp": 0.05}, "h3": {"kd": -0.001}},
     "hinge 3: kd = -0.001 is outside the bounds"),
])
def test_hil_refuses_a_bad_gains_file_before_anything_is_sent(emulator, spec, tmp_path, capsys, change, message):
    emu = emulator()
    before = _device_gains(emu.port)
    (tmp_path / "s.toml").write_text(ONE_STEP)
    gains = _gains_file(tmp_path / "g.json", spec, **change)
    rc = vrscroll(["hil", str(tmp_path / "s.toml"), "--serial", emu.port, "--gains", str(gains),
                   "--out", str(tmp_path / "run")])
    assert rc == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and str(gains) in err
    assert re.search(message, err), err
    assert _device_gains(emu.port) == before
    assert not [e for e in emu.events("rx") if e["msg"] == "SET_GAINS"]


def test_hil_restores_the_devices_gains_when_the_gate_refuses(emulator, spec, tmp_path, capsys):
    """Gains within the firmware's bounds too weak to reach the scenario's targets in time: the gate refuses."""
    emu = emulator()
    before = _device_gains(emu.port)
    (tmp_path / "s.toml").write_text(ONE_STEP)
    weak = {f"h{k}": {"kp": 0.001, "ki": 0.0, "kd": 0.0, "deadband_duty": 0.0} for k in range(6)}
    gains = _gains_file(tmp_path / "g.json", spec, **weak)
    rc = vrscroll(["hil", str(tmp_path / "s.toml"), "--serial", emu.port, "--gains", str(gains),
                   "--out", str(tmp_path / "run")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "refused by the gate" in err and "were sent, then the device's previous gains sent back" in err
    assert "nothing was sent" not in err
    assert _device_gains(emu.port) == before
    sent = [e for e in emu.events("rx") if e["msg"] == "SET_GAINS"]
    assert len(sent) == 12  # six hinges' new gains, then six hinges' old ones
    assert not [e for e in emu.events("rx") if e["msg"] == "SET_TARGETS"]


def test_calibrate_refuses_a_run_that_did_not_complete(spec, tmp_path, capsys):
    """A run killed while recording keeps "running" in its run.json; calibrate once fitted it without a word."""
    run = tmp_path / "killed"
    run.mkdir()
    n = spec.n_hinges
    write_run_meta(run, {"scenario": "s", "start_counts": [0] * n, "start_target_counts": [0] * n,
                         "before": {"state": "IDLE", "counts": [0] * n, "target_counts": [0] * n},
                         "changes": [{"t_s": 0.0, "angles_deg": [10.0] * n}], "status": "running"})
    with TraceWriter(run / "device.csv", n) as w:
        for i in range(50):
            w.write(i * 0.002, target_deg=[10.0] * n, angle_deg=[0.0] * n, counts=[0] * n, duty=[0.1] * n,
                    current_A=[0.1] * n)
    write_gains(run / "gains.json", Gains([PidGains.from_spec(spec)] * n))
    assert vrscroll(["calibrate", str(run), "--out", str(tmp_path / "cal.toml")]) == 2
    err = capsys.readouterr().err
    assert f"{run}: the run did not complete (status 'running'" in err and "--incomplete" in err
    assert not (tmp_path / "cal.toml").exists()


def test_tune_returns_the_best_whole_candidate_it_evaluated(spec, monkeypatch):
    """Every gain set the search simulated is recorded (the real evaluator, watched); none ranks above the one
    returned: fewer hinges breaking a limit, or as many and a lower total cost. The chains' bests put together
    (never simulated whole during the search) are returned only where their own simulation ranks first."""
    seen = []
    evaluate = RobustEvaluator.evaluate

    def watched(self, kp, ki, kd):
        cost, worst = evaluate(self, kp, ki, kd)
        seen.extend(cost)
        return cost, worst

    monkeypatch.setattr(RobustEvaluator, "evaluate", watched)
    goal = TuneGoal()
    result = tune(spec, goal, population=8, generations=4, nthread=2, seed=3)
    assert len(seen) == 8 * 4 + 1
    rank = (int(np.sum(result.cost >= goal.duration)), float(result.cost.sum()))
    assert all(rank <= (int(np.sum(c >= goal.duration)), float(c.sum())) for c in seen)
    assert result.history == sorted(result.history, reverse=True)  # the best so far never gets worse
    # the numbers returned are the returned gains' own: simulated again, the same
    again, _ = RobustEvaluator(spec, goal, 1, 2, result.gains).evaluate(
        *(np.array([[getattr(g, k) for g in result.gains]]) for k in ("kp", "ki", "kd")))
    assert again[0] == pytest.approx(result.cost, abs=1e-12)


def test_tune_says_which_limit_it_could_not_keep_on_which_plant(spec):
    """An overshoot limit no gains keep on every plant (0.05 deg on a 30 deg step): the result names each hinge
    whose worst plant breaks it, and that plant; no hinge over the limit goes unnamed. Each hinge's worst
    case is traced to one parameter's range."""
    goal = TuneGoal(max_overshoot=math.radians(0.05))
    result = tune(spec, goal, population=6, generations=2, nthread=2)
    over = [h for h in range(spec.n_hinges) if result.overshoot[h] > goal.max_overshoot]
    assert over, "the limit was meant to be out of reach"
    named = {int(line.split(":")[0].split()[1]) for line in result.broken}
    assert set(over) <= named
    for line in result.broken:
        h = int(line.split(":")[0].split()[1])
        assert line.endswith(f"worst on {result.worst_plant[h]})")
        if h in over:
            assert f"overshoots {math.degrees(result.overshoot[h]):.2f} deg (limit 0.05)" in line
    ranges = tolerance_ranges(spec, goal.tolerance)
    assert all(r["parameter"] in ranges.shared and r["end"] in ("low", "high") for r in result.sensitivity)
