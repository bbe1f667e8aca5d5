"""Tuning on the twin, HIL comparison runs and calibration, against the device emulator on a pty."""

import json
import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from controllers.pid import PidGains
from controllers.tuning import TuneGoal, read_gains, step_report, tune, write_gains
from twin.hil import compare, load_run, load_scenario, read_trace, run_hil
from twin.link import Link

ROOT = Path(__file__).resolve().parent.parent

SCENARIO = """name = "steps"
duration_s = {duration}
[[step]]
t_s = 0.0
angles_deg = [30, 20, 10, 10, 20, 30]
[[step]]
t_s = {t1}
angles_deg = [5, 40, 25, 0, -10, 60]
[[step]]
t_s = {t2}
angles_deg = [8, 8, 8, 8, 8, 8]
"""

HOLDOUT = """name = "holdout"
duration_s = 1.8
[[step]]
t_s = 0.0
angles_deg = [45, 5, 20, 30, 10, 15]
[[step]]
t_s = 0.6
angles_deg = [10, 30, 5, 15, 50, 40]
[[step]]
t_s = 1.2
angles_deg = [25, 15, 35, 5, 20, 0]
"""


@pytest.fixture(scope="module")
def tuned():
    from twin.spec import load_spec

    spec = load_spec()
    goal = TuneGoal(duration=1.0)  # as long as step_report's look at the tail of the response
    return spec, goal, tune(spec, goal, population=24, generations=5, nthread=2)


@pytest.mark.xfail(strict=True, reason="issue 6 open: one hinge overshoots 1.004 deg against the 1.0 deg limit")
def test_tuned_gains_beat_the_spec_defaults_on_the_twin(tuned, tmp_path):
    spec, goal, result = tuned
    before, _ = step_report(spec, PidGains.from_spec(spec), goal.step)
    after, _ = step_report(spec, result.gains, goal.step)
    limit = math.degrees(goal.max_overshoot)
    for b, a in zip(before, after):
        assert a["settle_time_s"] < b["settle_time_s"]
        assert a["overshoot_deg"] <= max(b["overshoot_deg"], limit) + 1e-9
    # robust: the worst of the five plants also keeps the overshoot limit
    assert np.all(np.degrees(result.overshoot) <= limit) and np.all(np.isfinite(result.settle))
    path = tmp_path / "gains.json"
    write_gains(path, result.gains, {"test": True})
    assert read_gains(path, spec.n_hinges) == result.gains
    assert json.loads(path.read_text())["units"]["kp"] == "duty/count"


def test_tune_command_writes_a_gains_file(tmp_path, capsys):
    from twin.cli import main as vrscroll

    out = tmp_path / "g.json"
    assert vrscroll(["tune", "--population", "8", "--generations", "2", "--threads", "2", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "spec defaults" in text and "tuned" in text and out.exists()
    assert vrscroll(["tune", "--tolerance", "150"]) == 2


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="issue 6 open: the gate refuses the tuned step (peak current 1.94 A > 1.6 A)")
def test_tuned_gains_on_the_emulator_settle_as_the_twin_predicts(tuned, emulator, tmp_path):
    from twin.hil import device_step
    from twin.response import step_metrics
    from twin.simulation import Twin, move_report

    spec, goal, result = tuned
    emu = emulator()
    targets = np.full(spec.n_hinges, goal.step)
    with Link(emu.port) as link:
        for k, g in enumerate(result.gains):
            link.set_gains(g, hinge=k)
        t, deg, start, res = device_step(link, spec, targets)
    assert res.ok, res.message
    twin = Twin(spec, result.gains)
    twin.reset(start)
    pred = move_report(spec, twin.move_to(targets, max_time=1.5, stop_when_settled=False))
    band = math.degrees(spec.settle_band * spec.rad_per_count)
    tgt = math.degrees(round(goal.step / spec.rad_per_count) * spec.rad_per_count)
    dev = [step_metrics(t, deg[:, k], tgt, band).settle_time for k in range(spec.n_hinges)]
    twin_s = [r["settle_time_s"] for r in pred]
    assert abs(np.mean(dev) - np.mean(twin_s)) <= 0.25 * np.mean(twin_s), (dev, twin_s)


def test_hil_interrupted_half_way_keeps_both_traces(emulator, tmp_path):
    emu = emulator()
    scen = tmp_path / "steps.toml"
    scen.write_text(SCENARIO.format(duration=3.0, t1=1.0, t2=2.0))
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "twin.cli", "hil", str(scen), "--port", emu.port, "--out", str(out)],
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
    assert 1.4 <= dev["time_s"][-1] < 2.9 and 1.4 <= tw["time_s"][-1] < 2.9
    assert abs(dev["time_s"][-1] - tw["time_s"][-1]) < 0.1  # the twin keeps up with the device
    assert len(dev["time_s"]) > 400 and dev["angle_deg"].shape[1] == 6
    meta = json.loads((out / "run.json").read_text())
    assert meta["status"] == "running" and len(meta["changes"]) >= 2
    from twin.spec import load_spec
    rows = compare(load_spec(), dev, tw,
                   [c["t_s"] for c in meta["changes"]])
    assert all(r["rmse_deg"] < 2.0 for r in rows)


def test_hil_command_writes_report(emulator, tmp_path, capsys):
    from twin.cli import main as vrscroll

    emu = emulator()
    scen = tmp_path / "s.toml"
    scen.write_text(SCENARIO.format(duration=1.2, t1=0.4, t2=0.8))
    out = tmp_path / "run"
    assert vrscroll(["hil", str(scen), "--port", emu.port, "--out", str(out)]) == 0
    report = (out / "report.md").read_text()
    assert "| hinge | RMSE deg" in report and "![hinge 5](hinge5.png)" in report
    assert all((out / f"hinge{k}.png").stat().st_size > 1000 for k in range(6))
    metrics = json.loads((out / "metrics.json").read_text())
    assert all(m["rmse_deg"] < 1.5 and abs(m["lag_s"]) <= 0.01 for m in metrics)


@pytest.mark.slow
@pytest.mark.xfail(reason="issue 6 open: friction recovery varies run to run (1.17-1.42 x for a true 1.6 x): stick-slip at low "
                   "duty", strict=False)
def test_calibration_recovers_the_emulators_plant(emulator, tmp_path):
    from twin.calibration import calibrate, trace_rmse, write_spec
    from twin.spec import load_spec

    spec = load_spec()
    truth = {"speed": 0.75, "friction": 1.6, "damping": 1.15}  # known to the test, not to the calibration
    emu = emulator("--speed-scale", str(truth["speed"]), "--friction-scale", str(truth["friction"]),
                   "--damping-scale", str(truth["damping"]), "--backlash-deg", "0")
    soft = PidGains.from_spec(spec).replace(kp=0.015, ki=0.05, kd=0.0003)  # slow moves: friction shows
    train, hold = tmp_path / "train", tmp_path / "hold"
    (tmp_path / "a.toml").write_text(SCENARIO.format(duration=2.0, t1=0.7, t2=1.4))
    (tmp_path / "b.toml").write_text(HOLDOUT)
    with Link(emu.port) as link:
        run_hil(link, spec, load_scenario(tmp_path / "a.toml", spec), train, gains=[soft] * 6)
        run_hil(link, spec, load_scenario(tmp_path / "b.toml", spec), hold, gains=[soft] * 6)
    res = calibrate([load_run(train)], spec)
    assert res.scales["no_load_speed"] == pytest.approx(truth["speed"], rel=0.2)
    assert res.scales["gear_friction"] == pytest.approx(truth["friction"], rel=0.2)
    assert res.scales["gear_damping"] == pytest.approx(truth["damping"], rel=0.2)
    before = trace_rmse(load_run(hold), spec, spec, transients_only=True)
    after = trace_rmse(load_run(hold), res.spec, spec, transients_only=True)
    assert np.sqrt(np.mean(after ** 2)) < 0.75 * np.sqrt(np.mean(before ** 2))
    write_spec(tmp_path / "cal.toml", res.spec, res.values, "calibrated from train")
    cal = load_spec(tmp_path / "cal.toml")
    assert cal.no_load_speed == pytest.approx(res.spec.no_load_speed, rel=1e-4)
    assert "calibrated from train" in (tmp_path / "cal.toml").read_text()
