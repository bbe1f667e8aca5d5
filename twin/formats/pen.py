"""Pen CSV (docs/formats.md "Pen CSV"): pen samples to redirect, and the redirected samples.

One sample per row: the pen tip's position x_mm,y_mm,z_mm and orientation qw,qx,qy,qz (world),
optionally the tracked device's pose device_x_mm..device_qz; any other column is passed through.
The redirected file is the input's columns followed by the virtual pen and the redirection
applied (REDIRECTED_COLUMNS).
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from twin.checks import REACH_M, read_text
from twin.paths import replacing
from twin.records.pen import PenSamples

REDIRECTED_COLUMNS = ("virtual_x_mm", "virtual_y_mm", "virtual_z_mm", "virtual_qw", "virtual_qx", "virtual_qy",
                      "virtual_qz", "offset_mm", "rotation_deg", "height_mm", "flap", "within_thresholds")

PEN_COLUMNS = ("x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz")
DEVICE_COLUMNS = tuple(f"device_{c}" for c in PEN_COLUMNS)


def read_pen_samples(path) -> PenSamples:
    """Read a pen CSV as the record (positions m, unit orientations, device poses or None, every column as given).

    Required columns x_mm, y_mm, z_mm, qw, qx, qy, qz (pen tip, world); optional
    device_x_mm ... device_qz (tracked device pose); any other column is passed through.
    """
    path = Path(path)
    try:
        with io.StringIO(read_text(path), newline="") as f:
            reader = csv.DictReader(f)
            header = reader.fieldnames or []
            twice = sorted({c for c in header if header.count(c) > 1})
            if twice:  # the csv module keeps one of them: the other's values would be dropped unseen
                raise ValueError(f"{path}: column(s) {', '.join(twice)} given twice in the header")
            missing = [c for c in PEN_COLUMNS if c not in header]
            if missing:
                raise ValueError(f"{path}: missing column(s) {', '.join(missing)}; a pen file has "
                                 f"{','.join(PEN_COLUMNS)} (+ optional {','.join(DEVICE_COLUMNS)})")
            has_device = all(c in header for c in DEVICE_COLUMNS)
            if not has_device and any(c in header for c in DEVICE_COLUMNS):
                raise ValueError(f"{path}: device pose columns must be all of {','.join(DEVICE_COLUMNS)} or none")
            wanted = PEN_COLUMNS + (DEVICE_COLUMNS if has_device else ())
            rows, values = {c: [] for c in header}, []
            for line, row in enumerate(reader, start=2):
                if None in row:  # the csv module puts a row's fields beyond the header's under None
                    raise ValueError(f"{path}:{line}: {len(header) + len(row[None])} fields, the header has "
                                     f"{len(header)}")
                try:
                    numbers = [float(row[c]) for c in wanted]
                except (TypeError, ValueError):
                    raise ValueError(f"{path}:{line}: expected numbers in {','.join(wanted)}") from None
                if not all(math.isfinite(v) for v in numbers):
                    raise ValueError(f"{path}:{line}: non-finite value")
                if any(abs(v) > REACH_M * 1e3 for v in numbers):
                    raise ValueError(f"{path}:{line}: a value beyond +-{REACH_M * 1e3:g} mm "
                                     f"({REACH_M:g} m from the target)")
                values.append(numbers)
                for c in header:
                    rows[c].append(row[c])
    except csv.Error as exc:  # a field over the csv module's limit, a NUL byte
        raise ValueError(f"{path}: not a pen CSV ({exc})") from None
    if not values:
        raise ValueError(f"{path}: no pen samples")
    v = np.array(values)
    quats = [v[:, 3:7]] + ([v[:, 10:14]] if has_device else [])
    for q in quats:
        norm = np.linalg.norm(q, axis=1)
        if np.any(norm < 1e-6):
            raise ValueError(f"{path}: line {int(np.argmax(norm < 1e-6)) + 2}: zero quaternion")
        q /= norm[:, None]
    poses = None
    if has_device:
        poses = np.tile(np.eye(4), (len(v), 1, 1))
        poses[:, :3, :3] = Rotation.from_quat(v[:, 10:14], scalar_first=True).as_matrix()
        poses[:, :3, 3] = v[:, 7:10] / 1e3
    return PenSamples(v[:, :3] / 1e3, v[:, 3:7], poses, rows)


def write_redirected(path, pens: PenSamples, redirected, within: np.ndarray) -> None:
    """Write the pen file's columns followed by the virtual pen and the redirection applied (mm, deg);
    redirected: a twin.morphpatch.redirection.Redirected (SI)."""
    columns = pens.columns
    names = list(columns)
    with replacing(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(names + list(REDIRECTED_COLUMNS))
        for k in range(len(redirected.position)):
            p, q = redirected.position[k] * 1e3, redirected.orientation[k]
            w.writerow([columns[c][k] for c in names] + [f"{v:.4f}" for v in p] + [f"{v:.6f}" for v in q]
                       + [f"{redirected.offset[k] * 1e3:.4f}", f"{math.degrees(redirected.angle[k]):.4f}",
                          f"{redirected.height[k] * 1e3:.4f}", int(redirected.flap[k]), int(within[k])])
