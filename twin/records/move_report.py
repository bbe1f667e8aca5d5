"""The move report record: a move's step response, hinge by hinge."""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class MoveReport:
    """One move of the twin, per hinge (arrays of n_hinges), SI; NaN where not defined (never settled).
    twin.sim.response.move_report measures it; twin.formats.move_report.move_rows writes it in deg."""

    target: np.ndarray  # rad, the target
    final: np.ndarray  # rad, the true angle at the end
    settle_time: np.ndarray  # s after the command (the firmware's settle band, in counts)
    overshoot: np.ndarray  # rad, past the target (true angle)
    steady_state_error: np.ndarray  # rad, target - final value (true angle)
    steady_state_error_counts: np.ndarray  # counts, the same from the encoder
    peak_current: np.ndarray  # A, the largest |current|

    @property
    def settled(self) -> bool:
        """Whether every hinge settled."""
        return bool(np.all(np.isfinite(self.settle_time)))

    @property
    def slowest(self) -> float:
        """s: the move's settle time (the slowest hinge's), NaN where any did not settle."""
        return float(np.max(self.settle_time)) if len(self.settle_time) else float("nan")
