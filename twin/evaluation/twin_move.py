"""A move on the twin as `vrscroll simulate` makes it: gated, simulated until settled (or for the whole time
allowed), reported per hinge, and for an approximation where the twin ended on its target. SI throughout; the
JSON (`to_json`) in deg and mm as the commands write it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from twin.checks import cell, hinge_angles
from twin.device.spec import DeviceSpec
from twin.formats.move_report import move_rows
from twin.formats.target import read_approximation
from twin.morphpatch.shapes import load_mesh, load_shape, shape_names
from twin.morphpatch.surface_metrics import match, match_json
from twin.records.approximation import Approximation
from twin.records.move_report import MoveReport
from twin.records.trace import Trace
from twin.sim.gate import GateReport, check_move
from twin.sim.response import move_report
from twin.sim.targets import check_targets
from twin.sim.twin import Twin


@dataclasses.dataclass(frozen=True)
class TwinMove:
    """A gated move on the twin and its report."""

    start: np.ndarray  # rad, the hinge angles it started from
    gate: GateReport  # the gate's checks (its prediction: the move until settled)
    trace: Trace  # the move: until settled, or the whole time allowed (hold)
    report: MoveReport  # per hinge: settle time, overshoot, errors, peak current
    on_target: dict  # for an approximation: where the twin ended on its target (match_json), or why not; else {}

    def to_json(self, label: str) -> dict:
        """The move as `vrscroll simulate --json` writes it (label: the device profile's)."""
        return {"device_profile": label, "simulated_s": round(self.trace.duration, 3),
                "wall_s": round(self.trace.wall_time, 4), "real_time_factor": round(self.trace.real_time_factor, 1),
                "settled": self.report.settled, "start_deg": np.degrees(self.start).round(3).tolist(),
                "gate": self.gate.to_dict(), "hinges": move_rows(self.report), **self.on_target}


def move_targets(spec: DeviceSpec, words: list[str], start: str | None) -> tuple[np.ndarray, np.ndarray, Approximation | None]:
    """(targets, start rad, the approximation or None) from the command line's targets (deg, one per hinge, or
    one approximation file) and --from (deg, comma-separated; None: flat). ValueError (TargetError) naming what
    is wrong."""
    approx = None
    if len(words) == 1 and not _number(words[0]):
        approx = read_approximation(words[0], spec)
        targets = approx.angles
    else:
        targets = np.radians([cell(v, f"target {k}") for k, v in enumerate(words)])
    check_targets(spec, targets)
    from_ = np.zeros(spec.n_hinges) if not start else hinge_angles(
        [cell(v, f"--from[{k}]") for k, v in enumerate(start.split(","))], spec.n_hinges, spec.hinge_limit, "--from")
    return targets, from_, approx


def _number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def move_lines(move: TwinMove, doc: dict) -> list[str]:
    """The move's report in words (deg, s, mm): the gate, each hinge's step response, the time it took, and
    where the twin ended on an approximation's target; doc: its JSON (to_json)."""
    lines = [move.gate.text(),
             f"{'hinge':>5} {'target_deg':>10} {'final_deg':>9} {'settle_time_s':>13} {'overshoot_deg':>13} "
             f"{'ss_err_deg':>10} {'ss_err_counts':>13} {'peak_A':>6}"]
    lines += [f"{r['hinge']:>5} {r['target_deg']:>10.2f} {r['final_deg']:>9.2f} {r['settle_time_s']:>13.3f} "
              f"{r['overshoot_deg']:>13.2f} {r['steady_state_error_deg']:>10.2f} "
              f"{r['steady_state_error_counts']:>13.1f} {r['peak_current_A']:>6.2f}" for r in doc["hinges"]]
    lines.append(f"simulated {doc['simulated_s']} s in {doc['wall_s']} s wall "
                 f"({doc['real_time_factor']}x real time); settled: {doc['settled']}")
    if "msd_after_morph_mm" in doc:
        lines.append(f"on {doc['target']}: MSD where the twin ended {doc['msd_after_morph_mm']} mm "
                     f"(HD {doc['hd_after_morph_mm']} mm; the approximation's own {doc['approximation_msd_mm']} mm); "
                     f"{doc['inside_after_morph_percent']} % of the touch surface inside the target, up to "
                     f"{doc['inside_depth_after_morph_mm']} mm deep")
    elif "target_note" in doc:
        lines.append(f"no MSD: {doc['target_note']}")
    return lines


def simulate_move(twin: Twin, gains, start, targets, max_time: float, hold: bool = False,
                  approx: Approximation | None = None, approx_path: str = "") -> TwinMove:
    """Gate the move from start to targets (rad) on the twin (gains: PidGains per hinge), settling within
    max_time s; the gate's simulated move, or with hold the whole max_time s from start. For an approximation
    (read from approx_path), the MSD, HD and the touch surface inside its target where the twin ended.
    ValueError (the gate's refusal) where the gate refused before simulating."""
    spec = twin.spec
    gate = check_move(spec, start, targets, gains, settle_limit=max_time, twin=twin)
    if gate.prediction is None:
        raise ValueError(gate.refusal())
    trace = gate.prediction
    if hold:
        twin.reset(start)
        trace = twin.move_to(targets, max_time=max_time, stop_when_settled=False)
    on_target = {} if approx is None else _on_target(spec, approx, trace, approx_path)
    return TwinMove(np.asarray(start, float), gate, trace, move_report(spec, trace), on_target)


def _on_target(spec, approx: Approximation, trace: Trace, path: str) -> dict:
    """The MSD, HD (mm) and the share of the touch surface inside the target (match_json) where the twin ended, on
    the approximation's target (a shape's name, or a mesh path relative to the approximation file or the working
    folder); a note where the target cannot be read."""
    target = approx.target
    out = {"target": target, "approximation_msd_mm": None if approx.msd is None else round(approx.msd * 1e3, 3)}
    if target is None:
        return {**out, "target_note": f"{path} names no target"}
    if target in shape_names():
        mesh = load_shape(target)
    else:
        mesh_path = next((p for p in (Path(path).parent / target, Path(target)) if p.is_file()), None)
        if mesh_path is None:
            return {**out, "target_note": f"its target {target!r} is neither a shape nor a mesh file found here"}
        mesh = load_mesh(mesh_path)
    return {**out, **match_json(match(spec, mesh, approx.root_pose, trace.true_angle[-1], approx.widths),
                                "_after_morph")}
