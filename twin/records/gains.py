"""The gains record: a gains file's content (twin.formats.gains), read and written whole."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class Gains:
    """One PID gain set per hinge, in the firmware's units, and what they were made for.

    The record layer imports neither the firmware's host build nor the device (the layers above): each of `hinges`
    is a controllers.pid.PidGains (duty per count, per count*s, per count/s; Hz; counts)."""

    hinges: list  # PidGains per hinge
    meta: dict = dataclasses.field(default_factory=dict)  # where they came from, what they were tuned for (JSON values)
