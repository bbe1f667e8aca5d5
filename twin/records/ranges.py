"""The ranges record: the plants a device may be, as intervals of its plant parameters (SI)."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class Ranges:
    """Each plant parameter's interval, SI (the spec field's unit), and where a hinge has its own values (a per-hinge
    calibration) its own intervals. Made by twin.device.variation (the spread about the spec, the tuner's
    tolerance) and twin.records.profile.Profile.ranges (what calibration left open); the plants they span are
    twin.device.variation.corners'. `what` says which in words, for reports."""

    shared: dict[str, tuple[float, float]]  # spec field -> (low, high), SI
    what: str  # how a report names them: "the calibrated intervals", "the spread about the spec", ...
    hinges: tuple[dict[str, tuple[float, float]], ...] | None = None  # per hinge, its own values' (low, high) SI
    calibrated: bool = False  # what calibration left open (else an assumption about an uncalibrated device)
