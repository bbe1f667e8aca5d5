"""Device profiles: where they live, selection and the remembered default, every command naming the one it
used, a missing or damaged profile as a one-line error."""

import json
import re

import numpy as np
import pytest

from controllers.pid import PidGains
from twin.cli import main as vrscroll
from twin.device.profile import profiles_dir
from twin.formats.gains import write_gains
from twin.device.variation import corners, scaled
from twin.live.morph import TwinMorpher
from twin.formats.profile import read_profile, select_profile, spec_defaults, updated, write_profile
from twin.records.calibration import Calibration, Estimate
from twin.records.gains import Gains
from twin.records.profile import Holding
from twin.records.ranges import Ranges
from twin.tuning.tuner import RobustEvaluator, TuneGoal

ONE_STEP = """name = "one"
duration_s = 0.6
[[step]]
t_s = 0.0
angles_deg = [20, 10, 5, 5, 10, 20]
"""


def write_profile_values(name, values, source, by="vrscroll calibrate", **parts):
    """Make or update the profile called name as the commands do: its record (the spec's defaults for a new
    one) with `values` (field -> SI) from `source` and `parts` replaced, written whole."""
    folder = profiles_dir() / name
    base = read_profile(folder) if folder.is_dir() else spec_defaults()
    return write_profile(updated(base, values, source, name=name, **parts), by=by)


def _run(capsys, *args):
    rc = vrscroll(list(args))
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_profiles_live_in_the_folder_the_environment_names(device_profiles):
    assert profiles_dir() == device_profiles
    assert select_profile().label == "spec defaults"


def test_device_selects_a_profile_and_it_is_remembered(capsys, spec):
    rc, out, _ = _run(capsys, "device", "create", "bench")
    assert rc == 0 and "bench" in out
    assert "selected: spec defaults" in _run(capsys, "device", "list")[1]
    # a profile whose device is slower: the twin of that profile settles later
    write_profile_values("bench", {"no_load_speed": spec.no_load_speed * 0.7}, "test: slower motor")
    rc, out, _ = _run(capsys, "simulate", "30", "30", "30", "30", "30", "30", "--json", "-")
    default = json.loads(out)
    assert default["device_profile"] == "spec defaults"
    rc, out, _ = _run(capsys, "simulate", "30", "30", "30", "30", "30", "30", "--json", "-", "--device", "bench")
    bench = json.loads(out)
    assert rc == 0 and bench["device_profile"] == "bench"
    assert bench["hinges"][0]["settle_time_s"] > default["hinges"][0]["settle_time_s"]
    # remembered: the next command without --device uses it too
    rc, out, _ = _run(capsys, "simulate", "30", "30", "30", "30", "30", "30")
    assert rc == 0 and out.startswith("device profile: bench (")
    assert "* bench" in _run(capsys, "device", "list")[1]
    assert _run(capsys, "device", "select", "none")[0] == 0
    assert _run(capsys, "simulate", "30", "30", "30", "30", "30", "30")[1].startswith("device profile: spec defaults")
    assert "test: slower motor" in _run(capsys, "device", "show", "bench")[1]


def test_a_profiles_gains_are_the_twins(capsys, spec, device_profiles):
    _run(capsys, "device", "create", "soft")
    soft = PidGains.from_spec(spec).replace(kp=0.003, ki=0.0, kd=0.0)
    write_gains(device_profiles / "soft" / "gains.json", Gains([soft] * spec.n_hinges))
    assert read_profile(device_profiles / "soft").gains == [soft] * spec.n_hinges
    rc, out, _ = _run(capsys, "simulate", "30", "30", "30", "30", "30", "30", "--json", "-", "--device", "soft",
                      "--max-time-s", "1.0")
    assert rc in (0, 1)  # 1: the gate found the soft gains too slow to settle (the report is written all the same)
    assert (rc == 0) == json.loads(out)["gate"]["passed"]
    soft_row = json.loads(out)["hinges"][0]
    _run(capsys, "device", "select", "none")
    default_row = json.loads(_run(capsys, "simulate", "30", "30", "30", "30", "30", "30", "--json", "-",
                                  "--max-time-s", "1.0")[1])["hinges"][0]
    # no integral, a weak kp, no derivative: the soft profile's hinge takes longer (or never settles)
    assert not soft_row["settle_time_s"] <= default_row["settle_time_s"] + 0.02, (soft_row, default_row)


def _hinge_estimates(spec, slow_hinge: int, speed_scale: float) -> list[dict]:
    """A per-hinge calibration's hinges: every hinge at the shared speed but slow_hinge, x scale."""
    rows = []
    for k in range(spec.n_hinges):
        v = spec.no_load_speed * (speed_scale if k == slow_hinge else 1.0)
        rows.append({"no_load_speed": Estimate(v, spec.no_load_speed, v * 0.95, v * 1.05, True, "test")})
    return rows


def test_a_profile_written_before_the_spec_gained_an_entry_takes_the_specs(capsys, spec, device_profiles):
    """A profile's spec.toml from before the spec had cogging (this round's entries) still loads, the new
    entries the spec's; a calibration into it keeps its own values and reads back."""
    _run(capsys, "device", "create", "old")
    path = device_profiles / "old" / "spec.toml"
    text = path.read_text()
    old = "\n".join(line for line in text.splitlines() if not line.startswith("cogging"))
    assert old != text.rstrip("\n")
    path.write_text(old.replace("value = 0.004,", "value = 0.005,", 1) + "\n")  # its own friction
    rc, out, err = _run(capsys, "device", "show", "old")
    assert rc == 0, err
    profile = read_profile(device_profiles / "old")
    assert profile.spec.cogging == spec.cogging and profile.spec.gear_friction == pytest.approx(0.005)
    write_profile_values("old", {"no_load_speed": spec.no_load_speed * 0.9}, "test")
    again = read_profile(device_profiles / "old")
    assert again.spec.gear_friction == pytest.approx(0.005) and again.spec.cogging_phase == spec.cogging_phase


def test_a_profile_calibrated_per_hinge_gives_each_hinge_its_own(capsys, spec, device_profiles):
    """The twin of a profile with per-hinge values (calibrate --per-hinge) moves each hinge with its own motor:
    the hinge whose motor is slower settles later, the others as on the spec's twin; `device show` lists them."""
    calibration = Calibration(["test"], {}, _hinge_estimates(spec, 4, 0.6))
    write_profile_values("uneven", {}, "test", calibration=calibration)
    hinges = read_profile(device_profiles / "uneven").hinges
    assert [h.no_load_speed / spec.no_load_speed for h in hinges] == pytest.approx([1, 1, 1, 1, 0.6, 1])
    targets = ["30"] * spec.n_hinges
    uneven = json.loads(_run(capsys, "simulate", *targets, "--json", "-", "--device", "uneven")[1])["hinges"]
    _run(capsys, "device", "select", "none")
    default = json.loads(_run(capsys, "simulate", *targets, "--json", "-")[1])["hinges"]
    assert uneven[4]["settle_time_s"] > default[4]["settle_time_s"] + 0.01, (uneven[4], default[4])
    # hinge 1 shares no flap with hinge 4's (the root flap between hinges 2 and 3 is held): unchanged
    assert uneven[1]["settle_time_s"] == pytest.approx(default[1]["settle_time_s"], abs=2e-3)
    assert "hinge 4's own, x the shared value (95 % interval): no_load_speed x0.600" in \
        _run(capsys, "device", "show", "uneven")[1]


def test_tuning_a_profile_calibrated_per_hinge_scores_each_hinge_on_its_own_plant(capsys, spec, device_profiles):
    """tune's plants give each hinge its own values at its own intervals' corners: hinge 4's motor at x0.6
    (x0.57 .. x0.63) settles later on every plant than on the shared twin's, hinge 1 as there; `vrscroll tune`
    on such a profile says it tunes each hinge about its own values."""
    calibration = Calibration(["test"], {}, _hinge_estimates(spec, 4, 0.6))
    write_profile_values("uneven", {}, "test", calibration=calibration)
    profile = read_profile(device_profiles / "uneven")
    shared_ranges = {"no_load_speed": (spec.no_load_speed * 0.9, spec.no_load_speed * 1.1)}
    ranges = profile.ranges(Ranges(shared_ranges, "test"))
    uneven = TuneGoal(ranges=ranges, hinges=tuple(profile.hinges))
    plants = corners(spec, ranges, uneven.hinges)
    assert [p.hinges[4].no_load_speed / spec.no_load_speed for p in plants] == pytest.approx([0.6, 0.57, 0.63])
    assert [p.hinges[1].no_load_speed / spec.no_load_speed for p in plants] == pytest.approx([1.0, 0.95, 1.05])
    assert [p.spec.no_load_speed / spec.no_load_speed for p in plants] == pytest.approx([1.0, 0.9, 1.1])
    gains = PidGains.from_spec(spec)
    kp, ki, kd = (np.full((1, spec.n_hinges), getattr(gains, k)) for k in ("kp", "ki", "kd"))
    own, _ = RobustEvaluator(spec, uneven, 1).costs(kp, ki, kd)  # (1, plant, hinge), s
    shared, _ = RobustEvaluator(spec, TuneGoal(ranges=Ranges(shared_ranges, "test")), 1).costs(kp, ki, kd)
    assert np.all(own[0, :, 4] > shared[0, :, 4] + 0.01), (own[0, :, 4], shared[0, :, 4])
    assert own[0, :, 1] == pytest.approx(shared[0, :, 1], abs=5e-3)
    out = _run(capsys, "tune", "--device", "uneven", "--population", "4", "--generations", "1", "--json", "t.json")[1]
    assert "each hinge about its own calibrated values" in out
    speeds = [row["no_load_speed"] for row in json.loads(open("t.json").read())["goal"]["hinge_ranges"]]
    assert speeds[4] == pytest.approx([spec.no_load_speed * 0.57, spec.no_load_speed * 0.63])


def test_serves_twin_moves_each_hinge_with_its_own_plant(spec):
    """`vrscroll serve` without a device gates and moves on the profile's twin, each hinge its own plant: hinge
    4's motor at x0.6 is behind the shared twin's 30 ms into the move, hinge 1 with it."""
    slow = [scaled(spec, {"no_load_speed": 0.6}) if k == 4 else spec for k in range(spec.n_hinges)]
    at = {}
    for name, hinges in (("shared", None), ("own", slow)):
        morpher = TwinMorpher(spec, hinges=hinges)
        morpher.open()
        morpher.on_move = lambda _, trace, name=name: at.__setitem__(name, np.degrees(trace.true_angle[30]))
        assert morpher.morph(np.radians([20.0] * spec.n_hinges), lambda event: None).status == "done"
    assert at["own"][4] < at["shared"][4] - 0.5, at
    assert at["own"][1] == pytest.approx(at["shared"][1], abs=0.05)


@pytest.mark.parametrize("damage, message", [
    (lambda rows: rows[:-1], "hinges: expected a list of 6 objects"),
    (lambda rows: rows[:2] + [{"hinge_limit": rows[2]["no_load_speed"]}] + rows[3:], "hinges[2]: hinge_limit: not a plant"),
    (lambda rows: rows[:1] + [{"no_load_speed": {**rows[1]["no_load_speed"], "value": -1.0}}] + rows[2:],
     "hinges[1]: no_load_speed: value -1 is not within"),
    (lambda rows: rows[:3] + [{"no_load_speed": {**rows[3]["no_load_speed"], "runs_low": 1.0}}] + rows[4:],
     "hinges[3]: no_load_speed: missing"),  # one end of the runs' interval without the other
    (lambda rows: rows[:3] + [{"no_load_speed": {**rows[3]["no_load_speed"], "runs_low": 1e3, "runs_high": 2e3}}]
     + rows[4:], "hinges[3]: no_load_speed: value"),
])
def test_a_damaged_per_hinge_calibration_is_named(capsys, spec, device_profiles, damage, message):
    _run(capsys, "device", "create", "bad")
    meta = device_profiles / "bad" / "profile.json"
    doc = json.loads(meta.read_text())
    rows = [{p: e.to_json() for p, e in row.items()} for row in _hinge_estimates(spec, 0, 0.9)]  # the file's form
    doc["calibration"] = {"runs": [], "parameters": {}, "hinges": damage(rows)}
    meta.write_text(json.dumps(doc))
    rc, out, err = _run(capsys, "simulate", "0", "0", "0", "0", "0", "0", "--device", "bad")
    assert rc == 2 and len(err.splitlines()) == 1 and message in err, err


@pytest.mark.parametrize("damage, message", [
    (None, "'nope' (given with --device) is not in"),
    ("profile.json", "profile.json: not JSON"),
    ("spec.toml", "spec.toml: [motor] gear_friction: value: expected a number"),
    ("gains.json", "gains.json: not a vrscroll-gains/1 gains file"),
    ("name", "profile.json: name 'other' is not the folder's, 'nope'"),
])
def test_a_missing_or_damaged_profile_is_a_one_line_error(capsys, device_profiles, damage, message):
    if damage:
        _run(capsys, "device", "create", "nope")
        folder = device_profiles / "nope"
        if damage == "profile.json":
            (folder / "profile.json").write_text("{not json")
        elif damage == "spec.toml":
            text = (folder / "spec.toml").read_text()
            (folder / "spec.toml").write_text(re.sub(r"(gear_friction\s*= \{ value = )[^,]*", r'\1"lots"', text))
        elif damage == "gains.json":
            (folder / "gains.json").write_text("{}")
        else:
            (folder / "profile.json").write_text(json.dumps({"format": "vrscroll-profile/1", "name": "other"}))
    for cmd in (["simulate", "0", "0", "0", "0", "0", "0"], ["tune", "--generations", "1"], ["device", "show"]):
        rc, out, err = _run(capsys, *cmd, "--device", "nope") if cmd[0] != "device" else _run(capsys, *cmd, "nope")
        assert rc == 2 and len(err.splitlines()) == 1 and message in err, err


def test_a_selected_profile_that_was_removed_is_named(capsys, device_profiles):
    _run(capsys, "device", "create", "gone")
    _run(capsys, "device", "select", "gone")
    (device_profiles / "gone" / "profile.json").unlink()
    (device_profiles / "gone" / "spec.toml").unlink()
    (device_profiles / "gone").rmdir()
    rc, _, err = _run(capsys, "simulate", "0", "0", "0", "0", "0", "0")
    assert rc == 2 and len(err.splitlines()) == 1
    assert f"'gone' (selected in {device_profiles / 'default'}) is not in" in err


def test_every_command_that_talks_to_the_device_names_its_profile(capsys, emulator, tmp_path, spec):
    _run(capsys, "device", "create", "emu")
    emu = emulator()
    (tmp_path / "s.toml").write_text(ONE_STEP)
    run = tmp_path / "run"
    commands = [
        ["status", "--serial", emu.port],
        ["mirror", "--angles", "10,10,10,10,10,10", "--serial", emu.port, "--log", str(tmp_path / "m.jsonl")],
        ["hil", str(tmp_path / "s.toml"), "--serial", emu.port, "--out", str(run)],
        ["scenario", str(tmp_path / "cal.toml")],
        ["tune", "--population", "6", "--generations", "1", "--threads", "2", "--serial", emu.port,
         "--log", str(tmp_path / "t.jsonl")],
    ]
    for i, cmd in enumerate(commands):
        rc, out, err = _run(capsys, *cmd, *(["--device", "emu"] if i == 0 else []))
        assert rc == 0, (cmd, err)
        assert out.startswith(f"device profile: emu ({profiles_dir() / 'emu'})"), (cmd, out[:200])
    assert json.loads((run / "run.json").read_text())["device_profile"] == "emu"
    assert "device profile emu" in (run / "report.md").read_text()
    # tune stored its gains in the profile, and the device holds them: status says so
    assert (profiles_dir() / "emu" / "gains.json").is_file()
    assert "gains    as emu's" in _run(capsys, "status", "--serial", emu.port)[1]
    assert "device settle s" in out and "twin settle s" in out


@pytest.mark.parametrize("key, value", [("hinge_limit", "170"), ("settle_band", "400"), ("n_flaps", "3")])
def test_a_profile_cannot_change_the_design_the_host_checks_against(capsys, key, value):
    """hinge_limit = 170 once let the gate pass a 150 deg target; settle_band = 400 reported "settled" 25 deg
    short; n_flaps = 3 crashed simulate and mirror. A profile holds plant parameters only."""
    _run(capsys, "device", "create", "edited")
    spec_file = profiles_dir() / "edited" / "spec.toml"
    text = spec_file.read_text()
    pattern = re.compile(rf"^({key}\s*=\s*\{{\s*value\s*=\s*)[^,]+", re.M)
    assert pattern.search(text), key
    spec_file.write_text(pattern.sub(rf"\g<1>{value}", text))
    rc, out, err = _run(capsys, "simulate", "10", "0", "0", "0", "0", "0", "--device", "edited")
    assert rc == 2 and key in err and "plant parameters" in err, err


def test_none_cannot_name_a_profile(capsys):
    rc, _, err = _run(capsys, "device", "create", "none")
    assert rc == 2 and "reserved" in err


def test_what_holding_measured_survives_a_later_calibration(spec, device_profiles):
    """profile.json's parts are each replaced by the command that writes them, the others kept: a calibration
    after `vrscroll holding` keeps the holding, and a damaged holding is refused naming it."""
    est = Estimate(0.3, 0.5, 0.2, 0.45, False, "test")
    holding = Holding("/dev/ttyACM0", 2, {"backdrive_efficiency": est})
    write_profile_values("kept", {"backdrive_efficiency": 0.3}, "test", by="vrscroll holding", holding=holding)
    calibration = Calibration(["run"], {"gear_friction": Estimate(spec.gear_friction, spec.gear_friction, 0.001, 0.01,
                                                                  False, "test")})
    write_profile_values("kept", {"gear_friction": spec.gear_friction}, "test", calibration=calibration)
    profile = read_profile(device_profiles / "kept")
    assert profile.holding == holding and profile.calibration == calibration
    assert profile.spec.backdrive_efficiency == 0.3
    meta = device_profiles / "kept" / "profile.json"
    doc = json.loads(meta.read_text())
    doc["holding"]["parameters"]["backdrive_efficiency"]["high"] = 0.1
    meta.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"holding: parameters: backdrive_efficiency: value 0.3 is not within"):
        read_profile(device_profiles / "kept")
