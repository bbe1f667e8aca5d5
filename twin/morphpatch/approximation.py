"""MorphPatch's surface approximation: root pose, hinge angles and flap widths for a target.

The pipeline, in the paper's order (its figure; §3.2):

1. snap: the device moves along its anchor direction (the device's -z from the
   anchor) until the anchor touches the surface (S = 0 along that line, within
   SNAP_REACH; if the line misses the target, the anchor goes to its closest surface
   point instead, sphere tracing down S in steps short of it);
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

The side the device came from (every variant): the anchor's path from the start (straight
to the snapped point, then the pipeline's slide and each of the refinement's steps, each
straight) never crosses the target's solid. Step 1 reaches the surface without crossing
it (the first entry along -z, or the closest surface point); step 5 is undone where its
slide would cross the solid; the refinement refuses a step whose path would. (A start
inside the target, which the live service meets when a hand pushes the device into a
virtual object, backs out along +z; the commands refuse such a start.) What it does not yet guarantee: a device
wider than a cavity it is lowered into (a cup from above its opening) can still rest
its anchor inside it (docs/approximation.md, "Starts and the approached side").
Variant "refined" (ours, beyond the paper) is "full" followed by a bounded local
least-squares refinement of the root pose and hinge angles (twin.morphpatch.refinement),
and more from full's pose with the root turned a quarter about its normal (`_refined`).
SI units throughout (m, rad, s); the result is the record twin.records.approximation.Approximation, whose
file form (mm and degrees) is twin.formats.target's.
"""

from __future__ import annotations

import dataclasses
import math
import time
from functools import lru_cache

import numba
import numpy as np
from scipy.spatial.transform import Rotation

from twin.checks import REACH_M
from twin.device.kinematics import _chain, flap_frames, hinge_axis_sign, outer_flap, pose_matrix
from twin.device.spec import DeviceSpec, load_spec
from twin.morphpatch.fields import Fields, _gradient_sum, _hcevf_at, _interpolate, _path_clear, _value
from twin.morphpatch.refinement import refine_best
from twin.morphpatch.sampling import SAMPLE_SPACING, edge_layout, grid_layout, world_points
from twin.morphpatch.surface_metrics import match
from twin.records.approximation import Approximation

VARIANTS = ("full", "no_hcevf", "refined")
SNAP_REACH = 0.25  # m, how far along +-z a snap looks for the surface (here, and CBS's press along its normal)
TRACE_STEPS = 64  # sphere-tracing steps to the closest surface point where the snap's line misses the target
TRACE_TOLERANCE = 1e-4  # m: a traced point this close to the surface is on it
TRACE_RELAX = 0.9  # each tracing step goes this share of the distance: short of the surface where S is long
ROOT_PASSES = 2  # passes of each root rotation step
HINGE_PASSES = 3  # passes per hinge
HINGE_TOLERANCE = 1e-3  # rad: a hinge pass that changes the angle less than this ends the hinge
PRINCIPAL_MIN = 0.2  # the in-plane gradients' anisotropy (0..1) below which step 4 does nothing
PRINCIPAL_MIN_TILT = math.radians(3)  # ... or their RMS tilt from the normal below which it does nothing
# ours also refines from the pipeline's pose with the root turned by TURN (rad) about its normal (`_refined`): the
# local search keeps the direction step 4 gave the row, which on a cup or a plate's edge can lie along the side
# the row cannot curl round (docs/approximation.md, "Turned starts"). Always, since issue 37's sixth session: it was
# tried only where the objective at the turned start was at most 3 times the first refinement's end, but the start's
# objective does not tell where its search ends (plate_0: turned starts 16-60 times the first end's, ending at 1.7 mm
# where the first ended at 3.3). (The root tilted by +-0.5 rad about its hinge axis too, issue 37's eighth and ninth
# sessions, not since the bounded searches' steps keep the depth bound: on the 40 corpus shapes x 3 starts as near
# the target without them, in less time: docs/approximation.md, "Issue 37's tenth session")
TURN = math.pi / 2
WIDTH_RANGE = (0.5, 1.5)  # flap widths stay within these multiples of the pitch


def frames(spec: DeviceSpec, a: Approximation) -> np.ndarray:
    """World poses (n_flaps, 4, 4) of an approximation's flaps' touch-surface frames."""
    return flap_frames(spec, a.angles, a.root_pose, a.widths)


def measured(spec: DeviceSpec, mesh, a: Approximation) -> Approximation:
    """A copy of `a` with MSD, HD (m) and the share inside the target and its depth against the exact mesh (see
    twin.morphpatch.surface_metrics)."""
    m = match(spec, mesh, a.root_pose, a.angles, a.widths)
    return dataclasses.replace(a, msd=m.msd, hd=m.hd, inside=m.inside, depth=m.depth)


def pose_from_mm_deg(values) -> np.ndarray:
    """4x4 pose from [x_mm, y_mm, z_mm, roll_deg, pitch_deg, yaw_deg] (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    values = np.asarray(values, float)
    if values.shape != (6,) or not np.all(np.isfinite(values)):
        raise ValueError(f"a start is 6 finite numbers x,y,z (mm), roll,pitch,yaw (deg); got {values.tolist()}")
    if np.any(np.abs(values[3:]) > 360.0):
        raise ValueError(f"a start's roll, pitch and yaw are within +-360 deg; got {values[3:].tolist()}")
    rotation = Rotation.from_euler("xyz", values[3:], degrees=True).as_matrix()
    return as_pose(pose_matrix(values[:3] / 1e3, rotation))


def as_pose(start) -> np.ndarray:
    """A 4x4 pose from a 4x4 matrix or a (position (3,) m, rotation (3, 3)) pair, checked before any compiled
    step sees it: finite, a rotation (orthonormal, det +1, to 1e-6), the anchor within REACH_M of the
    target frame's origin. ValueError naming what is wrong."""
    pose = pose_matrix(*start) if isinstance(start, tuple) else np.array(start, float)
    if pose.shape != (4, 4):
        raise ValueError(f"a start pose is a 4x4 matrix or (position, rotation); got shape {pose.shape}")
    if not np.all(np.isfinite(pose)):
        raise ValueError("a start pose must be finite numbers")
    distance = float(np.linalg.norm(pose[:3, 3]))
    if distance > REACH_M:
        raise ValueError(f"the start is {distance:.3g} m from the target's origin; at most {REACH_M:g} m")
    rotation = pose[:3, :3]
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6) or np.linalg.det(rotation) < 0:
        raise ValueError("a start pose's rotation must be orthonormal with determinant +1")
    return pose


@dataclasses.dataclass(frozen=True)
class _Layouts:
    """Precomputed samples for one spec (device frame, flat, nominal widths), m."""

    root_points: np.ndarray  # (M, 3) root flap samples
    all_points: np.ndarray  # (n_flaps*M, 3) all flaps' samples
    edge_points: np.ndarray  # (n_flaps*2*K, 3) both edges of every flap
    flap: object  # sampling.Layout on one flap
    flap_points: np.ndarray  # (M, 3) one flap's samples in its frame at the pitch
    edge_y: np.ndarray  # (K,) y of the samples along a flap's edge
    hinge_order: np.ndarray  # hinges from the root outward
    hinge_sign: np.ndarray  # per hinge, its axis sign
    hinge_outer: np.ndarray  # per hinge, the flap it moves
    flap_order: np.ndarray  # flaps from the root outward


@lru_cache(maxsize=8)
def _layouts(spec: DeviceSpec) -> _Layouts:
    widths = np.full(spec.n_flaps, spec.flap_pitch)
    flat = flap_frames(spec, np.zeros(spec.n_hinges), None, widths)
    flap = grid_layout(spec, SAMPLE_SPACING)
    edges = (edge_layout(spec, -1), edge_layout(spec, +1))
    r = spec.root_flap
    right, left = list(range(r, spec.n_hinges)), list(range(r - 1, -1, -1))
    return _Layouts(
        root_points=world_points(flat, widths, flap, [r])[0],
        all_points=world_points(flat, widths, flap).reshape(-1, 3),
        edge_points=np.vstack([world_points(flat, widths, e).reshape(-1, 3) for e in edges]),
        flap=flap,
        flap_points=flap.local(spec.flap_pitch),
        edge_y=np.ascontiguousarray(edges[0].y),
        hinge_order=np.array(right + left),
        hinge_sign=hinge_axis_sign(spec),
        hinge_outer=outer_flap(spec),
        flap_order=np.array(sorted(range(spec.n_flaps), key=lambda f: abs(f - r))),
    )


def approximate(fields: Fields, start, spec: DeviceSpec | None = None, variant: str = "full") -> Approximation:
    """Approximate the target of `fields` with the device, from a start pose of its anchor.

    start: 4x4 pose, or (position (3,) m, rotation (3, 3)); hinges start flat and
    widths at the pitch. variant: one of VARIANTS. Returns root pose, hinge angles
    (rad, inside +-spec.hinge_limit), flap widths (m) and the time taken (s).
    Each step is one compiled call on the fields' grids (`Fields.grid`, `Fields.edge_grid`).
    """
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; choose from {', '.join(VARIANTS)}")
    spec = load_spec() if spec is None else spec
    start = as_pose(start)
    t0 = time.perf_counter()
    lay = _layouts(spec)
    snapped, pose = _rest(fields.grid, start, lay)
    if variant != "no_hcevf":
        slid = _hcevf_translation(fields.grid, fields.edge_grid, pose, lay.edge_points)
        if _path_clear(fields.grid, snapped[:3, 3], slid[:3, 3]):
            pose = slid
    angles, widths = _hinges_and_widths(fields, spec, lay, pose, variant != "no_hcevf")
    rests = None
    if variant == "refined":
        pose, angles, rests = _refined(fields, spec, lay, snapped[:3, 3], pose, angles)
        widths = np.full(spec.n_flaps, spec.flap_pitch)
    return Approximation(pose, angles, widths, time.perf_counter() - t0, variant, rests=rests)


def _hinges_and_widths(fields: Fields, spec: DeviceSpec, lay: _Layouts, pose, hcevf: bool = True):
    """Steps 6-7 at a root pose: the hinge angles (rad), then with `hcevf` the HCEVF flap widths (m; else the
    pitch)."""
    widths = np.full(spec.n_flaps, spec.flap_pitch)
    angles = _align_hinges(fields.grid, pose, lay.flap_points, widths, lay.hinge_order, lay.hinge_outer,
                           lay.hinge_sign, spec.root_flap, spec.hinge_limit)
    if hcevf:
        widths = _scale_flaps(fields.edge_grid, pose, angles, widths, lay.edge_y, lay.flap_order, lay.hinge_sign,
                              spec.root_flap, WIDTH_RANGE[0] * spec.flap_pitch, WIDTH_RANGE[1] * spec.flap_pitch)
    return angles, widths


def _refined(fields: Fields, spec: DeviceSpec, lay: _Layouts, centre, pose, angles):
    """Ours: the refinement (twin.morphpatch.refinement.refine_best) from the pipeline's pose and from that pose with
    the root turned by TURN about its normal (step 6 redone there), their bounded searches screened together; of the
    ends that rest on the target from outside the one whose samples lie nearer the target on the grid (mean |S|, what
    the MSD measures; the earlier on ties); the anchor within ANCHOR_RADIUS of the snapped anchor `centre` (3,) m or
    of the point above it the start was lifted to: (root pose 4x4, hinge angles rad, whether it rests). Flaps at the
    pitch: ours is a pose the device takes, judged as the device is built."""
    widths = np.full(spec.n_flaps, spec.flap_pitch)
    turned = pose.copy()
    turned[:3, :3] = pose[:3, :3] @ _rot(2, TURN)
    turned_angles = _hinges_and_widths(fields, spec, lay, turned, hcevf=False)[0]
    return refine_best(fields, spec, lay.flap.local(widths), np.array([pose, turned]),
                       np.array([angles, turned_angles]), widths, centre)


def root_pose(fields: Fields, start, spec: DeviceSpec) -> np.ndarray:
    """Steps 1-4 only: the start snapped onto the target and the root turned to it (4x4, m)."""
    return _rest(fields.grid, as_pose(start), _layouts(spec))[1]


def _rest(grid, start: np.ndarray, lay: _Layouts) -> tuple[np.ndarray, np.ndarray]:
    """Steps 1-4: (the snapped pose, the root turned to the target there)."""
    snapped = _snap(grid, start)
    return snapped, _align_root(grid, snapped, lay.root_points, lay.all_points)


@numba.njit(cache=True)
def _hcevf_translation(grid, edge_grid, pose, edge_points):
    """Step 5: the pose moved by the mean HCEVF vector's component along the root's x-y plane, re-snapped.
    edge_points (N, 3): both edges of every flap in the device frame, flat, m."""
    rot, pos = pose[:3, :3].copy(), pose[:3, 3].copy()
    shift = np.zeros(3)
    count = 0
    for p in range(edge_points.shape[0]):
        x, y, z = _placed(rot, pos, edge_points[p])
        vx, vy, vz = _hcevf_at(edge_grid, x, y, z)
        if vx != 0.0 or vy != 0.0 or vz != 0.0:
            shift[0] += vx
            shift[1] += vy
            shift[2] += vz
            count += 1
    if count == 0:
        return pose
    shift /= count
    normal = rot[:, 2].copy()
    shift -= (shift @ normal) * normal
    moved = pose.copy()
    moved[:3, 3] = pos + shift
    return _snap(grid, moved)


@numba.njit(cache=True, inline="always")
def _placed(rot, pos, p):
    """rot @ p + pos for one point p (3,), as (x, y, z): written out (a matrix product here is a BLAS call)."""
    return (pos[0] + rot[0, 0] * p[0] + rot[0, 1] * p[1] + rot[0, 2] * p[2],
            pos[1] + rot[1, 0] * p[0] + rot[1, 1] * p[1] + rot[1, 2] * p[2],
            pos[2] + rot[2, 0] * p[0] + rot[2, 1] * p[1] + rot[2, 2] * p[2])


@numba.njit(cache=True)
def _snap(grid, pose):
    """Move the pose along its -z until the anchor is on the surface (see module docstring)."""
    anchor, down = pose[:3, 3].copy(), -pose[:3, 2]
    step = min(grid[2], 0.002)
    s = np.arange(-SNAP_REACH, SNAP_REACH + step / 2, step)
    values = np.empty(len(s))
    for k in range(len(s)):
        p = anchor + s[k] * down
        values[k] = _value(grid, p[0], p[1], p[2])
    mid = len(s) // 2  # s[mid] == 0
    a = -1
    if values[mid] > 0.0:  # outside: first entry ahead
        for j in range(mid, len(s)):
            if values[j] <= 0.0:
                a = j - 1
                break
    else:  # inside: back out along +z to the last exit behind
        for j in range(mid, -1, -1):
            if values[j] > 0.0:
                a = j
                break
    out = pose.copy()
    if a < 0:  # the line misses the target: go to the closest surface point, sphere tracing down the distance
        p = anchor  # (steps of TRACE_RELAX x S: beyond the grid S is extrapolated, 3 % long 0.3 m out; a full step
        for _ in range(TRACE_STEPS):  # from there crossed a 7 mm plate)
            value, gx, gy, gz = _interpolate(grid, p[0], p[1], p[2])
            if value < TRACE_TOLERANCE:
                break
            grad = np.array([gx, gy, gz])
            p = p - TRACE_RELAX * value * grad / max(math.sqrt(grad @ grad), 1e-9)
        out[:3, 3] = p
        return out
    b = a + 1
    t = s[a] + (s[b] - s[a]) * values[a] / (values[a] - values[b])
    out[:3, 3] = anchor + t * down
    return out


@numba.njit(cache=True)
def _rot(axis, angle):
    """Rotation matrix (3, 3) by `angle` rad about coordinate axis 0, 1 or 2."""
    c, s = math.cos(angle), math.sin(angle)
    i, j = (1, 2) if axis == 0 else ((2, 0) if axis == 1 else (0, 1))
    m = np.eye(3)
    m[i, i] = m[j, j] = c
    m[i, j], m[j, i] = -s, s
    return m


@numba.njit(cache=True)
def _align_root(grid, pose, root_points, all_points):
    """Steps 2-4: the pose turned about y, then x, then z (about the anchor)."""
    rot, pos = pose[:3, :3].copy(), pose[:3, 3].copy()
    for _ in range(ROOT_PASSES):  # about y, root flap only
        g = rot.T @ _gradient_sum(grid, root_points, rot, pos)
        rot = rot @ _rot(1, math.atan2(g[0], g[2]))
    for _ in range(ROOT_PASSES):  # about x, all flaps
        g = rot.T @ _gradient_sum(grid, all_points, rot, pos)
        rot = rot @ _rot(0, math.atan2(-g[1], g[2]))
    power = a = b = 0.0  # about z: principal in-plane direction of the gradients in the root frame
    for p in range(all_points.shape[0]):
        x, y, z = _placed(rot, pos, all_points[p])
        _, wx, wy, wz = _interpolate(grid, x, y, z)
        gx = rot[0, 0] * wx + rot[1, 0] * wy + rot[2, 0] * wz
        gy = rot[0, 1] * wx + rot[1, 1] * wy + rot[2, 1] * wz
        power += gx * gx + gy * gy
        a += gx * gx - gy * gy
        b += 2.0 * gx * gy
    if power > all_points.shape[0] * math.sin(PRINCIPAL_MIN_TILT) ** 2 and math.hypot(a, b) > PRINCIPAL_MIN * power:
        rot = rot @ _rot(2, 0.5 * math.atan2(b, a))
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = pos
    return out


@numba.njit(cache=True)
def _align_hinges(grid, pose, flap_points, widths, hinge_order, hinge_outer, hinge_sign, root_flap, limit):
    """Step 6: the hinge angles (rad), from the root outward, for flaps of `widths` (m)."""
    angles = np.zeros(len(hinge_order))
    for h in hinge_order:
        i, sign = hinge_outer[h], hinge_sign[h]
        for _ in range(HINGE_PASSES):
            frame = _chain(hinge_sign * angles, widths, root_flap, pose)[i]
            r = frame[:3, :3].copy()
            g = r.T @ _gradient_sum(grid, flap_points, r, frame[:3, 3].copy())
            new = min(max(angles[h] + sign * math.atan2(g[0], g[2]), -limit), limit)
            delta = new - angles[h]
            angles[h] = new
            if abs(delta) < HINGE_TOLERANCE:
                break
    return angles


@numba.njit(cache=True)
def _scale_flaps(edge_grid, pose, angles, widths, edge_y, flap_order, hinge_sign, root_flap, lo, hi):
    """Step 7: HCEVF flap widths (m) from the root outward, from `widths`, kept within [lo, hi] m."""
    widths = widths.copy()
    for i in flap_order:
        frame = _chain(hinge_sign * angles, widths, root_flap, pose)[i]
        total, count = 0.0, 0
        for side in (-1.0, 1.0):
            if (i < root_flap and side > 0) or (i > root_flap and side < 0):
                continue  # a flap samples the edge a width change moves, the root flap both
            for y in edge_y:
                x = frame[:3, 3] + frame[:3, 0] * (0.5 * side * widths[i]) + frame[:3, 1] * y
                vx, vy, vz = _hcevf_at(edge_grid, x[0], x[1], x[2])
                if vx != 0.0 or vy != 0.0 or vz != 0.0:
                    # onto the flap's plane, then along the outward width direction: the in-plane
                    # projection does not change the component along x, so take that directly
                    total += side * (vx * frame[0, 0] + vy * frame[1, 0] + vz * frame[2, 0])
                    count += 1
        if count:
            widths[i] = min(max(widths[i] + total / count, lo), hi)
    return widths
