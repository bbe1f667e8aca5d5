"""The approximation record: where the device's anchor goes and how its hinges and flaps are set for a target."""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass
class Approximation:
    """One approximation's result (MorphPatch's, or CBS's end state), SI. The approximation JSON
    (twin.formats.target) is its file form; twin.morphpatch.approximation computes and measures it."""

    root_pose: np.ndarray  # 4x4, the anchor in the world (m)
    angles: np.ndarray  # rad, (n_hinges,)
    widths: np.ndarray  # m, (n_flaps,)
    time: float  # s, wall time of the approximation itself
    variant: str
    msd: float | None = None  # m, once measured
    hd: float | None = None  # m
    inside: float | None = None  # share (0..1) of the touch surface inside the target, once measured
    depth: float | None = None  # m, the deepest of it
    rests: bool | None = None  # ours: whether the search found a pose resting on the target from outside
    target: str | None = None  # the target's name (a shape, or a mesh path) where a file names it
