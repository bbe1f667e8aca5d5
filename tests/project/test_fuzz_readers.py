"""Every file reader, fed what a careless or hostile user might give it: it returns, or refuses with a one-line
ValueError naming the file. Never another exception (a traceback for the user), never a hang.

Inputs are drawn by hypothesis: arbitrary bytes, and text shaped like each format (valid JSON / TOML / CSV
values of any type, any nesting, numbers huge, tiny, non-finite or written as strings)."""

import json
import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from twin.device.spec import SPEC_PATH, load_spec
from twin.evaluation.table1 import METHODS
from twin.formats.gains import read_gains
from twin.formats.pen import read_pen_samples
from twin.formats.profile import read_profile
from twin.checks import json_object
from twin.formats.run import check_run_json
from twin.formats.scenario import read_scenario
from twin.formats.sweep import read_sweep
from twin.formats.target import read_approximation, read_target
from twin.formats.trace import read_trace
from twin.formats.trials import read_trials
from twin.morphpatch.shapes import shape_names
from twin.records.gains import Gains

SPEC = load_spec()


def _profile(meta_path):
    """A device profile folder with the spec's spec.toml and the drawn profile.json."""
    (meta_path.parent / "spec.toml").write_bytes(SPEC_PATH.read_bytes())
    return read_profile(meta_path.parent)

FUZZ = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

READERS = {
    "target.json": lambda p: read_target(p, SPEC),
    "approx.json": lambda p: read_approximation(p, SPEC),
    "gains.json": lambda p: read_gains(p, SPEC.n_hinges),
    "scenario.toml": lambda p: read_scenario(p, SPEC),
    "scenario.json": lambda p: read_scenario(p, SPEC),
    "sweep.toml": lambda p: read_sweep(p, shape_names(), list(METHODS)),
    "spec.toml": load_spec,
    "trace.csv": lambda p: read_trace(p, SPEC.n_hinges, SPEC.hinge_limit),
    "pens.csv": read_pen_samples,
    "trials.csv": read_trials,
    "run.json": lambda p: check_run_json(json_object(p), p, SPEC),
    "profile.json": _profile,
}

numbers = st.one_of(st.integers(-10 ** 30, 10 ** 30), st.floats(allow_nan=True, allow_infinity=True),
                    st.sampled_from([1e308, -1e308, 1e-320, "12", "nan", True, None, 10 ** 400, -(10 ** 400)]))
json_values = st.recursive(st.one_of(numbers, st.text(max_size=8)),
                           lambda inner: st.one_of(st.lists(inner, max_size=8),
                                                   st.dictionaries(st.text(max_size=12), inner, max_size=6)),
                           max_leaves=30)
KEYS = ["angles_deg", "root_position_mm", "root_quat_wxyz", "widths_mm", "variant", "kp", "ki", "kd", "hinges",
        "name", "duration_s", "step", "t_s", "shapes", "starts", "design", "plants", "draws", "count", "value",
        "scenario", "status", "changes", "start_counts", "start_target_counts", "start_integral_duty", "format",
        "calibration"]
objects = st.dictionaries(st.sampled_from(KEYS), json_values, max_size=6)


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return repr(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if v != v else ("inf" if v > 0 else "-inf"))
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v if x is not None) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {_toml_value(x)}" for k, x in v.items() if x is not None) + "}"
    return json.dumps(str(v))


def _refuses_or_reads(reader, path):
    try:
        reader(path)
    except ValueError as exc:
        assert str(path) in str(exc) or path.name in str(exc), exc


@pytest.mark.parametrize("name", READERS)
@FUZZ
@given(data=st.binary(max_size=300))
def test_any_bytes(tmp_path, name, data):
    path = tmp_path / name
    path.write_bytes(data)
    _refuses_or_reads(READERS[name], path)


@pytest.mark.parametrize("name", [n for n in READERS if n.endswith((".json", ".toml"))])
@FUZZ
@given(doc=objects)
def test_any_document_of_the_format(tmp_path, name, doc):
    path = tmp_path / name
    if name.endswith(".json"):
        path.write_text(json.dumps(doc, allow_nan=True))
    else:
        path.write_text("\n".join(f"{k} = {_toml_value(v)}" for k, v in doc.items() if v is not None) + "\n")
    _refuses_or_reads(READERS[name], path)


@pytest.mark.parametrize("name", [n for n in READERS if n.endswith(".csv")])
@FUZZ
@given(rows=st.lists(st.lists(st.one_of(numbers.map(str), st.text(max_size=6)), min_size=1, max_size=12),
                     max_size=6),
       header=st.sampled_from(["time_s,h0_target_deg,h0_angle_deg", "x_mm,y_mm,z_mm,qw,qx,qy,qz",
                               "condition_mm,natural,confidence", "a,b"]))
def test_any_table_of_the_format(tmp_path, name, rows, header):
    path = tmp_path / name
    path.write_text(header + "\n" + "\n".join(",".join(r) for r in rows) + "\n")
    _refuses_or_reads(READERS[name], path)


@pytest.mark.parametrize("name", READERS)
def test_deep_nesting_utf16_a_folder_and_a_huge_field(tmp_path, name):
    reader = READERS[name]
    cases = {"nested": ("[" * 5000 if name.endswith(".json") else "a = " + "[" * 5000).encode(),
             "utf16": '{"angles_deg": [0]}'.encode("utf-16"),
             "huge_field": b"x_mm,y\n" + b"1" * 200_000 + b",2\n"}
    for label, data in cases.items():
        path = tmp_path / label / name
        path.parent.mkdir()
        path.write_bytes(data)
        _refuses_or_reads(reader, path)
    folder = tmp_path / "folder" / name
    folder.mkdir(parents=True)
    with pytest.raises(ValueError):
        reader(folder)


# ---- a 400-digit integer in place of each number of a valid file ----------------------------------------------

HUGE = 10 ** 400


def _valid_files(tmp_path) -> dict:
    """name -> a valid file of the format, written by the project's own writers."""
    from controllers.pid import PidGains
    from twin.formats.gains import write_gains
    from twin.formats.scenario import Scenario, write_scenario
    from twin.formats.sweep import write_sweep

    import tomllib

    out = {}
    write_gains(tmp_path / "gains.json", Gains([PidGains.from_spec(SPEC)] * SPEC.n_hinges))
    write_scenario(tmp_path / "scenario.toml", Scenario("s", [0.0] * 6, [0.0, 0.5], [[0.1] * 6, [0.2] * 6], 1.0))
    (tmp_path / "scenario.json").write_text(json.dumps(tomllib.loads((tmp_path / "scenario.toml").read_text())))
    write_sweep(tmp_path / "sweep.toml", ["cube"], 2, 0, ["full"], {"flap_gap": [0.001, 0.002]})
    (tmp_path / "spec.toml").write_bytes(SPEC_PATH.read_bytes())
    for name in ("gains.json", "scenario.toml", "scenario.json", "sweep.toml", "spec.toml"):
        out[name] = (tmp_path / name).read_text()
    return out


def _json_leaves(doc, at=()):
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _json_leaves(v, at + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _json_leaves(v, at + (i,))
    elif isinstance(doc, (int, float)) and not isinstance(doc, bool):
        yield at


def _with(doc, at, value):
    doc = json.loads(json.dumps(doc))
    node = doc
    for k in at[:-1]:
        node = node[k]
    node[at[-1]] = value
    return doc


def test_a_400_digit_integer_anywhere_is_refused_in_one_line(tmp_path):
    import re

    for name, text in _valid_files(tmp_path).items():
        READERS[name](tmp_path / name)  # valid as written
        if name.endswith(".json"):
            doc = json.loads(text)
            variants = [json.dumps(_with(doc, at, HUGE)) for at in _json_leaves(doc)]
        else:
            spans = [m.span(1) for m in re.finditer(r"(?m)(?:=|\[|,)\s*(-?\d[\d_.eE+-]*)", text)]
            variants = [text[:a] + str(HUGE) + text[b:] for a, b in spans]
        assert variants, name
        for k, variant in enumerate(variants):
            path = tmp_path / f"huge{k}" / name
            path.parent.mkdir(exist_ok=True)
            path.write_text(variant)
            _refuses_or_reads(READERS[name], path)


@pytest.mark.parametrize("name", [n for n in READERS if n.endswith(".json")])
def test_a_key_given_twice_is_refused(tmp_path, name):
    path = tmp_path / name
    path.write_text('{"name": "a", "name": "b"}')
    with pytest.raises(ValueError, match="given twice"):
        READERS[name](path)


def test_a_records_file_skips_what_it_cannot_trust_and_refuses_what_is_not_a_file(tmp_path):
    from twin.formats.records import read_jsonl

    path = tmp_path / "results.jsonl"
    path.write_text('{"key": "a", "msd_mm": 1.0}\n' + "[" * 60_000 + "\n" + '{"key": "b", "key": "c"}\n'
                    + '{"key": "d", "msd_mm": 2.0}\n')
    assert [r["key"] for r in read_jsonl(path)] == ["a", "d"]  # (60,000 '[' within the line bound: nested too deeply)
    with pytest.raises(ValueError, match="not a regular file"):
        read_jsonl("/dev/zero")


@pytest.mark.parametrize("field, value", [("gear_stiction", 1e6), ("backdrive_efficiency", 5.0),
                                          ("backdrive_efficiency", 0.0), ("resistance", 0.0),
                                          ("gear_friction", -0.004), ("no_load_speed", 0.0), ("gear_damping", -1.0),
                                          ("cogging", 1.5)])
def test_a_profile_whose_plant_no_gearmotor_has_is_refused(tmp_path, field, value):
    from twin.device.spec_toml import write_spec_toml
    from twin.formats.profile import PROFILE_FORMAT

    folder = tmp_path / "mine"
    folder.mkdir()
    write_spec_toml(folder / "spec.toml", SPEC_PATH, {field: value}, "attack")
    (folder / "profile.json").write_text(json.dumps({"format": PROFILE_FORMAT, "name": "mine"}))
    with pytest.raises(ValueError, match=f"{field} = .* is not a gearmotor's"):
        read_profile(folder)


def test_per_hinge_values_of_a_zero_in_the_spec_are_refused(tmp_path):
    """A per-hinge cogging scales the spec's: a spec cogging of 0 was a ZeroDivisionError."""
    from twin.device.spec_toml import write_spec_toml
    from twin.formats.profile import PROFILE_FORMAT

    folder = tmp_path / "mine"
    folder.mkdir()
    write_spec_toml(folder / "spec.toml", SPEC_PATH, {"cogging": 0.0}, "attack")
    estimate = {"value": 0.03, "prior": 0.03, "low": 0.01, "high": 0.05, "identifiable": True, "note": ""}
    calibration = {"runs": [], "parameters": {}, "hinges": [{"cogging": estimate}] * SPEC.n_hinges}
    (folder / "profile.json").write_text(json.dumps({"format": PROFILE_FORMAT, "name": "mine",
                                                     "calibration": calibration}))
    with pytest.raises(ValueError, match="cogging = 0, but hinge 0 has its own value"):
        read_profile(folder)
