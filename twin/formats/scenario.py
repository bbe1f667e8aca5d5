"""Scenario TOML or JSON (docs/formats.md "Scenario"): timed hinge targets for a HIL run.

    name = "steps"                    # optional (default: the file's name)
    start_deg = [0, 0, 0, 0, 0, 0]    # optional: where both sides begin (default flat)
    duration_s = 3.0                  # optional: total length (default last step + 1 s)
    [[step]]
    t_s = 0.0                         # the first step is at 0; each later one after the one before
    angles_deg = [20, 20, 20, 20, 20, 20]
    [[step]]
    t_s = 1.0
    file = "approx.json"              # or a target / approximation JSON (twin.formats.target)

JSON: the same keys, "step" a list of objects.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path

import numpy as np

from twin.checks import hinge_angles, known_keys, number, parse_json, parse_toml, read_text
from twin.device.spec import DeviceSpec
from twin.formats.target import read_target
from twin.paths import replacing

SCENARIO_KEYS = ("name", "start_deg", "duration_s", "step")
MAX_DURATION_S = 600.0  # a HIL run records both sides at 1 kHz in memory: ten minutes is ~60 MB of traces
MAX_STEPS = 10_000
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")  # a scenario's name becomes part of a folder's name
STEP_KEYS = ("t_s", "angles_deg", "file")


@dataclasses.dataclass
class Scenario:
    """Timed hinge targets (rad) from a start (rad); after the last step the run lasts until duration (s)."""

    name: str
    start: np.ndarray  # rad
    times: list[float]  # s, from the first target's taking effect; times[0] == 0
    targets: list[np.ndarray]  # rad
    duration: float  # s


def read_scenario(path, spec: DeviceSpec) -> Scenario:
    """Read a scenario; ValueError naming the file, the step and the key for anything wrong."""
    path = Path(path)
    text = read_text(path)
    doc = parse_json(text, str(path)) if path.suffix == ".json" else parse_toml(text, str(path))
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: expected an object with \"step\" entries")
    known_keys(doc, SCENARIO_KEYS, str(path))
    n, limit = spec.n_hinges, spec.hinge_limit
    steps = doc.get("step")
    if not steps:
        raise ValueError(f"{path}: no [[step]] entries")
    if not isinstance(steps, list) or not all(isinstance(s, dict) for s in steps):
        raise ValueError(f"{path}: step: expected a list of [[step]] tables, got {steps!r}")
    if len(steps) > MAX_STEPS:
        raise ValueError(f"{path}: {len(steps)} steps; at most {MAX_STEPS}")

    times, targets = [], []
    for i, entry in enumerate(steps):
        where = f"{path}: step {i}"
        known_keys(entry, STEP_KEYS, where)
        if ("angles_deg" in entry) == ("file" in entry):
            raise ValueError(f"{where}: give angles_deg or file (one of them)")
        if "file" in entry:
            if not isinstance(entry["file"], str):
                raise ValueError(f"{where}: file: expected a file name, got {entry['file']!r}")
            targets.append(read_target(path.parent / entry["file"], spec))
        else:
            targets.append(hinge_angles(entry["angles_deg"], n, limit, f"{where}: angles_deg"))
        t = number(entry.get("t_s", 0.0), f"{where}: t_s")
        if times and t <= times[-1]:
            raise ValueError(f"{where}: t_s {t} is not after the previous step's {times[-1]}")
        times.append(t)
    if times[0] != 0.0:
        raise ValueError(f"{path}: the first step must be at t_s = 0")
    start = hinge_angles(doc["start_deg"], n, limit, f"{path}: start_deg") if "start_deg" in doc else np.zeros(n)
    duration = number(doc.get("duration_s", times[-1] + 1.0), f"{path}: duration_s")
    if duration <= times[-1]:
        raise ValueError(f"{path}: duration_s {duration} ends before the last step at {times[-1]} s")
    if duration > MAX_DURATION_S:
        raise ValueError(f"{path}: duration_s {duration:g} s; a HIL run is at most {MAX_DURATION_S:g} s")
    name = doc.get("name", re.sub(r"[^A-Za-z0-9_.-]+", "-", path.stem).strip(".-")[:64] or "scenario")
    if not isinstance(name, str) or not NAME.fullmatch(name) or ".." in name:
        raise ValueError(f"{path}: name: {name!r} is not a plain name (letters, digits, '_', '.', '-'; at most 64; "
                         "it becomes part of the run folder's name)")
    return Scenario(name, start, times, targets, duration)


def scenario_of_steps(name: str, steps, duration: float, start_deg=None) -> Scenario:
    """A scenario from its steps as people write them: (t s, hinge angles deg) each, the first at 0, from start_deg
    (default flat); duration s."""
    n = len(steps[0][1])
    return Scenario(name, np.radians(np.zeros(n) if start_deg is None else np.asarray(start_deg, float)),
                    [float(t) for t, _ in steps], [np.radians(np.asarray(a, float)) for _, a in steps], float(duration))


def write_scenario(path, scenario: Scenario) -> None:
    """Write a scenario as TOML (angles in degrees)."""
    deg = (lambda a: "[" + ", ".join(f"{math.degrees(x):.6g}" for x in a) + "]")
    lines = [f"name = {json.dumps(scenario.name)}", f"start_deg = {deg(scenario.start)}",
             f"duration_s = {scenario.duration:.6g}"]
    for t, tgt in zip(scenario.times, scenario.targets):
        lines += ["", "[[step]]", f"t_s = {t:.6g}", f"angles_deg = {deg(tgt)}"]
    with replacing(path) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n")
