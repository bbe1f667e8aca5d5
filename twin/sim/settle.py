"""The settle rule, applied as samples come: a move is settled once every hinge's encoder counts have stayed
within the firmware's settle band (spec.settle_band counts) of its target for spec.settle_hold s; its settle
time is when they entered the band to stay (docs/device.md, "Settle time").

One home for the rule as it runs: the twin's stop (twin.sim.kernels.firmware_loop: `samples_in_band` tick by
tick, until `hold_samples` ticks in a row) and the device's watch (twin.hil.mirror: `SettleTracker`, frame by frame) both apply it here; a whole
recording's settle time is twin.sim.response.settle_time, the same rule looking back (the samples in the band
from the last entry to the record's end), which a tracker fed the same samples agrees with.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def in_band(target, counts, band) -> bool:
    """Whether every hinge's counts are within `band` counts of its target (counts)."""
    for h in range(counts.shape[0]):
        if abs(target[h] - counts[h]) > band:
            return False
    return True


@numba.njit(cache=True)
def samples_in_band(target, counts, band, before: int) -> int:
    """The rule a sample on: how many samples in a row, this one included, every hinge's counts have been within
    `band` counts of its target (0: this one is outside); `before` is the count at the sample before."""
    return before + 1 if in_band(target, counts, band) else 0


def hold_samples(hold: float, period: float) -> int:
    """How many samples in a row in the band settle a move when each stands for `period` s: the least k with
    k * period >= hold s, what SettleTracker asks of samples at that period (a float's last bit aside)."""
    return max(1, math.ceil(hold / period - 1e-9))


class SettleTracker:
    """The settle rule over samples fed one at a time (time s, counts per hinge), each standing for `period` s:
    `feed` gives the settle time (s, the time the samples entered the band to stay) once they have stayed
    `hold` s, else None."""

    def __init__(self, target_counts, band: int, hold: float, period: float):
        self.target = np.asarray(target_counts, np.int64)
        self.band, self.hold, self.period = band, hold, period
        self.since = math.nan  # s: when the samples last entered the band (NaN: outside it)

    def feed(self, t: float, counts) -> float | None:
        if not in_band(self.target, np.asarray(counts, np.int64), self.band):
            self.since = math.nan
            return None
        if math.isnan(self.since):
            self.since = t
        return self.since if t - self.since + self.period >= self.hold else None
