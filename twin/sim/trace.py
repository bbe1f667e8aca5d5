"""A twin's recording of the hinges at the firmware rate (SI), and consecutive ones joined."""

from __future__ import annotations

import dataclasses

import numpy as np

from controllers.encoder import angle_from_counts
from twin.device.spec import DeviceSpec
from twin.formats.trace import TWIN_COLUMNS, TraceWriter
from twin.paths import replacing


@dataclasses.dataclass
class Trace:
    """A recorded run at the firmware rate; arrays are (ticks, hinges), SI units."""

    time: np.ndarray  # s, start of each tick
    target: np.ndarray  # rad
    target_counts: np.ndarray  # counts
    angle: np.ndarray  # rad, true hinge angle
    counts: np.ndarray  # counts, as the firmware read them
    duty: np.ndarray  # [-1, 1]
    current: np.ndarray  # A, winding current
    torque: np.ndarray  # N*m at the output shaft
    wall_time: float = float("nan")  # s the simulation took

    @property
    def duration(self) -> float:
        return float(len(self.time) * (self.time[1] - self.time[0])) if len(self.time) > 1 else 0.0

    @property
    def real_time_factor(self) -> float:
        return self.duration / self.wall_time

    def write_csv(self, path, spec: DeviceSpec) -> None:
        """The trace as a trace CSV (twin.formats.trace, docs/formats.md): the device's columns (angle_deg the
        encoder's angle, as a device reports it) and the twin's own (true angle, target counts, torque)."""
        encoder = np.degrees(angle_from_counts(spec, self.counts))
        with replacing(path) as tmp, TraceWriter(tmp, self.angle.shape[1], extra=TWIN_COLUMNS) as w:
            for i in range(len(self.time)):
                w.write(self.time[i], target_deg=np.degrees(self.target[i]), angle_deg=encoder[i],
                        counts=self.counts[i], duty=self.duty[i], current_A=self.current[i],
                        true_angle_deg=np.degrees(self.angle[i]), target_counts=self.target_counts[i],
                        torque_Nm=self.torque[i])


def join_traces(traces: list[Trace]) -> Trace:
    """Consecutive traces of one twin as one (their wall times summed)."""
    cat = {f.name: np.concatenate([getattr(t, f.name) for t in traces])
           for f in dataclasses.fields(Trace) if f.name != "wall_time"}
    return Trace(**cat, wall_time=float(sum(t.wall_time for t in traces)))

