"""How well the proxy matches the target, on the exact mesh (never the grid).

The proxy's touch surface (all flaps, usable depth) is sampled on a grid no coarser
than 2 mm (`proxy.touch_surface_points`); each sample's signed distance to the target's
triangles is exact (libigl's, through an AABB tree), negative inside the target.

- MSD, mean surface distance: the mean of those distances' sizes;
- HD, one-sided Hausdorff distance, proxy -> target: the largest of them;
- inside: the share (0..1) of the samples deeper in the target than INSIDE_TOLERANCE, and
  depth, the deepest sample's depth (0 where none is inside): a row of flat flaps cannot follow
  every surface, and where it cannot, part of it may lie in the virtual object (a torus's tube, a
  cup's wall) rather than on it. The sign is libigl's pseudonormal test, exact on a watertight mesh.

Metres here; the command line and reports turn them into mm and percent.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import trimesh

from twin.device.kinematics import flap_frames
from twin.device.spec import DeviceSpec
from twin.morphpatch.fields import exact_closest_faces, exact_signed_distance
from twin.morphpatch.sampling import METRIC_SPACING, touch_surface_points


INSIDE_TOLERANCE = 0.5e-3  # m: a sample deeper than this in the target counts as inside it


class Match(NamedTuple):
    """How well a proxy matches its target (m; inside a share 0..1)."""

    msd: float
    hd: float
    inside: float
    depth: float


def point_distances(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """Exact signed distance (N,) m from points (N, 3) m to the mesh's surface, negative inside it."""
    return exact_signed_distance(mesh, points)[0]


def proxy_distances(spec: DeviceSpec, mesh: trimesh.Trimesh, root_pose, angles, widths=None,
                    spacing: float = METRIC_SPACING) -> np.ndarray:
    """Signed distance (N,) m from each touch-surface sample of the proxy to the target surface.

    root_pose: 4x4 anchor pose in the world (m); angles: hinge angles (n_hinges,) rad;
    widths: flap widths (n_flaps,) m, the pitch if None.
    """
    frames = flap_frames(spec, angles, root_pose, widths)
    return point_distances(mesh, touch_surface_points(spec, frames, widths, spacing))


def match(spec: DeviceSpec, mesh: trimesh.Trimesh, root_pose, angles, widths=None,
          spacing: float = METRIC_SPACING) -> Match:
    """MSD, HD, the share inside and its depth (module docstring) of the proxy with this root pose, hinge
    angles (rad) and widths (m)."""
    d = proxy_distances(spec, mesh, root_pose, angles, widths, spacing)
    return Match(float(np.abs(d).mean()), float(np.abs(d).max()), float(np.mean(d < -INSIDE_TOLERANCE)),
                 max(0.0, float(-d.min())))


def inside_faces(spec: DeviceSpec, mesh: trimesh.Trimesh, root_pose, angles, widths=None,
                 shown: trimesh.Trimesh | None = None, spacing: float = METRIC_SPACING) -> np.ndarray:
    """Which faces (n_faces,) bool of `shown` (the mesh itself by default, or a finer copy of it for a picture)
    the proxy lies inside the target under: the face nearest each touch-surface sample deeper in the mesh than
    INSIDE_TOLERANCE (the depth on the mesh itself, exact): the part of the target the touch surface is in."""
    frames = flap_frames(spec, angles, root_pose, widths)
    points = touch_surface_points(spec, frames, widths, spacing)
    shown = mesh if shown is None else shown
    d, nearest = exact_closest_faces(shown, points)
    if shown is not mesh:
        d = point_distances(mesh, points)
    out = np.zeros(len(shown.faces), bool)
    out[nearest[d < -INSIDE_TOLERANCE]] = True
    return out


def msd_hd(spec: DeviceSpec, mesh: trimesh.Trimesh, root_pose, angles, widths=None,
           spacing: float = METRIC_SPACING) -> tuple[float, float]:
    """(MSD, HD) in metres (see `match`)."""
    return match(spec, mesh, root_pose, angles, widths, spacing)[:2]


def match_json(m: Match, suffix: str = "") -> dict:
    """A Match for JSON: msd{suffix}_mm, hd{suffix}_mm, inside{suffix}_percent, inside_depth{suffix}_mm."""
    return {f"msd{suffix}_mm": round(m.msd * 1e3, 3), f"hd{suffix}_mm": round(m.hd * 1e3, 3),
            f"inside{suffix}_percent": round(m.inside * 100, 2), f"inside_depth{suffix}_mm": round(m.depth * 1e3, 3)}


def inside_text(m: Match) -> str:
    """One line on how much of the touch surface lies inside the target, and how deep."""
    if m.inside == 0.0:
        return "none of the touch surface inside the target"
    return f"{m.inside:.0%} of the touch surface inside the target, up to {m.depth * 1e3:.1f} mm deep"
