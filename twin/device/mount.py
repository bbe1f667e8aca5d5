"""How the device is held while it runs (docs/device.md "Mounts"): the twin is held the same way.

- hanging: the root flap held (in a hand, or clamped) with the hinges' axes horizontal and nothing under the
  other flaps: gravity loads every hinge, and unpowered flaps sag (today's twin, and a profile that does not say);
- flat: lying on a table, the root flap resting on it: the other flaps rest on the table and cannot fold
  below it (a MuJoCo contact in the twin); gravity presses them down, so a zero confirmed at power-on is flat;
- stand: the root flap clamped in a stand with the hinges' axes vertical (the device on its edge): gravity lies
  along the axes and loads no hinge, so nothing sags and every hinge is free both ways.
"""

from __future__ import annotations

from twin.device.spec import DeviceSpec

MOUNTS = ("hanging", "flat", "stand")
DEFAULT_MOUNT = "hanging"  # what the twin always was, and a profile that does not say
TABLE_GAP = 1e-4  # m between the flat device's underside and the table under it


def check_mount(mount: str, where: str = "mount") -> str:
    """mount, if it is one of MOUNTS; else ValueError naming them."""
    if mount not in MOUNTS:
        raise ValueError(f"{where}: expected one of {', '.join(MOUNTS)}, not {mount!r}")
    return mount


def table_height(spec: DeviceSpec) -> float:
    """The table's top under a device lying flat, m in the device frame (z of the touch surface's normal, the
    root flap's touch surface at 0): the flat device's underside, less TABLE_GAP."""
    return -(spec.thickness + TABLE_GAP)
