"""Append-only JSON-lines records (a sweep's records.jsonl, Table 1's results.jsonl): one JSON object a line,
appended and flushed one at a time, so an interrupted run resumes from what it wrote. A line an interruption
(or a full disk) cut short is removed before the next record is appended, and skipped when read."""

from __future__ import annotations

import json
import math
from pathlib import Path

from twin.checks import number, numbers, parse_json, regular_file


class RecordLog:
    """The sweep's records file, opened to append: a line an interruption cut short is removed first, so
    the next record starts on a line of its own."""

    def __init__(self, path):
        self.path = Path(path)
        if self.path.exists():
            with open(regular_file(self.path, MAX_RECORDS_BYTES), "r+b") as f:
                start = max(0, f.seek(0, 2) - MAX_LINE_BYTES - 1)  # a cut line is shorter than a whole one
                f.seek(start)
                tail = f.read()
                if tail and not tail.endswith(b"\n"):
                    if start and b"\n" not in tail:
                        raise ValueError(f"{self.path}: its last line is over {MAX_LINE_BYTES:,} bytes, not a record")
                    f.truncate(start + tail.rfind(b"\n") + 1)
        self._f = open(self.path, "a")

    def write(self, record: dict) -> None:
        """Append one record and flush it to the file."""
        self._f.write(json.dumps(record, allow_nan=False) + "\n")
        self._f.flush()

    def close(self) -> None:
        self._f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# a records file's bytes: 1 GiB holds a million (a sweep's MAX_RUNS) records of about 650 bytes, a sweep's over two keys
MAX_RECORDS_BYTES = 1 << 30
# bytes of one line: the largest record the programs write, a sweep's over all 62 spec keys, is about 4.5 kB; a file
# read line by line holds no more than this of a line (500 MB of zeros, within MAX_RECORDS_BYTES, was read whole)
MAX_LINE_BYTES = 64 << 10

# what each result field of a record must be where present (both records files share these: table1's
# evaluate_start and sweep's run_task write them); the summaries compute with them, so a word or NaN there was
# a TypeError traceback or a NaN mean with exit 0
NUMBER_FIELDS = {"msd_mm": (0, math.inf), "hd_mm": (0, math.inf), "time_ms": (0, math.inf),
                 "twin_msd_mm": (0, math.inf), "share_within": (0, 1), "inside_percent": (0, 100),
                 "inside_over_2mm_percent": (0, 100),
                 "inside_depth_mm": (0, math.inf), "anchor_depth_mm": (-math.inf, math.inf), "mass_g": (0, math.inf),
                 "morph_time_s": (0, math.inf)}  # each within (low, high), inclusive
FLAG_FIELDS = ("gate_range_ok", "gate_collision_ok", "rests")
TEXT_FIELDS = ("key", "shape", "method", "design")  # the labels a record is grouped by
WHOLE_FIELDS = ("start", "design_index", "plant")


def read_jsonl(path, required=(), together=()) -> list[dict]:
    """The objects of a records file, in order, read a line at a time; a line cut short, nested too deeply, with a
    key twice (which value would count?) or not an object is skipped (its work is done again). ValueError for a
    file that is not a regular file (/dev/zero) or over MAX_RECORDS_BYTES, before it is read, for a line over
    MAX_LINE_BYTES, and for a whole record missing a `required` key or one of a `together` group it has another
    of, or whose result fields are not what was written (check_record), naming the line."""
    path = Path(path)
    if not path.exists():
        return []
    out = []
    with open(regular_file(path, MAX_RECORDS_BYTES), "rb") as f:
        for n, line in enumerate(iter(lambda: f.readline(MAX_LINE_BYTES + 1), b""), 1):
            if len(line.rstrip(b"\r\n")) > MAX_LINE_BYTES:
                raise ValueError(f"{path} line {n}: over {MAX_LINE_BYTES:,} bytes, not a record (MAX_LINE_BYTES)")
            try:
                record = parse_json(line, str(path))
            except ValueError:
                continue
            if isinstance(record, dict):
                check_record(record, required, f"{path} line {n}", together)
                out.append(record)
    return out


def check_record(record: dict, required, where: str, together=()) -> None:
    """Check one record of a log: each `required` key there, each group of `together` there whole or not at all
    (fields one summary takes together, which older records lack), and each result field present is what the
    programs write:
    NUMBER_FIELDS finite numbers within their ranges (`morph_time_s` also null), FLAG_FIELDS true or false,
    `angles_deg` a list of numbers, TEXT_FIELDS strings and WHOLE_FIELDS whole numbers; ValueError naming `where`
    and the field otherwise."""
    for key in required:
        if key not in record:
            raise ValueError(f"{where}: missing {key!r}")
    for key in TEXT_FIELDS:
        if key in record and not isinstance(record[key], str):
            raise ValueError(f"{where}: {key}: expected a string, got {record[key]!r:.40}")
    for key in WHOLE_FIELDS:
        if key in record and (isinstance(record[key], bool) or not isinstance(record[key], int)):
            raise ValueError(f"{where}: {key}: expected a whole number, got {record[key]!r:.40}")
    for key, (low, high) in NUMBER_FIELDS.items():
        if key in record and not (key == "morph_time_s" and record[key] is None):
            x = number(record[key], f"{where}: {key}")
            if not low <= x <= high:
                raise ValueError(f"{where}: {key}: {x:g} is outside [{low:g}, {high:g}]")
    for key in FLAG_FIELDS:
        if key in record and not isinstance(record[key], bool):
            raise ValueError(f"{where}: {key}: expected true or false, got {record[key]!r:.40}")
    if "angles_deg" in record:
        numbers(record["angles_deg"], f"{where}: angles_deg")
    for group in together:
        present = [k for k in group if k in record]
        if present and len(present) < len(group):
            key = next(k for k in group if k not in record)
            raise ValueError(f"{where}: missing {key!r} (it comes with {present[0]!r})")
