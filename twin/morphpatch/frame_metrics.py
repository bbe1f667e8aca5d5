"""Surface metrics cheap enough for every VR frame, read from the target's SDF grid.

The exact metrics (`surface_metrics.msd_hd`, on the mesh) take 4-50 ms and the exact
redirection field (`redirection.build_field`) about 100 ms: too slow for a 90 Hz loop.
These estimates use the proxy's 5 mm sample grid and the SDF grid (one compiled lookup,
tens of microseconds):

- MSD estimate: the mean |SDF| at the samples (the grid's error against the exact
  distance is ~0.01 mm on average, see docs/approximation.md);
- share within the perception thresholds, estimated: a sample counts when |SDF| is within
  the positional threshold and the angle between the flap's normal and the SDF gradient
  (the target's normal at the nearest surface point) within the rotational one. The
  redirection proper looks along the proxy's normal and blurs the field, so the exact share
  (reported after a lock) can differ; the nearest-point distance is never longer than the
  distance along the normal, so this estimate leans optimistic on offsets.

SI units (m, rad).
"""

from __future__ import annotations

import numpy as np

from twin.device.kinematics import flap_frames
from twin.device.spec import DeviceSpec
from twin.morphpatch.fields import Fields
from twin.morphpatch.sampling import SAMPLE_SPACING, Layout, grid_layout
from twin.perception.thresholds import Thresholds


def frame_estimates(spec: DeviceSpec, fields: Fields, thresholds: Thresholds, root_pose, angles, widths,
                    layout: Layout | None = None) -> tuple[float, float]:
    """(MSD estimate m, share of samples within the thresholds 0..1) of a proxy on the SDF grid.

    layout: `grid_layout(spec, SAMPLE_SPACING)`, made once by a caller that estimates every frame (~20 us each).
    The flaps' points are placed in one broadcast rather than flap by flap (~0.1 ms less per frame)."""
    widths = np.asarray(widths, float)
    frames = flap_frames(spec, angles, root_pose, widths)  # (n, 4, 4)
    layout = layout or grid_layout(spec, SAMPLE_SPACING)
    x = layout.u[None, :, None] * widths[:, None, None]  # (n, M, 1), along each flap's x
    points = x * frames[:, None, :3, 0] + layout.y[None, :, None] * frames[:, None, :3, 1] + frames[:, None, :3, 3]
    normals = np.broadcast_to(frames[:, None, :3, 2], points.shape).reshape(-1, 3)
    value, grad = fields.sdf_grad(points.reshape(-1, 3))
    size = np.maximum(np.linalg.norm(grad, axis=1), 1e-12)
    cos = np.einsum("ij,ij->i", grad, normals) / size
    within = (np.abs(value) <= thresholds.position) & (cos >= np.cos(thresholds.rotation))
    return float(np.abs(value).mean()), float(within.mean())
