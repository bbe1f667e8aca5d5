"""Run folder (docs/formats.md "Run folder"): one HIL run, as `vrscroll hil` records it.

    run.json      what was played and how the run ended (RUN_KEYS); rewritten atomically as it goes
    device.csv    the device's telemetry, a trace CSV (twin.formats.trace)
    twin.csv      the twin's replay in device time, a trace CSV with the twin's columns
    gains.json    the gains the device held, a gains file (twin.formats.gains)
    scenario.*    a copy of the scenario played

run.json's "status" is "running" while the run is recorded (and stays so when the recording
process was killed), "complete" when every step was played, "interrupted" after Ctrl-C, or
"failed: <why>". Traces of a run that did not complete hold what was recorded up to its end.
"""

from __future__ import annotations

import json
from pathlib import Path

from twin.checks import hinge_angles, json_object, known_keys, number, required_keys
from twin.device.spec import DeviceSpec
from twin.formats.gains import read_gains
from twin.formats.trace import read_trace
from twin.paths import replacing

RUN_KEYS = ("scenario", "start_counts", "start_target_counts", "before", "telemetry_hz", "firmware_dt_s", "changes",
            "status", "port", "device_t0_us", "device_rows", "twin_rows", "device_profile")
BEFORE_KEYS = ("state", "counts", "target_counts")
COMPLETE = "complete"


def write_run_meta(run_dir, meta: dict) -> None:
    """Write run.json atomically (a killed run leaves the previous version whole)."""
    known_keys(meta, RUN_KEYS, f"{run_dir}/run.json")
    with replacing(Path(run_dir) / "run.json") as tmp:
        tmp.write_text(json.dumps(meta, indent=2) + "\n")


def _counts(value, n: int, where: str) -> list[int]:
    if not isinstance(value, list) or len(value) != n or not all(isinstance(c, int) and not isinstance(c, bool)
                                                                 for c in value):
        raise ValueError(f"{where}: expected {n} whole encoder counts, got {value!r}")
    return value


def read_run_meta(run_dir, spec: DeviceSpec) -> dict:
    """run.json, checked: its keys, the hinge count of every list, the angles within the hinge range."""
    path = Path(run_dir) / "run.json"
    meta = json_object(path)
    known_keys(meta, RUN_KEYS, str(path))
    required_keys(meta, ("scenario", "status", "changes", "start_counts", "start_target_counts"), str(path))
    n = spec.n_hinges
    _counts(meta["start_counts"], n, f"{path}: start_counts")
    _counts(meta["start_target_counts"], n, f"{path}: start_target_counts")
    if "before" in meta:
        before = meta["before"]
        if not isinstance(before, dict):
            raise ValueError(f"{path}: before: expected an object with {', '.join(BEFORE_KEYS)}")
        known_keys(before, BEFORE_KEYS, f"{path}: before")
        required_keys(before, BEFORE_KEYS, f"{path}: before")
        _counts(before["counts"], n, f"{path}: before.counts")
        _counts(before["target_counts"], n, f"{path}: before.target_counts")
    if not isinstance(meta["changes"], list) or not meta["changes"]:
        raise ValueError(f"{path}: changes: expected a list of {{t_s, angles_deg}}, at least the first target's "
                         "(a run that sent no target has nothing to compare or calibrate)")
    last = -1.0
    for i, c in enumerate(meta["changes"]):
        where = f"{path}: changes[{i}]"
        if not isinstance(c, dict):
            raise ValueError(f"{where}: expected {{t_s, angles_deg}}")
        known_keys(c, ("t_s", "angles_deg"), where)
        t = number(c.get("t_s"), f"{where}: t_s")
        if t < last:
            raise ValueError(f"{where}: t_s {t} is before the previous change's {last}")
        last = t
        hinge_angles(c.get("angles_deg"), n, spec.hinge_limit, f"{where}: angles_deg")
    return meta


def read_run(run_dir, spec: DeviceSpec, incomplete: bool = False) -> dict:
    """A recorded run: {dir, meta, device, twin (None if absent), gains}.

    A run whose status is not "complete" (killed, interrupted, failed) is refused, naming the run
    and its status, unless `incomplete` is True: then what was recorded is returned.
    """
    d = Path(run_dir)
    if not d.is_dir():
        raise ValueError(f"{d}: not a run folder (no such directory)")
    if not (d / "run.json").is_file():
        raise ValueError(f"{d}: not a run folder (no run.json)")
    meta = read_run_meta(d, spec)
    if meta["status"] != COMPLETE and not incomplete:
        raise ValueError(f"{d}: the run did not complete (status {meta['status']!r}: killed, interrupted or failed "
                         "while it was recorded)")
    n = spec.n_hinges
    return {"dir": d, "meta": meta,
            "device": read_trace(d / "device.csv", n, spec.hinge_limit),
            "twin": read_trace(d / "twin.csv", n, spec.hinge_limit) if (d / "twin.csv").exists() else None,
            "gains": read_gains(d / "gains.json", n)}
