"""The trace record: one recording of the hinges, the twin's and the device's alike."""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Trace:
    """A recording at the firmware (or telemetry) rate, SI: `time` (rows,) and per hinge (rows, hinges) the
    rest. `angle` is the encoder's angle (counts x rad per count), what a device reports and what the firmware's
    settle band is about, so a device's and a twin's compare like with like; `true_angle` is the flap's true
    angle where it is known (a twin's), None for a device's. The twin's own columns are None in a device's trace."""

    time: np.ndarray  # s
    target: np.ndarray  # rad, the target the firmware held
    angle: np.ndarray  # rad, the encoder's angle
    counts: np.ndarray  # encoder counts (whole numbers)
    duty: np.ndarray  # the commanded duty, -1 .. 1
    current: np.ndarray  # A, the winding current
    true_angle: np.ndarray | None = None  # rad, the flap's true angle (a twin's)
    target_counts: np.ndarray | None = None  # the target in counts (a twin's)
    torque: np.ndarray | None = None  # N*m at the output shaft (a twin's)
    decay: np.ndarray | None = None  # the decay the drive applied, 0 coast, 1 brake (a twin's)
    wall_time: float = float("nan")  # s the simulation took (a twin's)

    @property
    def n_hinges(self) -> int:
        return self.angle.shape[1]

    @property
    def duration(self) -> float:
        """s: the rows times their period (0 for fewer than two rows)."""
        return float(len(self.time) * (self.time[1] - self.time[0])) if len(self.time) > 1 else 0.0

    @property
    def real_time_factor(self) -> float:
        return self.duration / self.wall_time

    def until(self, end: float) -> "Trace":
        """The rows at or before `end` s."""
        sel = self.time <= end + 1e-9
        return dataclasses.replace(self, **{f: getattr(self, f)[sel] for f in _ROWS if getattr(self, f) is not None})


_ROWS = tuple(f.name for f in dataclasses.fields(Trace) if f.name != "wall_time")


def joined(traces: list[Trace]) -> Trace:
    """Consecutive traces of one source as one (their wall times summed); a column is kept where every trace has it."""
    cat = {f: None if any(getattr(t, f) is None for t in traces) else np.concatenate([getattr(t, f) for t in traces])
           for f in _ROWS}
    return Trace(**cat, wall_time=float(sum(t.wall_time for t in traces)))
