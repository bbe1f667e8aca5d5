"""The profile record: one researcher's device as the twin knows it, read and written whole (twin.formats.profile)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from twin.records.calibration import Calibration, Estimate
from twin.records.ranges import Ranges

NO_PROFILE = "spec defaults"  # how reports name the absence of a profile


@dataclasses.dataclass(frozen=True)
class Holding:
    """What a release under gravity measured (`vrscroll holding`, twin.hil.holding), SI."""

    port: str  # the device it was measured on
    releases: int  # how many releases the fit took
    parameters: dict[str, Estimate]  # the gearbox's back-driven efficiency


@dataclasses.dataclass(frozen=True)
class Profile:
    """The device the commands simulate, gate and talk to: a profile folder's, or the spec's defaults (name None).

    The record layer imports neither the device nor the firmware's host build (its siblings and the layer above):
    `spec` and each of `hinges` is a twin.device.spec.DeviceSpec, each of `gains` a controllers.pid.PidGains.
    `hinges`, the per-hinge plants, is the spec with each hinge's own calibrated values (Calibration.hinges); the
    one home that makes them is twin.formats.profile (`read_profile`, `updated`), so the record and its file agree."""

    name: str | None
    folder: Path | None
    spec: object  # DeviceSpec: the profile's spec.toml (the spec's defaults where it changes nothing)
    sources: dict[str, str]  # spec field -> where its value came from ("calibrated from ...", a datasheet)
    gains: list  # PidGains per hinge
    gains_from: str  # where the gains came from: the profile's gains.json or the spec
    mount: str  # how the device is held (twin.device.mount.MOUNTS): the twin is held so too
    calibration: Calibration | None = None  # profile.json's "calibration", if the profile was calibrated
    hinges: list | None = None  # DeviceSpec per hinge where calibration fitted per-hinge values, else None
    holding: Holding | None = None  # profile.json's "holding", if a release was measured (`vrscroll holding`)

    @property
    def label(self) -> str:
        """How every report names it: the profile's name, or "spec defaults"."""
        return self.name or NO_PROFILE

    def ranges(self, uncalibrated: Ranges | None = None) -> Ranges | None:
        """What tuning covers, SI: the twin's values that reproduce the calibration's runs (Estimate.runs_range),
        each hinge's own where calibration fitted per-hinge values. Where calibration fitted no shared value (none
        ran, or it fitted each hinge's only) the shared values' are `uncalibrated`'s (twin.device.variation's
        spread or tolerance about the spec), or None where that is None."""
        rows = self.calibration.hinges if self.calibration else None
        own = tuple({p: e.runs_range for p, e in row.items()} for row in rows) if rows else None
        if self.calibration and self.calibration.parameters:
            return Ranges({p: e.runs_range for p, e in self.calibration.parameters.items()}, "the calibrated intervals",
                          own, calibrated=True)
        return None if uncalibrated is None else dataclasses.replace(uncalibrated, hinges=own)
