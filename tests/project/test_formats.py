"""The file formats (twin/formats, docs/formats.md): each reader refuses bad files with the file, the
line or key and the reason; each writer's output reads back."""

import json
import math

import numpy as np
import pytest

from controllers.pid import PidGains
from twin.device.spec import SPEC_PATH, load_spec, spec_sources
from twin.formats.gains import read_gains, write_gains
from twin.formats.run import read_run, write_run_meta
from twin.formats.scenario import Scenario, read_scenario, write_scenario
from twin.device.spec_toml import write_spec_toml
from twin.formats.target import read_approximation, read_target, write_approximation
from twin.formats.trace import TWIN_COLUMNS, TraceWriter, read_trace
from twin.formats.trials import read_trials, write_trials
from twin.records.gains import Gains
from controllers.pid import GAIN_BOUNDS

SPEC = load_spec()
N = SPEC.n_hinges


def random_gains(rng, n=N):
    """Gains drawn anywhere inside the firmware's bounds."""
    def one():
        return PidGains(**{f: int(rng.integers(lo, hi + 1)) if f == "hold_band" else float(rng.uniform(lo, hi))
                           for f, (lo, hi) in GAIN_BOUNDS.items()})

    return [one() for _ in range(n)]


# ---- gains file ------------------------------------------------------------------------------

def test_gains_round_trip_anywhere_in_the_bounds(tmp_path):
    rng = np.random.default_rng(7)
    for i in range(5):
        gains = random_gains(rng)
        write_gains(tmp_path / f"g{i}.json", Gains(gains, {"seed": 7}))
        assert read_gains(tmp_path / f"g{i}.json", N) == Gains(gains, {"seed": 7})


def _gains_doc():
    return json.loads(json.dumps({"format": "vrscroll-gains/1", "hinges": [
        {"hinge": k, "kp": 0.04, "ki": 0.02, "kd": 0.001, "derivative_cutoff_hz": 50.0, "integral_limit": 0.3,
         "deadband_duty": 0.03, "hold_band_counts": 2} for k in range(N)]}))


@pytest.mark.parametrize("change, message", [
    (lambda d: d["hinges"][2].update(kp=1000), r"hinges?.*2.*kp = 1000 is outside the bounds the firmware takes \[0, 1\]"),
    (lambda d: d["hinges"][4].pop("ki"), r"hinges\[4\]: missing key 'ki'"),
    (lambda d: d["hinges"][1].update(kd="fast"), r"hinges\[1\]: kd: expected a number, got 'fast'"),
    (lambda d: d["hinges"][0].update(kp=float("nan")), r"hinges\[0\]: kp: nan is not a finite number"),
    (lambda d: d["hinges"][3].update(hold_band_counts=2.5), r"hinges\[3\]: hold_band_counts = 2.5 is not a whole"),
    (lambda d: d["hinges"][3].update(kp_gain=1), r"hinges\[3\]: unknown key 'kp_gain'"),
    (lambda d: d.update(hinge=[]), r"unknown key 'hinge'"),
    (lambda d: d["hinges"].pop(), r"gains for 5 hinges, the device has 6"),
    (lambda d: d["hinges"][5].update(hinge=7), r"hinge indices \[0, 1, 2, 3, 4, 7\]"),
    (lambda d: d.update(format="gains"), r"not a vrscroll-gains/1 gains file"),
])
def test_bad_gains_files_are_refused_with_the_key(tmp_path, change, message):
    doc = _gains_doc()
    change(doc)
    path = tmp_path / "gains.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=message) as err:
        read_gains(path, N)
    assert str(path) in str(err.value)


def test_gains_outside_the_bounds_are_not_written(tmp_path):
    gains = [PidGains.from_spec(SPEC)] * N
    gains[5] = gains[5].replace(derivative_cutoff=900.0)  # above the 1 kHz loop's Nyquist rate
    with pytest.raises(ValueError, match="hinge 5: derivative_cutoff_hz = 900"):
        write_gains(tmp_path / "g.json", Gains(gains))
    assert not (tmp_path / "g.json").exists()


# ---- trace CSV -------------------------------------------------------------------------------

def _trace(path, rows=5, extra=()):
    rng = np.random.default_rng(3)
    with TraceWriter(path, N, extra) as w:
        for i in range(rows):
            cols = {"target_deg": rng.uniform(-100, 100, N), "angle_deg": rng.uniform(-100, 100, N),
                    "counts": rng.integers(-300, 300, N), "duty": rng.uniform(-1, 1, N),
                    "current_A": rng.uniform(-2, 2, N)}
            cols.update({c: rng.uniform(-1, 1, N) for c in extra})
            w.write(i * 0.002, **cols)
    return path


def _cell(line, i, value):
    cells = line.split(",")
    cells[i] = value
    return ",".join(cells)


def test_trace_round_trip_with_the_twins_columns(tmp_path):
    path = _trace(tmp_path / "t.csv", extra=TWIN_COLUMNS)
    t = read_trace(path, N, SPEC.hinge_limit)
    assert all(getattr(t, f) is not None for f in ("true_angle", "target_counts", "torque"))
    assert t.angle.shape == (5, N) and t.time[-1] == pytest.approx(0.008)


def test_a_cut_off_last_line_is_dropped_and_a_bad_middle_line_refused(tmp_path):
    path = _trace(tmp_path / "t.csv")
    text = path.read_text()
    path.write_text(text[:-20])  # killed while writing the last row
    assert len(read_trace(path, N).time) == 4
    lines = text.splitlines()
    lines[2] = _cell(lines[2], 3, "oops")
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"t.csv:3: h0_counts: expected a number, got 'oops'"):
        read_trace(path, N)


@pytest.mark.parametrize("edit, message", [
    (lambda h, r: (h, _cell(r, 1, "nan")), r":2: h0_target_deg: 'nan' is not a finite number"),
    (lambda h, r: (h, _cell(r, 1, "500")), r":2: h0_target_deg 500 is outside the hinge range"),
    (lambda h, r: (h.replace("h0_duty", "h0_dooty"), r), r":1: unknown column 'h0_dooty'"),
    (lambda h, r: (h.replace("time_s", "t"), r), r":1: the first column must be time_s"),
])
def test_bad_trace_files_are_refused_with_the_line(tmp_path, edit, message):
    path = _trace(tmp_path / "t.csv", rows=3)
    header, first, *rest = path.read_text().splitlines()
    header, first = edit(header, first)
    path.write_text("\n".join([header, first, *rest]) + "\n")
    with pytest.raises(ValueError, match=message):
        read_trace(path, N, SPEC.hinge_limit)


def test_a_trace_of_another_hinge_count_is_refused(tmp_path):
    with TraceWriter(tmp_path / "t.csv", 4) as w:
        w.write(0.0, target_deg=[0] * 4, angle_deg=[0] * 4, counts=[0] * 4, duty=[0] * 4, current_A=[0] * 4)
    with pytest.raises(ValueError, match="a trace of 4 hinges, the device has 6"):
        read_trace(tmp_path / "t.csv", N)


# ---- spec TOML -------------------------------------------------------------------------------

def test_spec_writer_keeps_comments_and_other_sources(tmp_path):
    out = tmp_path / "cal.toml"
    write_spec_toml(out, SPEC_PATH, {"no_load_speed": SPEC.no_load_speed * 0.8, "hinge_limit": math.radians(100),
                                     "counts_per_motor_rev": 24}, "calibrated (test)", header="test header")
    text = out.read_text()
    assert text.startswith("# test header\n")
    original = [ln for ln in SPEC_PATH.read_text().splitlines() if ln.startswith("#")]
    assert all(ln in text for ln in original)  # every comment kept
    spec = load_spec(out)
    assert spec.no_load_speed == pytest.approx(SPEC.no_load_speed * 0.8, rel=1e-5)
    assert spec.hinge_limit == pytest.approx(math.radians(100)) and spec.counts_per_motor_rev == 24
    sources = spec_sources(out)
    assert sources["no_load_speed"] == "calibrated (test)" and sources["mass_total"] == spec_sources()["mass_total"]
    assert spec.replace(no_load_speed=SPEC.no_load_speed, hinge_limit=SPEC.hinge_limit,
                        counts_per_motor_rev=SPEC.counts_per_motor_rev) == SPEC


@pytest.mark.parametrize("old, new, message", [
    ("value = 3.75,", 'value = "low",', r"\[motor\] resistance: value: expected a number, got 'low'"),
    ("value = 3.75,", "value = nan,", r"\[motor\] resistance: value: nan is not a finite number"),
    ('unit = "ohm",', 'unit = "ohm", note = "x",', r"\[motor\] resistance: unknown key 'note'"),
    ('unit = "ohm",', "", r"\[motor\] resistance: missing key 'unit'"),
])
def test_bad_spec_files_are_refused_with_the_key(tmp_path, old, new, message):
    text = SPEC_PATH.read_text()
    line = next(ln for ln in text.splitlines() if ln.startswith("resistance"))
    path = tmp_path / "spec.toml"
    path.write_text(text.replace(line, line.replace(old, new)))
    with pytest.raises(ValueError, match=message):
        load_spec(path)


# ---- target and approximation JSON -----------------------------------------------------------

APPROX = {"target": "cube", "variant": "full", "root_position_mm": [0, 0, 30], "root_quat_wxyz": [1, 0, 0, 0],
          "angles_deg": [10, 20, 0, -5, 30, 1], "widths_mm": [26.9] * 7, "msd_mm": 1.0, "hd_mm": 2.0,
          "time_ms": 3.0}


def test_approximation_round_trip(tmp_path):
    write_approximation(tmp_path / "a.json", APPROX)
    a = read_approximation(tmp_path / "a.json", SPEC)
    assert np.degrees(a.angles) == pytest.approx(APPROX["angles_deg"])
    assert a.root_pose[2, 3] == pytest.approx(0.03) and a.widths == pytest.approx([0.0269] * 7)
    assert read_target(tmp_path / "a.json", SPEC) == pytest.approx(a.angles)


@pytest.mark.parametrize("change, message", [
    (dict(angles_deg=[500, 0, 0, 0, 0, 0]), r"angles_deg: hinge 0 at 500 deg is outside the hinge range \+-112.5"),
    (dict(angles_deg=[0, 0, 0, 0, 0]), "expected 6 hinge angles in degrees, got 5"),
    (dict(angles_deg=[0, 0, "flat", 0, 0, 0]), r"angles_deg\[2\]: expected a number, got 'flat'"),
    (dict(angles_deg=[0, 0, 0, float("inf"), 0, 0]), r"angles_deg\[3\]: inf is not a finite number"),
    (dict(angle_deg=[0] * 6), "unknown key 'angle_deg'"),
    (dict(widths_mm=[26.9] * 6), r"widths_mm: expected 7 numbers, got 6"),
    (dict(root_quat_wxyz=[0, 0, 0, 0]), "root_quat_wxyz is not a unit quaternion"),
    (dict(root_quat_wxyz=[1e200, 1e200, 1e200, 1e200]), "root_quat_wxyz is not a unit quaternion"),
    (dict(root_quat_wxyz=[2, 0, 0, 0]), "root_quat_wxyz is not a unit quaternion"),
])
def test_bad_approximations_are_refused_with_the_key(tmp_path, change, message):
    path = tmp_path / "a.json"
    path.write_text(json.dumps({**APPROX, **change}))
    with pytest.raises(ValueError, match=message):
        read_approximation(path, SPEC)


def test_bad_target_files_are_refused(tmp_path):
    path = tmp_path / "t.json"
    path.write_text(json.dumps({"hinges_deg": [0] * 6}))
    with pytest.raises(ValueError, match="unknown key 'hinges_deg'"):
        read_target(path, SPEC)
    path.write_text("[0, 0, 0]")
    with pytest.raises(ValueError, match="expected a JSON object"):
        read_target(path, SPEC)
    path.write_text("{")
    with pytest.raises(ValueError, match="not JSON"):
        read_target(path, SPEC)


# ---- scenario --------------------------------------------------------------------------------

GOOD = """name = "s"
duration_s = 2.0
[[step]]
t_s = 0.0
angles_deg = [10, 10, 10, 10, 10, 10]
[[step]]
t_s = 1.0
file = "a.json"
"""


def test_scenario_round_trip(tmp_path):
    (tmp_path / "a.json").write_text(json.dumps(APPROX))
    (tmp_path / "s.toml").write_text(GOOD)
    s = read_scenario(tmp_path / "s.toml", SPEC)
    assert s.times == [0.0, 1.0] and np.degrees(s.targets[1]) == pytest.approx(APPROX["angles_deg"])
    write_scenario(tmp_path / "again.toml", s)
    again = read_scenario(tmp_path / "again.toml", SPEC)
    assert again.times == s.times and again.duration == s.duration and again.name == s.name
    assert np.allclose(again.targets, s.targets) and np.allclose(again.start, s.start)
    assert isinstance(again, Scenario)


@pytest.mark.parametrize("text, message", [
    ('name = "s"\nstep = 5\n', r"s.toml: step: expected a list of \[\[step\]\] tables, got 5"),
    (GOOD.replace("t_s = 1.0\n", "t_s = 1.0\nstep = 5\n"), r"step 1: unknown key 'step'"),
    (GOOD.replace("duration_s", "durations"), r"unknown key 'durations'"),
    (GOOD.replace("[10, 10, 10, 10, 10, 10]", "[10, 10, 500, 10, 10, 10]"), r"step 0: angles_deg: hinge 2 at 500"),
    (GOOD.replace("[10, 10, 10, 10, 10, 10]", "[10, 10, 10]"), r"step 0: angles_deg: expected 6 hinge angles"),
    (GOOD.replace("[10, 10, 10, 10, 10, 10]", '[10, 10, "x", 10, 10, 10]'), r"step 0: angles_deg\[2\]: expected a number"),
    (GOOD.replace("t_s = 1.0", "t_s = nan"), r"step 1: t_s: nan is not a finite number"),
    (GOOD.replace("t_s = 1.0", "t_s = 0.0"), r"step 1: t_s 0.0 is not after"),
    (GOOD.replace('file = "a.json"', 'file = "missing.json"'), r"missing.json"),
])
def test_bad_scenarios_are_refused_with_the_key(tmp_path, text, message):
    (tmp_path / "a.json").write_text(json.dumps(APPROX))
    (tmp_path / "s.toml").write_text(text)
    with pytest.raises((ValueError, OSError), match=message):
        read_scenario(tmp_path / "s.toml", SPEC)


# ---- run folder ------------------------------------------------------------------------------

def _run(folder, status="complete"):
    folder.mkdir()
    write_run_meta(folder, {"scenario": "s", "start_counts": [0] * N, "start_target_counts": [0] * N,
                            "before": {"state": "IDLE", "counts": [0] * N, "target_counts": [0] * N},
                            "changes": [{"t_s": 0.0, "angles_deg": [10] * N}], "status": status})
    _trace(folder / "device.csv", rows=20)
    write_gains(folder / "gains.json", Gains([PidGains.from_spec(SPEC)] * N))
    return folder


def test_a_run_that_did_not_complete_is_refused_unless_asked(tmp_path):
    assert read_run(_run(tmp_path / "done"), SPEC).status == "complete"
    killed = _run(tmp_path / "killed", status="running")
    with pytest.raises(ValueError, match=r"killed: the run did not complete \(status 'running'"):
        read_run(killed, SPEC)
    assert len(read_run(killed, SPEC, incomplete=True).device.time) == 20


def test_bad_run_folders_are_refused(tmp_path):
    run = _run(tmp_path / "r")
    meta = json.loads((run / "run.json").read_text())
    meta["changes"][0]["angles_deg"][4] = 200
    (run / "run.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"changes\[0\]: angles_deg: hinge 4 at 200 deg is outside"):
        read_run(run, SPEC)
    meta["changes"][0]["angles_deg"][4] = 0
    meta["start_counts"] = [0] * 5
    (run / "run.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="start_counts: expected 6 whole encoder counts"):
        read_run(run, SPEC)
    meta["start_counts"] = [0] * 6
    for bad in ([0.1] * 5, [0.1] * 5 + [1.5], [0.1] * 5 + [None], [0.1] * 5 + [True]):
        meta["start_integral_duty"] = bad
        (run / "run.json").write_text(json.dumps(meta))
        with pytest.raises(ValueError, match="start_integral_duty: expected 6 duties, numbers from -1 to 1"):
            read_run(run, SPEC)
    meta["start_integral_duty"] = [0.25, -0.5, 0, 1, -1, 0.125]
    (run / "run.json").write_text(json.dumps(meta))
    assert read_run(run, SPEC).start.integral.tolist() == meta["start_integral_duty"]
    meta["changes"] = []
    (run / "run.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"r/run.json: changes: expected a list .* at least the first target's"):
        read_run(run, SPEC)
    with pytest.raises(ValueError, match="no run.json"):
        read_run(tmp_path, SPEC)
    meta["changes"] = [{"t_s": 0.0, "angles_deg": [10] * N}]
    for key, bad in (("scenario", {}), ("status", 5)):  # a traceback in compare before
        (run / "run.json").write_text(json.dumps({**meta, key: bad}))
        with pytest.raises(ValueError, match=f"run.json: {key}: expected a string"):
            read_run(run, SPEC)


def test_a_run_longer_than_any_run_is_refused_before_it_is_replayed(tmp_path, capsys):
    """A device.csv whose last time was 1e9 s asked calibration's replay for 43.7 TiB (issue 40 attack 7)."""
    from twin.cli import main
    from twin.formats.run import MAX_RUN_S

    run = _run(tmp_path / "r")
    lines = (run / "device.csv").read_text().splitlines()
    (run / "device.csv").write_text("\n".join(lines + [_cell(lines[-1], 0, "1e9")]) + "\n")
    assert main(["calibrate", str(run), "--out", str(tmp_path / "spec.toml")]) == 2
    err = capsys.readouterr().err
    assert f"device.csv: its last time 1e+09 s is past the longest a run spans, {MAX_RUN_S:g} s" in err
    assert len(err.strip().splitlines()) == 1
    (run / "device.csv").write_text("\n".join(lines + [_cell(lines[-1], 0, f"{MAX_RUN_S}")]) + "\n")
    assert read_run(run, SPEC).device.time[-1] == MAX_RUN_S  # the bound itself is a run
    meta = json.loads((run / "run.json").read_text())
    meta["changes"].append({"t_s": 1e9, "angles_deg": [0] * N})
    (run / "run.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"changes\[1\]: t_s 1e\+09 s is past the longest a run spans"):
        read_run(run, SPEC)


def test_compare_refuses_a_run_without_device_frames_or_twin_in_one_line(tmp_path, capsys):
    from twin.cli import main

    full, bare = _run(tmp_path / "full"), _run(tmp_path / "bare")
    _trace(full / "twin.csv", rows=20)
    _trace(bare / "device.csv", rows=20)
    for trace, rows, says in (("twin.csv", None, "no twin.csv"), ("twin.csv", 0, "no twin rows"),
                              ("device.csv", 0, "no device frames")):
        if rows is not None:
            _trace(bare / trace, rows=rows)
        rc = main(["compare", str(full), str(bare), "--png", str(tmp_path / "c.png")])
        err = capsys.readouterr().err
        assert rc == 2 and f"bare: {says}" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


# ---- trials CSV ------------------------------------------------------------------------------

def test_more_surfaces_than_a_fit_and_a_panel_each_are_refused(tmp_path, capsys):
    """5,000 surfaces once asked psychometric for a figure 3 million pixels wide (issue 40 attack 7)."""
    from twin.cli import main
    from twin.formats.trials import MAX_SURFACES

    def trials(n):
        rows = [{"participant": "p", "surface": f"s{k}", "condition": c, "natural": c < 2, "confidence": 4}
                for k in range(n) for c in (0.0, 1.0, 2.0, 4.0)]
        write_trials(tmp_path / f"{n}.csv", rows, "deg")
        return tmp_path / f"{n}.csv"

    assert len(set(read_trials(trials(MAX_SURFACES)).surface)) == MAX_SURFACES
    path = trials(5000)
    with pytest.raises(ValueError, match=f"{path}:{2 + 4 * MAX_SURFACES}: surface 's{MAX_SURFACES}' is the "
                                         f"{MAX_SURFACES + 1}th; a trials file holds at most {MAX_SURFACES}"):
        read_trials(path)
    assert main(["psychometric", str(path)]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_trials_round_trip(tmp_path):
    rows = [{"participant": f"p{i % 3}", "condition": c, "natural": i % 2 == 0, "confidence": 1 + i % 5}
            for i, c in enumerate([0.5, 1.0, 2.0, 4.0] * 3)]
    write_trials(tmp_path / "t.csv", rows, "mm")
    t = read_trials(tmp_path / "t.csv")
    assert t.unit == "mm" and t.condition.tolist() == [r["condition"] for r in rows]
    assert t.natural.tolist() == [r["natural"] for r in rows]
    (tmp_path / "bad.csv").write_text("condition_mm,natural,confidence\n1,yes,3\n2,no,3\ninf,yes,2\n")
    with pytest.raises(ValueError, match=r"bad.csv:4: condition 'inf' is not a number"):
        read_trials(tmp_path / "bad.csv")


@pytest.mark.parametrize("line, words", [
    ('name = "../../../x"', "not a plain name"), ('name = "/etc/evil"', "not a plain name"),
    ("duration_s = 1e9", "at most 600 s")])
def test_a_scenario_cannot_place_its_run_anywhere_or_last_forever(tmp_path, spec, line, words):
    path = tmp_path / "s.toml"
    path.write_text(line + '\n[[step]]\nt_s = 0.0\nangles_deg = [1, 1, 1, 1, 1, 1]\n')
    with pytest.raises(ValueError, match=words):
        read_scenario(path, spec)


def test_a_scenario_named_by_an_odd_file_name_gets_a_plain_one(tmp_path, spec):
    path = tmp_path / "my steps (v2).toml"
    path.write_text('[[step]]\nt_s = 0.0\nangles_deg = [1, 1, 1, 1, 1, 1]\n')
    assert read_scenario(path, spec).name == "my-steps-v2"
