"""The calibration record: what calibration leaves known about a device's plant, parameter by parameter."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass
class Estimate:
    """One parameter after calibration, SI (the spec field's unit)."""

    value: float  # fitted, or exactly the prior when the runs do not show it
    prior: float  # the value calibration started from (the profile's or the spec's)
    low: float  # left open: the 95 % interval when identifiable, with the prior range when not
    high: float
    identifiable: bool  # fitted, and its interval within x(1 -+ MAX_HALFWIDTH)
    note: str  # why it is or is not fitted, in words
    # the twin's values that reproduce the runs, the bounded parameters at the profile's values (what tuning
    # covers): low .. high less what the bounded ones could move it and the prior range kept open with it
    runs_low: float | None = None  # None: low .. high
    runs_high: float | None = None

    @property
    def fitted(self) -> bool:
        """Whether calibration moved it from its prior (a parameter left at its prior is exactly its prior)."""
        return self.value != self.prior

    @property
    def runs_range(self) -> tuple[float, float]:
        """(low, high) SI of the twin's values that reproduce the runs (runs_low .. runs_high)."""
        return (self.low if self.runs_low is None else self.runs_low,
                self.high if self.runs_high is None else self.runs_high)

    def to_json(self) -> dict:
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}


@dataclasses.dataclass(frozen=True)
class Calibration:
    """A device profile's calibration (profile.json's "calibration", twin.formats.profile), SI."""

    runs: list[str]  # the run folders it was fitted to
    parameters: dict[str, Estimate]  # the shared values
    hinges: list[dict[str, Estimate]] | None = None  # per hinge its own values, each about the shared one
