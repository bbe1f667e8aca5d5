"""The physical proxy's sample points: where the approximation and the metrics look at the device.

Points are laid out in each flap's touch-surface frame (from `kinematics.flap_frames`):
x across the flap (its width, the row direction), y along the hinge axis, z = 0 on
the touch surface. The usable surface (spec.usable_depth) is taken as centred on
the frame's origin in y (assumption: the paper does not say where the motor strip
sits, and the MJCF's flaps are centred there too).

- flap points: a grid no coarser than 5 mm over the whole flap (the paper's spacing);
- edge points: the same y samples along the flap's two width-bounding edges, the
  lines x = +-w/2 parallel to the hinge axis, i.e. the motor axes;
- metric points: a grid no coarser than 2 mm, for MSD and HD.

Local x is stored as a fraction of the flap's width (u in [-1/2, 1/2]), so the same
layout serves any flap widths. All lengths in metres.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from twin.device.spec import DeviceSpec

SAMPLE_SPACING = 0.005  # m, the paper's flap and edge sample grid
METRIC_SPACING = 0.002  # m, touch-surface samples for MSD and HD


@dataclasses.dataclass(frozen=True)
class Layout:
    """Sample layout on one flap: u (fraction of width along x) and y (m) of each point, (M,) each."""

    u: np.ndarray
    y: np.ndarray

    def local(self, width) -> np.ndarray:
        """Points in the flap's frame for a flap of this width, m: (M, 3), or (n, M, 3) for n widths (m)."""
        u = self.u * np.asarray(width, float)[..., None]
        return np.stack([u, np.broadcast_to(self.y, u.shape), np.zeros(u.shape)], axis=-1)


def _count(length: float, spacing: float) -> int:
    """Samples across `length` so that neighbours are at most `spacing` apart (ends included)."""
    return max(2, math.ceil(length / spacing - 1e-9) + 1)


def grid_layout(spec: DeviceSpec, spacing: float, width: float | None = None) -> Layout:
    """A grid on a flap with neighbours at most `spacing` m apart for a flap of `width` m (default the pitch)."""
    u = np.linspace(-0.5, 0.5, _count(spec.flap_pitch if width is None else width, spacing))
    y = np.linspace(-spec.usable_depth / 2, spec.usable_depth / 2, _count(spec.usable_depth, spacing))
    uu, yy = np.meshgrid(u, y, indexing="ij")
    return Layout(uu.ravel(), yy.ravel())


def edge_layout(spec: DeviceSpec, side: int, spacing: float = SAMPLE_SPACING) -> Layout:
    """Points along one width-bounding edge of a flap: side +1 is x = +w/2, -1 is x = -w/2."""
    y = np.linspace(-spec.usable_depth / 2, spec.usable_depth / 2, _count(spec.usable_depth, spacing))
    return Layout(np.full_like(y, 0.5 * side), y)


def world_points(frames: np.ndarray, widths: np.ndarray, layout: Layout, flaps=None) -> np.ndarray:
    """Layout points of the given flaps (default all) in the world, shape (n, M, 3), m."""
    flaps = range(len(frames)) if flaps is None else flaps
    return np.stack([layout.local(widths[i]) @ frames[i, :3, :3].T + frames[i, :3, 3] for i in flaps])


def touch_surface_points(spec: DeviceSpec, frames: np.ndarray, widths=None,
                         spacing: float = METRIC_SPACING) -> np.ndarray:
    """Dense samples (N, 3), m, of the whole touch surface for the given flap frames."""
    widths = np.full(spec.n_flaps, spec.flap_pitch) if widths is None else np.asarray(widths, float)
    return np.vstack([world_points(frames, widths, grid_layout(spec, spacing, w), [i])[0]
                      for i, w in enumerate(widths)])
