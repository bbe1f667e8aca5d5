"""A records file (evaluate's results.jsonl, sweep's records.jsonl) is read back to resume and to summarise:
what the programs did not write there is refused in one line naming the file and line, before any work, never
a traceback or a NaN in a table (issue 40 attacks 7 and 9)."""

import json
import os

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from twin.cli import main
from twin.evaluation.table1 import METHODS
from twin.formats.sweep import read_records as read_sweep_records


def _evaluation(folder, line: str):
    """An evaluate folder of one complete start whose first record is `line`, and its settings."""
    folder.mkdir()
    (folder / "settings.json").write_text(json.dumps({"starts": 2, "seed": 0, "methods": list(METHODS)}))
    rows = [json.dumps({"shape": "cube", "start": 0, "method": m, "msd_mm": 1.0, "hd_mm": 2.0, "time_ms": 3.0})
            for m in METHODS]
    (folder / "results.jsonl").write_text("\n".join([line] + rows[1:]) + "\n")


@pytest.mark.parametrize("field, value, says", [
    ("msd_mm", '"abc"', "msd_mm: expected a number, got 'abc'"),
    ("msd_mm", "NaN", "msd_mm: nan is not a finite number"),
    ("hd_mm", "1e999", "hd_mm: inf is not a finite number"),
    ("time_ms", "null", "time_ms: expected a number, got None"),
    ("start", '"0"', "start: expected a whole number"),
    ("shape", "[1]", "shape: expected a string"),
    ("gate_range_ok", '"yes"', "gate_range_ok: expected true or false"),
    ("angles_deg", '[1, "x"]', "angles_deg[1]: expected a number"),
])
def test_evaluate_refuses_a_record_it_did_not_write(tmp_path, capsys, field, value, says):
    record = {"shape": "cube", "start": 0, "method": METHODS[0], "msd_mm": 1.0, "hd_mm": 2.0, "time_ms": 3.0}
    line = json.dumps(record).replace(f'"{field}": {json.dumps(record[field])}', f'"{field}": {value}') \
        if field in record else json.dumps(record)[:-1] + f', "{field}": {value}}}'
    folder = tmp_path / "ev"
    _evaluation(folder, line)
    assert main(["evaluate", "--out", str(folder), "--shapes", "cube", "--starts", "2"]) == 2
    err = capsys.readouterr().err
    assert f"{folder / 'results.jsonl'} line 1: {says}" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("extra, says", [({}, "missing 'hd_mm'"),
                                         ({"hd_mm": 2.0, "time_ms": 3.0, "twin_msd_mm": 1.5},
                                          "missing 'share_within' (it comes with 'twin_msd_mm')")])
def test_a_record_without_what_the_table_needs_is_refused(tmp_path, capsys, extra, says):
    """(A record with the twin's MSD but not its share within the thresholds was a KeyError in the summary.)"""
    folder = tmp_path / "ev"
    _evaluation(folder, json.dumps({"shape": "cube", "start": 0, "method": METHODS[0], "msd_mm": 1.0, **extra}))
    assert main(["evaluate", "--out", str(folder), "--shapes", "cube", "--starts", "2"]) == 2
    assert f"line 1: {says}" in capsys.readouterr().err


def test_nesting_a_long_line_a_special_file_and_a_huge_sparse_file_are_one_line_each(tmp_path, capsys):
    from twin.evaluation.table1 import read_records
    from twin.formats.records import MAX_LINE_BYTES, RecordLog

    folder = tmp_path / "ev"
    _evaluation(folder, "[" * 60_000)  # nested too deeply: skipped as a cut line, the start computed again...
    log = folder / "results.jsonl"
    assert {r["method"] for r in read_records(log)} == set()  # ...so no start is complete yet
    _evaluation(tmp_path / "long", "[" * 100_000)  # longer than any record: refused, not parsed
    assert main(["evaluate", "--out", str(tmp_path / "long"), "--shapes", "cube", "--starts", "2"]) == 2
    err = capsys.readouterr().err
    assert f"results.jsonl line 1: over {MAX_LINE_BYTES:,} bytes, not a record" in err and len(err.splitlines()) == 1
    with open(log, "ab") as f:  # a last line cut short is removed before the next record, read from the end
        f.write(b'{"shape": "cube", "sta')
    RecordLog(log).close()
    assert log.read_bytes().endswith(b'"time_ms": 3.0}\n')
    log.unlink()
    log.symlink_to("/dev/zero")
    assert main(["evaluate", "--out", str(folder), "--shapes", "cube", "--starts", "2"]) == 2
    assert f"{log}: not a regular file" in capsys.readouterr().err
    log.unlink()
    with open(log, "wb") as f:  # 3 GB sparse: no disk used, and refused before a byte is read
        f.truncate(3 << 30)
    assert main(["evaluate", "--out", str(folder), "--shapes", "cube", "--starts", "2"]) == 2
    err = capsys.readouterr().err
    assert f"{log}: 3,221,225,472 bytes; at most 1,073,741,824" in err and len(err.strip().splitlines()) == 1
    os.truncate(log, 500 << 20)  # 500 MB of zeros, within the size bound: one line too long, read no further
    assert main(["evaluate", "--out", str(folder), "--shapes", "cube", "--starts", "2"]) == 2
    assert f"{log} line 1: over {MAX_LINE_BYTES:,} bytes" in capsys.readouterr().err


def test_settings_that_are_not_a_json_object_are_one_line(tmp_path, capsys):
    folder = tmp_path / "ev"
    _evaluation(folder, "")
    (folder / "settings.json").unlink()
    (folder / "settings.json").symlink_to("/dev/zero")
    assert main(["evaluate", "--out", str(folder), "--shapes", "cube", "--starts", "2"]) == 2
    assert "settings.json: not a regular file" in capsys.readouterr().err


def test_sweep_records_are_checked_alike(tmp_path):
    log = tmp_path / "records.jsonl"
    good = {"key": "a", "msd_mm": 1.0, "twin_msd_mm": 1.5, "morph_time_s": None, "gate_range_ok": True,
            "gate_collision_ok": True}
    log.write_text(json.dumps(good) + "\n" + json.dumps({**good, "key": "b", "morph_time_s": "slow"}) + "\n")
    with pytest.raises(ValueError, match="line 2: morph_time_s: expected a number, got 'slow'"):
        read_sweep_records(log)
    log.write_text(json.dumps(good) + "\n" + json.dumps({**good, "key": 5}) + "\n")
    with pytest.raises(ValueError, match="line 2: key: expected a string"):
        read_sweep_records(log)
    log.write_text(json.dumps(good) + "\n")
    assert read_sweep_records(log) == {"a": good}


# ---- drawn records: read and summarised, or refused in one line naming the file ----------------------------

RESULT_KEYS = ["shape", "start", "method", "msd_mm", "hd_mm", "time_ms", "twin_msd_mm", "share_within",
               "gate_range_ok", "gate_collision_ok", "anchor_depth_mm", "inside_percent", "inside_depth_mm",
               "morph_time_s", "angles_deg"]
values = st.one_of(st.integers(-3, 3), st.floats(allow_nan=True, allow_infinity=True), st.booleans(), st.none(),
                   st.sampled_from(["cube", "abc", *METHODS]), st.lists(st.floats(-90, 90), max_size=3))
good = {"shape": "cube", "start": 0, "method": METHODS[0], "msd_mm": 1.0, "hd_mm": 2.0, "time_ms": 3.0,
        "twin_msd_mm": 1.5, "share_within": 0.5, "gate_range_ok": True, "gate_collision_ok": True,
        "anchor_depth_mm": -1.0}


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(changes=st.lists(st.tuples(st.integers(0, 2 * len(METHODS) - 1), st.sampled_from(RESULT_KEYS),
                                  st.one_of(values, st.just(...))), max_size=4))
def test_drawn_records_are_summarised_or_refused_naming_the_line(tmp_path, changes):
    """Two complete starts, then fields changed or (...) removed at random: evaluate's reader and summary either
    give a table or refuse in one line naming the file; never another exception."""
    from twin.evaluation.table1 import read_records, summarize

    rows = [{**good, "start": s, "method": m} for s in (0, 1) for m in METHODS]
    for row, key, value in changes:
        if value is ...:
            rows[row].pop(key, None)
        else:
            rows[row][key] = value
    path = tmp_path / "results.jsonl"
    path.write_text("".join(json.dumps(r, allow_nan=True) + "\n" for r in rows))
    try:
        records = read_records(path)
    except ValueError as exc:
        assert str(exc).startswith(f"{path} line ") and "\n" not in str(exc), exc
        return
    summarize(records)
