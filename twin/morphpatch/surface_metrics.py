"""How well the proxy matches the target, on the exact mesh (never the grid).

The proxy's touch surface (all flaps, usable depth) is sampled on a grid no coarser
than 2 mm (`proxy.touch_surface_points`); each sample's unsigned distance to the
target's triangles is exact (libigl's point-to-mesh distance through an AABB tree).

- MSD, mean surface distance: the mean of those distances;
- HD, one-sided Hausdorff distance, proxy -> target: the largest of them.

Metres here; the command line and reports turn them into mm.
"""

from __future__ import annotations

import igl
import numpy as np
import trimesh

from twin.device.kinematics import flap_frames
from twin.device.spec import DeviceSpec
from twin.morphpatch.sampling import METRIC_SPACING, touch_surface_points


def point_distances(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """Exact unsigned distance (N,) m from points (N, 3) m to the mesh's surface."""
    d2, _, _ = igl.point_mesh_squared_distance(np.ascontiguousarray(points, dtype=np.float64),
                                               np.ascontiguousarray(mesh.vertices, dtype=np.float64),
                                               np.ascontiguousarray(mesh.faces, dtype=np.int64))
    return np.sqrt(d2)


def proxy_distances(spec: DeviceSpec, mesh: trimesh.Trimesh, root_pose, angles, widths=None,
                    spacing: float = METRIC_SPACING) -> np.ndarray:
    """Distance (N,) m from each touch-surface sample of the proxy to the target surface.

    root_pose: 4x4 anchor pose in the world (m); angles: hinge angles (n_hinges,) rad;
    widths: flap widths (n_flaps,) m, the pitch if None.
    """
    frames = flap_frames(spec, angles, root_pose, widths)
    return point_distances(mesh, touch_surface_points(spec, frames, widths, spacing))


def msd_hd(spec: DeviceSpec, mesh: trimesh.Trimesh, root_pose, angles, widths=None,
           spacing: float = METRIC_SPACING) -> tuple[float, float]:
    """(MSD, HD) in metres of the proxy with this root pose, hinge angles (rad) and widths (m)."""
    d = proxy_distances(spec, mesh, root_pose, angles, widths, spacing)
    return float(d.mean()), float(d.max())
