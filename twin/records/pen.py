"""The pen samples record: a pen file's samples to redirect (twin.formats.pen), in SI."""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class PenSamples:
    """Pen samples, one per row of the file: the pen tip in the world and, where tracked, the device's pose."""

    position: np.ndarray  # (N, 3) m, the pen tip
    orientation: np.ndarray  # (N, 4) unit quaternions w, x, y, z, the pen
    device_pose: np.ndarray | None  # (N, 4, 4) homogeneous, m, the tracked device's; None where the file has none
    columns: dict[str, list[str]]  # every column of the file as read (text), passed through to the redirected file
