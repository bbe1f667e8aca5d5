"""Target and approximation JSON (docs/formats.md "Target JSON"): hinge angles, and the pose a
MorphPatch approximation found.

A target is `{"angles_deg": [one per hinge]}`. An approximation result (`vrscroll approximate
--json`, `vrscroll cbs --json`) is a target with the root pose, the flap widths and its measures
beside the angles, so it serves as a target too. The reader returns, and the writer takes, the
approximation record (twin.records.approximation.Approximation), in SI.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from twin.checks import REACH_M, hinge_angles, json_object, known_keys, number, numbers, required_keys
from twin.device.kinematics import matrix_quat, pose_matrix
from twin.device.spec import DeviceSpec
from twin.paths import replacing
from twin.records.approximation import Approximation

APPROXIMATION_KEYS = ("root_position_mm", "root_quat_wxyz", "angles_deg", "widths_mm")
OPTIONAL_KEYS = ("variant", "target", "start_mm_deg", "msd_mm", "hd_mm", "inside_percent", "inside_depth_mm", "time_ms",
                 "inside_over_2mm_percent", "flap_gap_mm", "flaps_through",  # vrscroll approximate (issue 37)
                 # vrscroll cbs adds these
                 "collision_parts", "collision_error_mean_mm", "collision_error_max_mm", "touching_flaps")


def read_target(path, spec: DeviceSpec) -> np.ndarray:
    """Hinge targets (rad) from a target or approximation JSON; ValueError naming the file and the key."""
    path = Path(path)
    doc = json_object(path)
    known_keys(doc, APPROXIMATION_KEYS + OPTIONAL_KEYS, str(path))
    required_keys(doc, ("angles_deg",), str(path))
    return hinge_angles(doc["angles_deg"], spec.n_hinges, spec.hinge_limit, f"{path}: angles_deg")


def read_approximation(path, spec: DeviceSpec) -> Approximation:
    """An approximation result file, checked, as the record (see `approximation_record`)."""
    path = Path(path)
    return approximation_record(json_object(path), spec, str(path))


QUAT_NORM_TOLERANCE = 1e-3  # a written quaternion's norm may miss 1 by its rounding; more is not a rotation


def approximation_record(doc: dict, spec: DeviceSpec, where: str) -> Approximation:
    """An approximation result (a file's object, or a live message's), checked, as the record in SI: root_pose
    (4x4, m), angles (rad), widths (m), time (s), variant (default "full"), msd/hd/depth (m or None), inside
    (share 0..1 or None), target (its name, or None). ValueError naming `where` and the key."""
    if not isinstance(doc, dict):
        raise ValueError(f"{where}: expected an approximation result {{...}}, got {type(doc).__name__}")
    known_keys(doc, APPROXIMATION_KEYS + OPTIONAL_KEYS, where)
    required_keys(doc, APPROXIMATION_KEYS, f"{where}: not an approximation result (vrscroll approximate --json)")
    angles = hinge_angles(doc["angles_deg"], spec.n_hinges, spec.hinge_limit, f"{where}: angles_deg")
    position = numbers(doc["root_position_mm"], f"{where}: root_position_mm", 3) / 1e3
    quat = numbers(doc["root_quat_wxyz"], f"{where}: root_quat_wxyz", 4)
    norm = float(np.linalg.norm(quat)) if np.abs(quat).max() <= 2.0 else math.inf  # no overflow on 1e200
    if not abs(norm - 1.0) <= QUAT_NORM_TOLERANCE:  # 1e200 each: a norm of inf, normalised to NaN ("MSD 0.0 mm")
        raise ValueError(f"{where}: root_quat_wxyz is not a unit quaternion (its norm is {norm:.6g})")
    if np.linalg.norm(position) > REACH_M:
        raise ValueError(f"{where}: root_position_mm is more than {REACH_M:g} m from the target's origin")
    widths = numbers(doc["widths_mm"], f"{where}: widths_mm", spec.n_flaps) / 1e3
    bad = (widths <= 0) | (widths > spec.length)
    if np.any(bad):
        raise ValueError(f"{where}: widths_mm: flap {int(np.argmax(bad))} is {widths[np.argmax(bad)] * 1e3:g} mm wide; "
                         f"a flap is above 0 and at most the device's {spec.length * 1e3:g} mm")
    measure = {k: (None if doc.get(f"{k}_mm") is None else number(doc[f"{k}_mm"], f"{where}: {k}_mm") / 1e3)
               for k in ("msd", "hd")}
    measure["depth"] = None if doc.get("inside_depth_mm") is None else number(doc["inside_depth_mm"],
                                                                              f"{where}: inside_depth_mm") / 1e3
    inside = None if doc.get("inside_percent") is None else number(doc["inside_percent"], f"{where}: inside_percent")
    if inside is not None and not 0.0 <= inside <= 100.0:
        raise ValueError(f"{where}: inside_percent: {inside:g} is not a percentage (0 to 100)")
    measure["inside"] = None if inside is None else inside / 100
    target = doc.get("target")
    if target is not None and not isinstance(target, str):
        raise ValueError(f"{where}: target: expected a shape name or mesh path, got {target!r}")
    return Approximation(pose_matrix(position, Rotation.from_quat(quat, scalar_first=True).as_matrix()), angles,
                         widths, number(doc.get("time_ms", 0.0), f"{where}: time_ms") / 1e3,
                         str(doc.get("variant", "full")), **measure, target=target)


def message_approximation(message: dict, spec: DeviceSpec, where: str) -> Approximation:
    """The approximation a live message carries beside its own keys (type, seq, ...), as the record."""
    return approximation_record({k: v for k, v in message.items() if k in APPROXIMATION_KEYS + OPTIONAL_KEYS}, spec,
                                where)


def approximation_json(a: Approximation) -> dict:
    """The record as the result's keys, the unit in every key (mm, deg, ms); the inverse of
    `approximation_record` (the target, a start and the OPTIONAL_KEYS a command adds are its own)."""
    quat = matrix_quat(a.root_pose[:3, :3])  # scipy's Rotation to the last bit, at a tenth of its cost
    mm = (lambda v: None if v is None else round(v * 1e3, 3))
    return {
        "variant": a.variant,
        "root_position_mm": [round(v, 3) for v in (a.root_pose[:3, 3] * 1e3).tolist()],
        "root_quat_wxyz": [round(v, 6) for v in quat],
        "angles_deg": [round(v, 3) for v in np.degrees(a.angles).tolist()],
        "widths_mm": [round(v, 3) for v in (a.widths * 1e3).tolist()],
        "msd_mm": mm(a.msd),
        "hd_mm": mm(a.hd),
        "inside_percent": None if a.inside is None else round(a.inside * 100, 2),
        "inside_depth_mm": mm(a.depth),
        "time_ms": round(a.time * 1e3, 4),
    }


def write_approximation(path, doc: dict) -> None:
    """Write an approximation result (`approximation_json` plus target, start and any OPTIONAL_KEYS)."""
    known_keys(doc, APPROXIMATION_KEYS + OPTIONAL_KEYS, str(path))
    with replacing(path) as tmp:
        Path(tmp).write_text(json.dumps(doc, indent=2) + "\n")
