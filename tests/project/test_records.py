"""The record layer (twin.records, issue 39): the file formats read and write the records, not dicts of their
fields; a twin's trace and a device's are one record whose `angle` is the encoder's on both; the record layer
sits at the bottom of the contract, beside the device, and breaks it by reaching up or sideways."""

import importlib
import inspect
import json
import pkgutil
import re

import numpy as np
import pytest

import twin.formats
from controllers.pid import PidGains
from test_layers import copy_tree, lint_imports
from twin.device.spec import spec_sources
from twin.device.variation import corners, prior_ranges, tolerance_ranges
from twin.formats.gains import read_gains, write_gains
from twin.formats.move_report import move_rows
from twin.formats.profile import read_profile, spec_defaults, updated, write_profile
from twin.formats.target import approximation_json, read_approximation, write_approximation
from twin.formats.trace import TraceWriter, read_trace, write_trace
from twin.records.approximation import Approximation
from twin.records.calibration import Calibration, Estimate
from twin.records.gains import Gains
from twin.records.move_report import MoveReport
from twin.records.profile import Holding, Profile
from twin.records.ranges import Ranges
from twin.records.trace import Trace, joined
from twin.sim.response import move_report, move_settle_time
from twin.sim.twin import Twin

RECORDS = ("Approximation", "Trace", "MoveReport", "Calibration", "Estimate", "Profile", "Holding", "Gains", "Ranges",
           "PenSamples")
# functions of twin.formats that return a dict, each with why it stays one (issue 39's contract): a results log's
# lines are the rows of several programs (a design sweep's, Table 1's), each row the keys its program writes and an
# older row without the keys added since; one record would be the union of them all, every field optional.
# check_record checks each field a row holds (its range, its type) as the line is read.
NOT_YET = {
    "twin.formats.records.read_jsonl": "a results log's rows (sweep, Table 1), each checked (check_record)",
    "twin.formats.sweep.read_records": "the same rows of a sweep's log by key: the rows the sweep itself wrote",
}


def formats_functions():
    """(dotted name, function) for every public function and method defined in twin.formats."""
    for info in pkgutil.iter_modules(twin.formats.__path__):
        module = importlib.import_module(f"twin.formats.{info.name}")
        for name, obj in vars(module).items():
            if name.startswith("_") or getattr(obj, "__module__", None) != module.__name__:
                continue
            if inspect.isfunction(obj):
                yield f"{module.__name__}.{name}", obj
            elif inspect.isclass(obj):
                for attr, member in vars(obj).items():
                    fn = member.fget if isinstance(member, property) else member
                    if not attr.startswith("_") and inspect.isfunction(fn):
                        yield f"{module.__name__}.{name}.{attr}", fn


def test_no_function_of_formats_returns_a_dict_where_a_record_exists():
    """A function of twin.formats that returns a dict (or dicts) either writes a record's JSON form (it takes a
    record) or is listed in NOT_YET with the reason; every reader of a format with a record returns it."""
    returning_dicts = []
    for name, fn in formats_functions():
        sig = inspect.signature(fn)
        if not re.search(r"\bdict\b", str(sig.return_annotation)):
            continue
        takes_record = any(re.search(rf"\b({'|'.join(RECORDS)})\b", str(p.annotation)) for p in sig.parameters.values())
        if not takes_record:
            returning_dicts.append(name)
    assert sorted(returning_dicts) == sorted(NOT_YET), "return a record, or say in NOT_YET why not"


@pytest.fixture(scope="module")
def moved(spec):
    """A twin's real move (MuJoCo, the C firmware) with a backlash the encoder does not see: (twin, trace)."""
    twin = Twin(spec)
    return twin, twin.move_to(np.radians([40.0, -30.0, 0.0, 20.0, 60.0, -50.0]), max_time=0.4,
                              stop_when_settled=False)


def test_a_twins_trace_holds_the_encoders_angle_and_the_flaps_true_one(spec, moved, tmp_path):
    """angle is the encoder's (counts x rad per count) as a device's is; true_angle the flap's, which the
    encoder does not follow exactly (its floor, the backlash, the gears' give): they differ, by less than a
    degree. A trace CSV gives both back, and a device's CSV (no twin columns) no true angle."""
    _, trace = moved
    assert isinstance(trace, Trace)
    assert np.array_equal(trace.angle, trace.counts * spec.rad_per_count)
    apart = np.abs(trace.true_angle - trace.angle)  # the counter's floor, the backlash, the gears' give
    assert 0 < apart.max() < np.radians(1.0), np.degrees(apart.max())
    write_trace(tmp_path / "twin.csv", trace)
    back = read_trace(tmp_path / "twin.csv", spec.n_hinges, spec.hinge_limit)
    assert isinstance(back, Trace)
    assert np.degrees(back.angle) == pytest.approx(np.degrees(trace.angle), abs=1e-4)
    assert np.degrees(back.true_angle) == pytest.approx(np.degrees(trace.true_angle), abs=1e-4)
    assert np.array_equal(back.counts, trace.counts) and np.array_equal(back.target_counts, trace.target_counts)
    with TraceWriter(tmp_path / "device.csv", spec.n_hinges) as w:
        for i in range(3):
            w.write(i * 0.002, target_deg=np.degrees(trace.target[i]), angle_deg=np.degrees(trace.angle[i]),
                    counts=trace.counts[i], duty=trace.duty[i], current_A=trace.current[i])
    device = read_trace(tmp_path / "device.csv", spec.n_hinges)
    assert device.true_angle is None and device.torque is None
    both = joined([device, back.until(0.004)])  # a column one of them lacks is not made up
    assert both.true_angle is None and len(both.time) == 3 + len(back.until(0.004).time)


def test_a_move_report_is_a_record_and_its_rows_are_its_values_in_degrees(spec, moved):
    """move_report gives the record (SI); its rows (the commands' JSON) the same values, rounded, in deg; the
    move's settle time is the slowest hinge's, the one the gate's settle rule gives for all hinges at once."""
    _, trace = moved
    report = move_report(spec, trace)
    assert isinstance(report, MoveReport)
    assert report.slowest == pytest.approx(move_settle_time(spec, trace.time, trace.counts, trace.target_counts),
                                           abs=1e-12)
    rows = move_rows(report)
    assert [r["settle_time_s"] for r in rows] == pytest.approx(report.settle_time, abs=5e-5)
    assert [r["overshoot_deg"] for r in rows] == pytest.approx(np.degrees(report.overshoot), abs=5e-4)
    assert [r["final_deg"] for r in rows] == pytest.approx(np.degrees(trace.true_angle[-1]), abs=5e-4)


def test_an_approximation_file_reads_back_as_the_record(tmp_path, spec):
    angles = np.radians([10.0, -20.0, 30.0, 0.0, 5.0, -5.0])
    pose = np.eye(4)
    pose[:3, 3] = (0.01, -0.02, 0.2)
    a = Approximation(pose, angles, np.full(spec.n_flaps, spec.flap_pitch), 0.002, "full", msd=0.001, hd=0.003,
                      inside=0.25, depth=0.0005)
    write_approximation(tmp_path / "a.json", {"target": "cube", **approximation_json(a)})
    b = read_approximation(tmp_path / "a.json", spec)
    assert isinstance(b, Approximation) and b.target == "cube" and b.variant == "full"
    assert b.root_pose == pytest.approx(pose, abs=1e-6) and b.angles == pytest.approx(angles, abs=1e-5)
    assert (b.msd, b.hd, b.inside, b.depth, b.time) == pytest.approx((0.001, 0.003, 0.25, 0.0005, 0.002))


def test_a_profile_is_written_whole_and_reads_back_as_the_record(spec, device_profiles):
    """The record a command makes (`updated`: a fitted value and its source, a calibration with each hinge's own
    values, a holding, a mount) is what write_profile writes and read_profile gives back whole: the per-hinge
    plants made from its calibration, each value's source in spec.toml, what it did not change as the spec had
    it; a record written again unchanged leaves the files as they were."""
    speed = spec.no_load_speed
    hinges = [{"no_load_speed": Estimate(speed * x, speed, speed * x * 0.9, speed * x * 1.1, True, "test",
                                         runs_low=speed * x * 0.95, runs_high=speed * x * 1.05)}
              for x in (0.8, 0.9, 1.0, 1.1, 1.2, 1.3)]
    friction = Estimate(spec.gear_friction * 1.3, spec.gear_friction, spec.gear_friction, spec.gear_friction * 2,
                        False, "test")
    calibration = Calibration(["run-a"], {"gear_friction": friction}, hinges)
    holding = Holding("/dev/ttyX", 3, {"backdrive_efficiency": Estimate(0.4, 0.5, 0.3, 0.45, True, "test")})
    made = updated(spec_defaults(), {"gear_friction": friction.value}, "fitted (test)", name="made",
                   calibration=calibration, holding=holding, mount="flat")
    assert [h.no_load_speed / speed for h in made.hinges] == pytest.approx([0.8, 0.9, 1.0, 1.1, 1.2, 1.3])
    folder = write_profile(made)
    back = read_profile(folder)
    assert isinstance(back, Profile) and back.name == "made" and back.mount == "flat"
    assert back.calibration == calibration and back.holding == holding
    assert back.spec.gear_friction == pytest.approx(friction.value, rel=1e-6)
    assert back.spec.gear_stiction == spec.gear_stiction  # a value given is written; none moved with it
    assert back.sources["gear_friction"] == "fitted (test)"
    assert {f: s for f, s in back.sources.items() if f != "gear_friction"} == \
        {f: s for f, s in spec_sources().items() if f != "gear_friction"}
    assert [h.no_load_speed for h in back.hinges] == pytest.approx([h.no_load_speed for h in made.hinges], rel=1e-6)
    assert back.ranges() == made.ranges()
    files = {p.name: p.read_bytes() for p in folder.iterdir()}
    write_profile(back)
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == files


def test_a_gains_file_is_written_whole_and_reads_back_as_the_record(spec, tmp_path):
    """write_gains takes the Gains record (each hinge's gains and what they were made for) and read_gains gives the
    same record back, its meta included; a file whose meta is not an object is refused, naming it."""
    rng = np.random.default_rng(3)
    base = PidGains.from_spec(spec)
    gains = Gains([base.replace(kp=base.kp * rng.uniform(0.5, 2), kd=base.kd * rng.uniform(0.5, 2))
                   for _ in range(spec.n_hinges)], {"device_profile": "drawn", "goal": {"step_deg": 30.0}})
    write_gains(tmp_path / "g.json", gains)
    back = read_gains(tmp_path / "g.json", spec.n_hinges)
    assert isinstance(back, Gains) and back == gains
    doc = json.loads((tmp_path / "g.json").read_text())
    (tmp_path / "bad.json").write_text(json.dumps({**doc, "meta": [1]}))
    with pytest.raises(ValueError, match=r"bad.json: \"meta\" must be an object"):
        read_gains(tmp_path / "bad.json", spec.n_hinges)


def test_a_profiles_ranges_are_one_record_its_hinges_own_inside(spec):
    """A per-hinge calibration's intervals are one Ranges (the shared values' and each hinge's own, the twin's
    values that reproduce the runs); uncalibrated, the spread about the spec or the tuner's tolerance are Ranges
    too, and a calibration of each hinge's values only takes its shared ones from them; corners spans them: the
    nominal and 2^k corners, each hinge at its own intervals' ends."""
    speed = spec.no_load_speed
    own = [0.8, 1.0, 1.2, 0.9, 1.1, 1.05]
    hinges = [{"no_load_speed": Estimate(speed * x, speed, speed * x * 0.9, speed * x * 1.1, True, "test",
                                         runs_low=speed * x * 0.95, runs_high=speed * x * 1.05)} for x in own]
    shared = {"no_load_speed": Estimate(speed, speed, speed * 0.8, speed * 1.2, True, "test"),
              "gear_friction": Estimate(spec.gear_friction, spec.gear_friction, spec.gear_friction * 0.5,
                                        spec.gear_friction * 2, False, "test")}
    profile = updated(spec_defaults(), calibration=Calibration(["run"], shared, hinges))
    ranges = profile.ranges()
    assert isinstance(ranges, Ranges) and ranges.calibrated
    assert ranges.shared == {p: (e.low, e.high) for p, e in shared.items()}
    assert [r["no_load_speed"] for r in ranges.hinges] == [(speed * x * 0.95, speed * x * 1.05) for x in own]
    plants = corners(spec, ranges, profile.hinges)
    assert len(plants) == 1 + 2 ** 2
    for plant in plants[1:]:  # each hinge at an end of its own interval, never the shared one's
        for h, x in enumerate(own):
            assert plant.hinges[h].no_load_speed / speed == pytest.approx(x * 0.95) or \
                plant.hinges[h].no_load_speed / speed == pytest.approx(x * 1.05)
    assert updated(spec_defaults()).ranges() is None
    per_hinge_only = updated(spec_defaults(), calibration=Calibration(["run"], {}, hinges))
    spread = per_hinge_only.ranges(prior_ranges(spec))  # the shared values as uncalibrated, each hinge its own
    assert per_hinge_only.ranges() is None and not spread.calibrated
    assert spread.shared == prior_ranges(spec).shared and spread.hinges == ranges.hinges
    for uncalibrated in (prior_ranges(spec), tolerance_ranges(spec, 0.2)):
        assert isinstance(uncalibrated, Ranges) and not uncalibrated.calibrated and uncalibrated.hinges is None
        assert all(lo < getattr(spec, p) < hi for p, (lo, hi) in uncalibrated.shared.items())


def test_the_record_layer_reaches_neither_up_nor_sideways(tmp_path):
    """Records beside the device: a record importing the device (its sibling) or a format (above) breaks the
    contract, each named."""
    tree = copy_tree(tmp_path)
    for module, target in (("trace.py", "from twin.device import spec"), ("move_report.py", "from twin.formats import trace")):
        path = tree / "twin" / "records" / module
        path.write_text(path.read_text() + f"\n\ndef _reach():\n    {target}  # noqa: F401\n")
    r = lint_imports(tree)
    assert r.returncode != 0 and "BROKEN" in r.stdout, r.stdout
    assert "twin.records.trace -> twin.device.spec" in r.stdout, r.stdout
    assert "twin.records.move_report -> twin.formats.trace" in r.stdout, r.stdout
