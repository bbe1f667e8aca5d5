"""MorphPatch's surface approximation: root pose, hinge angles and flap widths for a target.

The pipeline, in the paper's order (its figure; §3.2):

1. snap: the device moves along its anchor direction (the device's -z from the
   anchor) until the anchor touches the surface (S = 0 along that line; if the line
   misses the target, the anchor goes to its closest surface point instead);
2. root rotation about the hinge axis y (the paper's "yaw", its Unity axis Z): the
   root flap's SDF gradients, in the root frame, projected onto its x-z plane; the
   root turns by their mean's angle from its normal z;
3. root rotation about the row axis x (the paper's "roll", X): the same with all
   flaps' gradients projected onto the y-z plane;
4. root rotation about the normal z (the paper's "pitch", Y): all flaps' gradients
   projected onto the x-y plane; angles doubled so opposite gradients agree, their
   principal direction found, and the row (x) turned onto it, so the hinge axes lie
   along the surface's edges, 90 degrees from it (skipped when the in-plane
   gradients have no clear direction);
5. HCEVF root translation (variant "full"): the mean of the non-zero HCEVF vectors
   at the edge points of all flaps, its component along the surface (the root's x-y
   plane), and then the snap of step 1 again from there, so the anchor slides along the
   target and ends on it (the paper's full 3-D move left it up to 8.5 mm inside a
   wave, and 19 of 50 starts more than 5 mm inside the ellipsoid);
6. hinge angles, from the root outward: each flap's gradients projected onto its
   x-z plane, the hinge turned by the angle of their mean from the flap's normal
   (a few passes per flap), always clipped inside +-spec.hinge_limit;
7. HCEVF flap widths (variant "full"), from the root outward: the non-zero HCEVF
   vectors along the flap's moving edges, projected onto the flap's plane, their
   mean's component along the flap's outward width direction u_k (away from the
   root) added to its width. The edge a width change moves is the outer one, so
   that is where a flap samples; the root flap grows both ways and samples both
   edges, each with its own outward u. Widths are clipped to WIDTH_RANGE x pitch.

Where the paper averages angles we take the angle of the mean gradient (the same
for nearby gradients, and immune to wrap-around). Variant "no_hcevf" skips 5 and 7.
Variant "refined" (ours, beyond the paper) is "full" followed by a bounded local
least-squares refinement of the root pose and hinge angles (twin.morphpatch.refinement).
SI units throughout (m, rad, s); `Approximation.to_json` gives mm and degrees.
"""

from __future__ import annotations

import dataclasses
import math
import time
from functools import lru_cache

import numpy as np
from scipy.spatial.transform import Rotation

from twin.device.kinematics import bend, flap_frames, hinge_axis_sign, outer_flap, pose_matrix, widen
from twin.device.spec import DeviceSpec, load_spec
from twin.morphpatch.fields import Fields
from twin.morphpatch.refinement import refine
from twin.morphpatch.sampling import SAMPLE_SPACING, edge_layout, grid_layout, world_points
from twin.morphpatch.surface_metrics import msd_hd

VARIANTS = ("full", "no_hcevf", "refined")
SNAP_REACH = 0.25  # m, how far along +-z a snap looks for the surface (here, and CBS's press along its normal)
ROOT_PASSES = 2  # passes of each root rotation step
HINGE_PASSES = 3  # passes per hinge
HINGE_TOLERANCE = 1e-3  # rad: a hinge pass that changes the angle less than this ends the hinge
PRINCIPAL_MIN = 0.2  # the in-plane gradients' anisotropy (0..1) below which step 4 does nothing
PRINCIPAL_MIN_TILT = math.radians(3)  # ... or their RMS tilt from the normal below which it does nothing
WIDTH_RANGE = (0.5, 1.5)  # flap widths stay within these multiples of the pitch


@dataclasses.dataclass
class Approximation:
    """Result of one approximation: SI units (m, rad, s); `to_json` converts."""

    root_pose: np.ndarray  # 4x4, the anchor in the world
    angles: np.ndarray  # rad, (n_hinges,)
    widths: np.ndarray  # m, (n_flaps,)
    time: float  # s, wall time of the approximation itself
    variant: str
    msd: float | None = None  # m, once `measured`
    hd: float | None = None  # m

    def frames(self, spec: DeviceSpec) -> np.ndarray:
        """World poses (n_flaps, 4, 4) of the flaps' touch-surface frames."""
        return flap_frames(spec, self.angles, self.root_pose, self.widths)

    def measured(self, spec: DeviceSpec, mesh) -> "Approximation":
        """A copy with MSD and HD (m) against the exact mesh (see twin.surface_metrics)."""
        msd, hd = msd_hd(spec, mesh, self.root_pose, self.angles, self.widths)
        return dataclasses.replace(self, msd=msd, hd=hd)

    def to_json(self) -> dict:
        """Plain dict with the unit in every key (mm, deg, ms)."""
        quat = Rotation.from_matrix(self.root_pose[:3, :3]).as_quat(scalar_first=True)
        mm = (lambda v: None if v is None else round(v * 1e3, 3))
        return {
            "variant": self.variant,
            "root_position_mm": [round(v, 3) for v in (self.root_pose[:3, 3] * 1e3).tolist()],
            "root_quat_wxyz": [round(v, 6) for v in quat.tolist()],
            "angles_deg": [round(v, 3) for v in np.degrees(self.angles).tolist()],
            "widths_mm": [round(v, 3) for v in (self.widths * 1e3).tolist()],
            "msd_mm": mm(self.msd),
            "hd_mm": mm(self.hd),
            "time_ms": round(self.time * 1e3, 4),
        }


    @classmethod
    def from_json(cls, d: dict) -> "Approximation":
        """The inverse of `to_json` (e.g. a file written by `vrscroll approximate --json`)."""
        try:
            position = np.asarray(d["root_position_mm"], float) / 1e3
            quat = np.asarray(d["root_quat_wxyz"], float)
            angles = np.radians(np.asarray(d["angles_deg"], float))
            widths = np.asarray(d["widths_mm"], float) / 1e3
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"not an approximation result (needs root_position_mm, root_quat_wxyz, angles_deg, "
                             f"widths_mm): {exc}") from None
        if position.shape != (3,) or quat.shape != (4,) or not np.all(np.isfinite(np.r_[position, quat, angles, widths])):
            raise ValueError("approximation result: root_position_mm needs 3 and root_quat_wxyz 4 finite numbers")
        if np.linalg.norm(quat) < 1e-6 or np.any(widths <= 0):
            raise ValueError("approximation result: zero quaternion or non-positive flap width")
        rotation = Rotation.from_quat(quat, scalar_first=True).as_matrix()
        mm = (lambda v: None if v is None else v / 1e3)
        return cls(pose_matrix(position, rotation), angles, widths, d.get("time_ms", 0.0) / 1e3,
                   d.get("variant", "full"), mm(d.get("msd_mm")), mm(d.get("hd_mm")))


def pose_from_mm_deg(values) -> np.ndarray:
    """4x4 pose from [x_mm, y_mm, z_mm, roll_deg, pitch_deg, yaw_deg] (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    values = np.asarray(values, float)
    if values.shape != (6,) or not np.all(np.isfinite(values)):
        raise ValueError(f"a start is 6 finite numbers x,y,z (mm), roll,pitch,yaw (deg); got {values.tolist()}")
    rotation = Rotation.from_euler("xyz", values[3:], degrees=True).as_matrix()
    return pose_matrix(values[:3] / 1e3, rotation)


def as_pose(start) -> np.ndarray:
    """A 4x4 pose from a 4x4 matrix or a (position (3,) m, rotation (3, 3)) pair."""
    if isinstance(start, tuple):
        return pose_matrix(*start)
    pose = np.asarray(start, float)
    if pose.shape != (4, 4):
        raise ValueError(f"a start pose is a 4x4 matrix or (position, rotation); got shape {pose.shape}")
    return pose.copy()


@dataclasses.dataclass(frozen=True)
class _Layouts:
    """Precomputed samples for one spec (device frame, flat, nominal widths)."""

    flat_frames: np.ndarray  # (n_flaps, 4, 4)
    flap: object  # proxy.Layout on one flap
    root_points: np.ndarray  # (M, 3) root flap samples
    all_points: np.ndarray  # (n_flaps*M, 3) all flaps' samples
    edge_points: np.ndarray  # (n_flaps*2*K, 3) both edges of every flap
    edges: tuple  # (layout at x = -w/2, layout at x = +w/2)
    hinge_order: tuple  # hinges from the root outward
    hinge_sign: np.ndarray  # per hinge, its axis sign
    hinge_outer: np.ndarray  # per hinge, the flap it moves
    flap_order: tuple  # flaps from the root outward


@lru_cache(maxsize=8)
def _layouts(spec: DeviceSpec) -> _Layouts:
    widths = np.full(spec.n_flaps, spec.flap_pitch)
    flat = flap_frames(spec, np.zeros(spec.n_hinges), None, widths)
    flap = grid_layout(spec, SAMPLE_SPACING)
    edges = (edge_layout(spec, -1), edge_layout(spec, +1))
    r = spec.root_flap
    right, left = list(range(r, spec.n_hinges)), list(range(r - 1, -1, -1))
    return _Layouts(
        flat_frames=flat,
        flap=flap,
        root_points=world_points(flat, widths, flap, [r])[0],
        all_points=world_points(flat, widths, flap).reshape(-1, 3),
        edge_points=np.vstack([world_points(flat, widths, e).reshape(-1, 3) for e in edges]),
        edges=edges,
        hinge_order=tuple(right + left),
        hinge_sign=hinge_axis_sign(spec),
        hinge_outer=outer_flap(spec),
        flap_order=tuple(sorted(range(spec.n_flaps), key=lambda f: abs(f - r))),
    )


def approximate(fields: Fields, start, spec: DeviceSpec | None = None, variant: str = "full") -> Approximation:
    """Approximate the target of `fields` with the device, from a start pose of its anchor.

    start: 4x4 pose, or (position (3,) m, rotation (3, 3)); hinges start flat and
    widths at the pitch. variant: one of VARIANTS. Returns root pose, hinge angles
    (rad, inside +-spec.hinge_limit), flap widths (m) and the time taken (s).
    """
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; choose from {', '.join(VARIANTS)}")
    spec = load_spec() if spec is None else spec
    t0 = time.perf_counter()
    lay = _layouts(spec)
    snapped = _snap(fields, as_pose(start))
    pose = _align_root(fields, snapped, lay)
    if variant != "no_hcevf":
        pose = _hcevf_translation(fields, lay, pose)
    angles = np.zeros(spec.n_hinges)
    widths = np.full(spec.n_flaps, spec.flap_pitch)
    frames = pose @ lay.flat_frames
    frames = _align_hinges(fields, spec, lay, frames, angles, widths)
    if variant != "no_hcevf":
        _scale_flaps(fields, spec, lay, frames, widths)
    if variant == "refined":
        local = np.stack([lay.flap.local(w) for w in widths])
        pose, angles = refine(fields, spec, local, pose, angles, widths, snapped[:3, 3])
    return Approximation(pose, angles, widths, time.perf_counter() - t0, variant)


def root_pose(fields: Fields, start, spec: DeviceSpec) -> np.ndarray:
    """Steps 1-4 only: the start snapped onto the target and the root turned to it (4x4, m)."""
    return _align_root(fields, _snap(fields, as_pose(start)), _layouts(spec))


def _hcevf_translation(fields: Fields, lay: _Layouts, pose: np.ndarray) -> np.ndarray:
    """Step 5: the pose moved by the mean HCEVF vector's component along the root's x-y plane, re-snapped."""
    rot, pos = pose[:3, :3], pose[:3, 3]
    v = fields.hcevf(lay.edge_points @ rot.T + pos)
    nonzero = np.any(v != 0.0, axis=1)
    if not nonzero.any():
        return pose
    shift = v[nonzero].mean(axis=0)
    shift -= (shift @ rot[:, 2]) * rot[:, 2]
    return _snap(fields, pose_matrix(pos + shift, rot))


def _snap(fields: Fields, pose: np.ndarray) -> np.ndarray:
    """Move the pose along its -z until the anchor is on the surface (see module docstring)."""
    anchor, down = pose[:3, 3], -pose[:3, 2]
    step = min(fields.spacing, 0.002)
    s = np.arange(-SNAP_REACH, SNAP_REACH + step / 2, step)
    values = fields.sdf_values(anchor + s[:, None] * down)
    mid = len(s) // 2  # s[mid] == 0
    inside = values <= 0.0
    if values[mid] > 0.0:  # outside: first entry ahead
        hits = np.flatnonzero(inside[mid:]) + mid
        j = hits[0] if len(hits) else None
        pair = None if j is None else (j - 1, j)
    else:  # inside: back out along +z to the last exit behind
        hits = np.flatnonzero(~inside[:mid + 1])
        j = hits[-1] if len(hits) else None
        pair = None if j is None else (j, j + 1)
    out = pose.copy()
    if pair is None:  # the line misses the target: go to the closest surface point
        p = anchor.copy()
        for _ in range(2):
            value, grad = fields.sdf_grad(p[None])
            p = p - value[0] * grad[0] / max(np.linalg.norm(grad[0]), 1e-9)
        out[:3, 3] = p
        return out
    a, b = pair
    t = s[a] + (s[b] - s[a]) * values[a] / (values[a] - values[b])
    out[:3, 3] = anchor + t * down
    return out


def _rot(axis: int, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    m = np.eye(3)
    m[i, i] = m[j, j] = c
    m[i, j], m[j, i] = -s, s
    return m


def _align_root(fields: Fields, pose: np.ndarray, lay: _Layouts) -> np.ndarray:
    """Steps 2-4: the pose turned about y, then x, then z (about the anchor)."""
    rot, pos = pose[:3, :3], pose[:3, 3]
    for _ in range(ROOT_PASSES):  # about y, root flap only
        g = rot.T @ fields.gradient_sum(lay.root_points, rot, pos)
        rot = rot @ _rot(1, math.atan2(g[0], g[2]))
    for _ in range(ROOT_PASSES):  # about x, all flaps
        g = rot.T @ fields.gradient_sum(lay.all_points, rot, pos)
        rot = rot @ _rot(0, math.atan2(-g[1], g[2]))
    g = fields.sdf_grad(lay.all_points @ rot.T + pos)[1] @ rot  # about z: principal in-plane direction
    gx, gy = g[:, 0], g[:, 1]
    power = float(np.sum(gx * gx + gy * gy))
    a, b = float(np.sum(gx * gx - gy * gy)), float(np.sum(2.0 * gx * gy))
    if power > len(g) * math.sin(PRINCIPAL_MIN_TILT) ** 2 and math.hypot(a, b) > PRINCIPAL_MIN * power:
        rot = rot @ _rot(2, 0.5 * math.atan2(b, a))
    return pose_matrix(pos, rot)


def _align_hinges(fields, spec, lay, frames, angles, widths) -> np.ndarray:
    """Step 6: hinge angles from the root outward; updates `angles` in place, returns the frames."""
    local = lay.flap.local(spec.flap_pitch)
    limit = spec.hinge_limit
    for h in lay.hinge_order:
        i, sign = lay.hinge_outer[h], lay.hinge_sign[h]
        for _ in range(HINGE_PASSES):
            r = frames[i, :3, :3]
            g = r.T @ fields.gradient_sum(local, r, frames[i, :3, 3])
            new = min(max(angles[h] + sign * math.atan2(g[0], g[2]), -limit), limit)
            delta = new - angles[h]
            frames = bend(spec, frames, widths, h, delta)
            angles[h] = new
            if abs(delta) < HINGE_TOLERANCE:
                break
    return frames


def _scale_flaps(fields, spec, lay, frames, widths) -> np.ndarray:
    """Step 7: HCEVF flap widths from the root outward; updates `widths` in place, returns the frames."""
    r = spec.root_flap
    lo, hi = (k * spec.flap_pitch for k in WIDTH_RANGE)
    for i in lay.flap_order:
        sides = (-1, 1) if i == r else ((1,) if i > r else (-1,))
        rot, t = frames[i, :3, :3], frames[i, :3, 3]
        total, count = 0.0, 0
        for side in sides:
            v = fields.hcevf(lay.edges[(side + 1) // 2].local(widths[i]) @ rot.T + t)
            v = v[v.any(axis=1)]
            # onto the flap's plane, then along the outward width direction: the in-plane
            # projection does not change the component along x, so take that directly
            total += side * float((v @ rot[:, 0]).sum())
            count += len(v)
        if count:
            new = min(max(widths[i] + total / count, lo), hi)
            frames = widen(spec, frames, i, new - widths[i])
            widths[i] = new
    return frames
