"""Append-only JSON-lines records (a sweep's records.jsonl, Table 1's results.jsonl): one JSON object a line,
appended and flushed one at a time, so an interrupted run resumes from what it wrote. A line an interruption
(or a full disk) cut short is removed before the next record is appended, and skipped when read."""

from __future__ import annotations

import json
from pathlib import Path

from twin.checks import parse_json, read_text


class RecordLog:
    """The sweep's records file, opened to append: a line an interruption cut short is removed first, so
    the next record starts on a line of its own."""

    def __init__(self, path):
        self.path = Path(path)
        if self.path.exists():
            data = self.path.read_bytes()
            if data and not data.endswith(b"\n"):
                with open(self.path, "r+b") as f:
                    f.truncate(data.rfind(b"\n") + 1)
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


MAX_RECORDS_BYTES = 1 << 30  # a records file read whole: 1 GiB is a million records of the largest sweep


def read_jsonl(path) -> list[dict]:
    """The objects of a records file, in order; a line cut short, nested too deeply, with a key twice (which
    value would count?) or not an object is skipped (its work is done again). ValueError for a file that is not
    a regular file (/dev/zero) or over MAX_RECORDS_BYTES, before it is read."""
    path = Path(path)
    if not path.exists():
        return []
    out = []
    for line in read_text(path, MAX_RECORDS_BYTES).splitlines():
        try:
            record = parse_json(line, str(path))
        except ValueError:
            continue
        if isinstance(record, dict):
            out.append(record)
    return out
