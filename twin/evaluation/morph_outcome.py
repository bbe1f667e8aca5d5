"""What a morph to an approximation comes to on the twin: the gate, the move's report, where the twin came to
rest, how well that pose fits the target and how much of its mismatch the pen redirection covers within the
perception thresholds. One function for `vrscroll demo`, Table 1 and the design sweeps (their twin columns)."""

from __future__ import annotations

import dataclasses

import numpy as np

from twin.device.spec import DeviceSpec
from twin.morphpatch.fields import Fields
from twin.morphpatch.redirection import build_field, threshold_summary
from twin.morphpatch.surface_metrics import Match, match
from twin.records.approximation import Approximation
from twin.records.move_report import MoveReport
from twin.sim.gate import GateReport, check_move
from twin.sim.response import move_report
from twin.sim.twin import Twin


@dataclasses.dataclass(frozen=True)
class MorphOutcome:
    """A morph from flat to an approximation's hinge angles on the twin, SI."""

    gate: GateReport  # range, collisions, settling, current; its prediction the simulated move (None: refused)
    report: MoveReport | None  # the move per hinge (None where the gate refused before simulating)
    reached: np.ndarray  # rad, the hinge angles the twin came to rest at (flat where the gate refused the move)
    end: Match  # the reached pose on the target (MSD, HD m, share inside, its depth m)
    redirection: dict  # the pen redirection over the reached pose against the thresholds (threshold_summary)

    @property
    def settle_time(self) -> float:
        """s: the move's settle time (the slowest hinge's); NaN where a hinge did not settle or none moved."""
        return float("nan") if self.report is None else self.report.slowest


def morph_outcome(spec: DeviceSpec, mesh, fields: Fields, approx: Approximation, twin: Twin,
                  gains=None) -> MorphOutcome:
    """Gate and simulate the morph from flat to approx's angles on `twin` (held as it is: its mount, or the root
    pose a caller set), then measure where it came to rest against the target (mesh, its fields)."""
    gate = check_move(spec, np.zeros(spec.n_hinges), approx.angles, gains, twin=twin)
    reached = twin.angles  # after the gate's move and hold; flat where it refused: the device does not move
    field = build_field(spec, approx.root_pose, reached, approx.widths, mesh, fields)
    return MorphOutcome(gate, None if gate.prediction is None else move_report(spec, gate.prediction), reached,
                        match(spec, mesh, approx.root_pose, reached, approx.widths), threshold_summary(field))
