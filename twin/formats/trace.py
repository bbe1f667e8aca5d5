"""Trace CSV (docs/formats.md "Trace CSV"): the twin's and the device's recordings, one format.

Header `time_s`, then `h{k}_{column}` for every hinge k and column, hinge by hinge. Columns every
trace has (TRACE_COLUMNS): target_deg, angle_deg (the encoder's angle: counts x rad per count, as
the device reports it), counts, duty, current_A. Columns only a twin has (TWIN_COLUMNS):
true_angle_deg (the simulated hinge's true angle), target_counts, torque_Nm. One line per row,
written and flushed as it comes, so an interrupted recording keeps every row up to its last
line; the reader drops a cut-off last line and refuses any other bad line, and returns a `Trace`
(twin.records.trace): the same columns in SI (rad, A, N*m), so no degree travels past the reader;
`write_trace` writes a whole one.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from twin.checks import cell, read_text
from twin.paths import replacing
from twin.records.trace import Trace

TRACE_COLUMNS = ("target_deg", "angle_deg", "counts", "duty", "current_A")
TWIN_COLUMNS = ("true_angle_deg", "target_counts", "torque_Nm")
_INTEGER = ("counts", "target_counts")
_HEADER = re.compile(r"h(\d+)_(.+)")
MAX_TRACE_BYTES = 512 << 20  # a 600 s HIL run at 1 kHz is about 210 MB
# column -> (Trace field, its unit in SI from the file's)
_FIELDS = {"target_deg": ("target", math.radians(1.0)), "angle_deg": ("angle", math.radians(1.0)),
           "counts": ("counts", 1), "duty": ("duty", 1.0), "current_A": ("current", 1.0),
           "true_angle_deg": ("true_angle", math.radians(1.0)), "target_counts": ("target_counts", 1),
           "torque_Nm": ("torque", 1.0)}


class TraceWriter:
    """Writes a trace CSV a line at a time (one write per row, line-buffered)."""

    def __init__(self, path, n: int, extra=()):
        unknown = [c for c in extra if c not in TWIN_COLUMNS]
        if unknown:
            raise ValueError(f"{path}: unknown trace column {unknown[0]!r}")
        self.n = n
        self.cols = TRACE_COLUMNS + tuple(extra)
        self.f = open(path, "w", newline="", buffering=1)
        self.f.write(",".join(["time_s"] + [f"h{k}_{c}" for k in range(n) for c in self.cols]) + "\n")
        self.rows = 0

    def write(self, t: float, **cols) -> None:
        """One row at time t (s); cols: each column's n values (deg, counts, duty, A, N*m as named)."""
        row = [f"{t:.4f}"]
        for k in range(self.n):
            for c in self.cols:
                v = cols[c][k]
                row.append(str(int(v)) if c in _INTEGER else f"{v:.5f}" if c == "torque_Nm" else f"{v:.4f}")
        self.f.write(",".join(row) + "\n")  # one write per row: a killed run loses at most the line being written
        self.rows += 1

    def write_rows(self, trace: Trace, rows=slice(None)) -> None:
        """The rows `rows` (an index, a slice; default all) of a trace, this writer's columns (deg in the file)."""
        columns = {c: getattr(trace, _FIELDS[c][0])[rows] for c in self.cols}
        for i, t in enumerate(trace.time[rows]):
            self.write(t, **{c: np.degrees(v[i]) if c.endswith("_deg") else v[i] for c, v in columns.items()})

    def close(self) -> None:
        self.f.close()

    def __enter__(self) -> "TraceWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_trace(path, n: int | None = None, hinge_limit: float | None = None) -> Trace:
    """A trace CSV as a Trace (SI).

    n: the hinge count it must have; hinge_limit (rad): targets must lie within it. A cut-off
    last line (an interrupted recording) is dropped; any other bad line is a ValueError naming it.
    """
    path = Path(path)
    lines = read_text(path, MAX_TRACE_BYTES).splitlines()
    if not lines:
        raise ValueError(f"{path}: empty (expected a header time_s,h0_target_deg,...)")
    header = lines[0].split(",")
    if header[0] != "time_s":
        raise ValueError(f"{path}:1: the first column must be time_s, got {header[0]!r}")
    where = {}
    for i, name in enumerate(header[1:], start=1):
        m = _HEADER.fullmatch(name)
        if not m or m.group(2) not in TRACE_COLUMNS + TWIN_COLUMNS:
            raise ValueError(f"{path}:1: unknown column {name!r} (expected h<k>_<column>, columns "
                             f"{', '.join(TRACE_COLUMNS + TWIN_COLUMNS)})")
        if name in where.values():
            raise ValueError(f"{path}:1: column {name!r} twice")
        where[i] = name
    hinges = sorted({int(_HEADER.fullmatch(h).group(1)) for h in header[1:]})
    if hinges != list(range(len(hinges))):
        raise ValueError(f"{path}:1: hinge columns {hinges} are not 0..{len(hinges) - 1}")
    if n is not None and len(hinges) != n:
        raise ValueError(f"{path}:1: a trace of {len(hinges)} hinges, the device has {n}")
    columns = [c for c in TRACE_COLUMNS + TWIN_COLUMNS if f"h0_{c}" in header]
    for c in TRACE_COLUMNS:
        if c not in columns:
            raise ValueError(f"{path}:1: missing column h0_{c}")
    for k in hinges:
        for c in columns:
            if f"h{k}_{c}" not in header:
                raise ValueError(f"{path}:1: missing column h{k}_{c}")
    ncol = len(header)
    if ncol != 1 + len(hinges) * len(columns):
        raise ValueError(f"{path}:1: hinges have different columns")
    rows = []
    last = len(lines)
    for lineno, line in enumerate(lines[1:], start=2):
        cells = line.split(",")
        try:
            if len(cells) != ncol:
                raise ValueError(f"{len(cells)} fields, the header has {ncol}")
            values = [cell(text, header[i]) for i, text in enumerate(cells)]
        except ValueError as exc:
            if lineno == last:
                break  # the line being written when the recording stopped
            raise ValueError(f"{path}:{lineno}: {exc}") from None
        rows.append(values)
    data = np.array(rows, float).reshape(-1, ncol)
    t = data[:, 0]
    if np.any(np.diff(t) < 0):
        i = int(np.argmax(np.diff(t) < 0))
        raise ValueError(f"{path}:{i + 3}: time_s {t[i + 1]:g} goes back from {t[i]:g}")
    out = {}
    for c in columns:
        column = np.stack([data[:, header.index(f"h{k}_{c}")] for k in hinges], axis=1)
        if c == "target_deg" and hinge_limit is not None and len(t):
            bad = np.abs(column) > math.degrees(hinge_limit) + 1e-3
            if bad.any():
                row, k = np.argwhere(bad)[0]
                raise ValueError(f"{path}:{row + 2}: h{k}_target_deg {column[row, k]:g} is outside the hinge "
                                 f"range +-{math.degrees(hinge_limit):g} deg")
        field, unit = _FIELDS[c]
        out[field] = column.astype(np.int64) if c in _INTEGER else column * unit
    return Trace(time=t, **out)


def write_trace(path, trace: Trace) -> None:
    """A whole trace as a trace CSV, written to a temporary file and moved into place: every column it holds
    (a twin's: true_angle_deg, target_counts, torque_Nm beside the device's)."""
    extra = tuple(c for c in TWIN_COLUMNS if getattr(trace, _FIELDS[c][0]) is not None)
    with replacing(path) as tmp, TraceWriter(tmp, trace.n_hinges, extra=extra) as w:
        w.write_rows(trace)
