"""Run folder (docs/formats.md "Run folder"): one HIL run, as `vrscroll hil` records it.

    run.json      what was played and how the run ended (RUN_KEYS); rewritten atomically as it goes
    device.csv    the device's telemetry, a trace CSV (twin.formats.trace)
    twin.csv      the twin's replay in device time, a trace CSV with the twin's columns
    gains.json    the gains the device held, a gains file (twin.formats.gains)
    scenario.*    a copy of the scenario played

run.json's "status" is "running" while the run is recorded (and stays so when the recording
process was killed), "complete" when every step was played, "interrupted" after Ctrl-C, "stopped:
<why>" when the host e-stopped the device for parting from the twin by more than "tolerance_deg"
(the hinge and the time named), or "failed: <why>". "mount" is how the device was held (twin.device.mount). Traces of a run that did not complete hold what was recorded up to its end.
`read_run` returns a `Run`, in SI (times s, targets rad), the form calibration, replay and the
reports take.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from controllers.pid import PidGains
from twin.checks import hinge_angles, json_object, known_keys, number, required_keys
from twin.device.spec import DeviceSpec
from twin.formats.gains import read_gains
from twin.formats.scenario import MAX_DURATION_S
from twin.formats.trace import read_trace
from twin.paths import replacing
from twin.records.trace import Trace

RUN_KEYS = ("scenario", "start_counts", "start_target_counts", "start_integral_duty", "before", "telemetry_hz",
            "firmware_dt_s", "changes", "status", "port", "device_t0_us", "device_rows", "twin_rows", "device_profile",
            "mount", "tolerance_deg")
BEFORE_KEYS = ("state", "counts", "target_counts")
COMPLETE = "complete"
# s of device time a run may span: its scenario (at most MAX_DURATION_S) and the telemetry drained after the
# scenario's end, which is the last batch and never a minute of it; calibration and view play a run from 0 to
# its last frame at the firmware's rate, so a device.csv whose last time was 1e9 s asked for 43.7 TiB
MAX_RUN_S = MAX_DURATION_S + 60.0


@dataclasses.dataclass(frozen=True)
class RunStart:
    """Where the device was when a run began, and just before (its recent history: the twin replays it)."""

    counts: np.ndarray  # encoder counts at the start
    target_counts: np.ndarray  # the targets it held at the start, counts
    before_state: str | None = None  # its state just before the run's first move ("ACTIVE", "IDLE", ...)
    before_counts: np.ndarray | None = None  # its counts then
    before_target_counts: np.ndarray | None = None  # its targets then
    integral: np.ndarray | None = None  # each hinge's PID integral at the start, duty (None: not reported)


@dataclasses.dataclass(frozen=True)
class Run:
    """A recorded run, in SI."""

    dir: Path
    scenario: str
    status: str
    start: RunStart
    changes: list  # [(device time s, targets rad (n,))], the first at 0: each target from its ACK on
    device: Trace
    twin: Trace | None
    gains: list[PidGains]  # per hinge, the gains the device held
    meta: dict  # run.json as written: the report's other lines (port, telemetry rate, device profile)


def run_start(meta: dict) -> RunStart:
    """The start of a run from its run.json (checked by check_run_json, or being written by the recorder)."""
    before = meta.get("before") or {}
    counts = {k: np.asarray(before[k], np.int64) if k in before else None for k in ("counts", "target_counts")}
    integral = meta.get("start_integral_duty")
    return RunStart(np.asarray(meta["start_counts"], np.int64), np.asarray(meta["start_target_counts"], np.int64),
                    before.get("state"), counts["counts"], counts["target_counts"],
                    None if integral is None else np.asarray(integral, float))


def run_changes(meta: dict) -> list:
    """run.json's target changes as [(t s, targets rad)]."""
    return [(float(c["t_s"]), np.radians(np.asarray(c["angles_deg"], float))) for c in meta["changes"]]


def write_run_meta(run_dir, meta: dict) -> None:
    """Write run.json atomically (a killed run leaves the previous version whole)."""
    known_keys(meta, RUN_KEYS, f"{run_dir}/run.json")
    with replacing(Path(run_dir) / "run.json") as tmp:
        tmp.write_text(json.dumps(meta, indent=2) + "\n")


def recorded_status(run_dir) -> str | None:
    """The status in run_dir's run.json where a run is recorded there ("unreadable" where the file cannot be
    read as one), None where none is."""
    meta = Path(run_dir) / "run.json"
    if not (meta.exists() or meta.is_symlink()):
        return None
    try:
        return str(json.loads(meta.read_text()).get("status", "unknown"))
    except (OSError, ValueError, AttributeError):
        return "unreadable"


def _counts(value, n: int, where: str) -> list[int]:
    if not isinstance(value, list) or len(value) != n or not all(isinstance(c, int) and not isinstance(c, bool)
                                                                 for c in value):
        raise ValueError(f"{where}: expected {n} whole encoder counts, got {value!r}")
    return value


def _duties(value, n: int, where: str) -> None:
    if not isinstance(value, list) or len(value) != n or not all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and -1 <= x <= 1
            for x in value):
        raise ValueError(f"{where}: expected {n} duties, numbers from -1 to 1, got {value!r}")


def check_run_json(meta, path, spec: DeviceSpec) -> None:
    """A run's run.json as read (meta, from `path`), checked: its keys, the hinge count of every list, the angles
    within the hinge range; ValueError naming the key. read_run makes the Run record of it."""
    known_keys(meta, RUN_KEYS, str(path))
    required_keys(meta, ("scenario", "status", "changes", "start_counts", "start_target_counts"), str(path))
    for key in ("scenario", "status"):  # names, shown in reports and compared between runs
        if not isinstance(meta[key], str):
            raise ValueError(f"{path}: {key}: expected a string, got {type(meta[key]).__name__}")
    n = spec.n_hinges
    _counts(meta["start_counts"], n, f"{path}: start_counts")
    _counts(meta["start_target_counts"], n, f"{path}: start_target_counts")
    if "start_integral_duty" in meta:
        _duties(meta["start_integral_duty"], n, f"{path}: start_integral_duty")
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
        if t > MAX_RUN_S:
            raise ValueError(f"{where}: t_s {t:g} s is past the longest a run spans, {MAX_RUN_S:g} s (MAX_RUN_S)")
        if t < last:
            raise ValueError(f"{where}: t_s {t} is before the previous change's {last}")
        last = t
        hinge_angles(c.get("angles_deg"), n, spec.hinge_limit, f"{where}: angles_deg")


def read_run(run_dir, spec: DeviceSpec, incomplete: bool = False) -> Run:
    """A recorded run, in SI.

    A run whose status is not "complete" (killed, interrupted, failed) is refused, naming the run
    and its status, unless `incomplete` is True: then what was recorded is returned.
    """
    d = Path(run_dir)
    if not d.is_dir():
        raise ValueError(f"{d}: not a run folder (no such directory)")
    if not (d / "run.json").is_file():
        raise ValueError(f"{d}: not a run folder (no run.json)")
    meta = json_object(d / "run.json")
    check_run_json(meta, d / "run.json", spec)
    if meta["status"] != COMPLETE and not incomplete:
        raise ValueError(f"{d}: the run did not complete (status {meta['status']!r}: killed, interrupted or failed "
                         "while it was recorded)")
    n = spec.n_hinges
    traces = {name: read_trace(d / name, n, spec.hinge_limit) if name == "device.csv" or (d / name).exists() else None
              for name in ("device.csv", "twin.csv")}
    for name, trace in traces.items():
        if trace is not None and len(trace.time) and trace.time[-1] > MAX_RUN_S:
            raise ValueError(f"{d / name}: its last time {trace.time[-1]:g} s is past the longest a run spans, "
                             f"{MAX_RUN_S:g} s (MAX_RUN_S)")
    return Run(d, meta["scenario"], meta["status"], run_start(meta), run_changes(meta), traces["device.csv"],
               traces["twin.csv"], read_gains(d / "gains.json", n).hinges, meta)
