"""Pen redirection with visuo-haptic illusion (the paper's §3.3), over the morphed device.

The physical pen touches the device (the proxy); the user sees a virtual pen on the
target surface. For a contact point p on the proxy, with the proxy's normal n_p there:

- positional redirection: the virtual contact point v = p + t n_p, the nearest point
  along the proxy's normal (either way, up to `reach`) where the target's surface lies;
  the offset is d = v - p;
- rotational redirection: the rotation R that turns n_p onto the target's outward
  normal n_t at v (the smallest such rotation); the virtual pen is the physical pen
  rotated by R, so the pen meets the target as it meets the device.

The offsets are computed once per approximation on a grid over the device's touch
surface, in its unrolled coordinates (s along the row of flaps from the anchor, y along
the hinge axes), exactly (on the mesh, not the SDF grid: libigl's point-to-mesh query,
bracketed along each normal by the SDF grid and closed by safeguarded Newton steps).
Then, as the paper describes, the grid is padded beyond the device's edges into the
interaction space around it (nearest value) and d and R are Gaussian-blurred (R as
quaternions, renormalised), so the virtual pen does not jump where the proxy's normal
does: across a hinge, or when it leaves the device. Where the target is not found
along the normal within `reach`, the nearest found value stands in and the point is
flagged.

A pen sample anywhere near the device (touching or hovering) is placed on the grid by
the flap it is closest to (the end flaps and the y direction extend without limit): its
foot point c on the proxy, its surface coordinates (s, y) and its height h above the
surface. Its virtual pose is the blurred rigid redirection at (s, y) applied about c:
position c + d(s, y) + R(s, y) (q - c), orientation R(s, y) * orientation. A touching pen
(h = 0) goes to c + d; a hovering pen keeps its height along the target's normal.

Frames: the field is built in the frame where the approximation put the device (its
root pose). If the device is tracked at another pose (it is hand-held), give that pose
per sample: the pen is carried with the device, i.e. redirected relative to it.

SI inside (m, rad); pen files and reports in mm and degrees.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numba
import numpy as np
import trimesh
from scipy import ndimage

from twin.device.kinematics import flap_frames
from twin.device.spec import DeviceSpec
from twin.morphpatch.fields import Fields, exact_surface_query
from twin.perception.thresholds import Thresholds, load_thresholds

NODE_SPACING = 0.002  # m, between the redirection grid's nodes over the touch surface (as the metrics' samples)
SIGMA = 0.005  # m, Gaussian blur of the offsets (assumption: the paper gives none; about a fifth of a flap)
PADDING = 0.03  # m, interaction space around the device's edges that the field covers
REACH = 0.1  # m, how far along the proxy's normal the target is looked for (twice the 50 mm threshold)
NEWTON_TOL = 1e-9  # m, exact projection tolerance


@dataclasses.dataclass(frozen=True)
class RedirectionField:
    """Positional and rotational redirection over the device's unrolled touch surface.

    Grid nodes (i, j) sit at s = s0 + i ds, y = y0 + j dy (m); `offset` (ns, ny, 3) m and
    `rotation` (ns, ny, 4) quaternions (w, x, y, z) are the blurred field in the world frame
    of the approximation; `raw_offset`/`raw_rotation` the unblurred ones (nearest-filled
    outside the device and where no target was found). `on_device` marks nodes on the
    usable touch surface; `hit` the on-device nodes whose normal found the target.
    """

    root_pose: np.ndarray  # 4x4, the anchor in the world where the approximation put it
    frames: np.ndarray  # (n_flaps, 4, 4) flap touch-surface frames in the world
    widths: np.ndarray  # (n_flaps,) m
    s_edges: np.ndarray  # (n_flaps + 1,) m, flap boundaries along s
    s0: float
    y0: float
    ds: float
    dy: float
    offset: np.ndarray
    rotation: np.ndarray
    raw_offset: np.ndarray
    raw_rotation: np.ndarray
    on_device: np.ndarray
    hit: np.ndarray
    sigma: float  # m
    padding: float  # m
    build_time: float  # s

    @property
    def shape(self) -> tuple[int, int]:
        return self.offset.shape[:2]

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """Node coordinates s (ns,) and y (ny,), m."""
        ns, ny = self.shape
        return self.s0 + self.ds * np.arange(ns), self.y0 + self.dy * np.arange(ny)

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        """Proxy points (ns, ny, 3) m and normals (ns, ny, 3) at the nodes (on the flaps' planes)."""
        s, y = self.axes()
        ss, yy = np.meshgrid(s, y, indexing="ij")
        points, normals = surface_points(self.frames, self.s_edges, ss.ravel(), yy.ravel())
        return points.reshape(*self.shape, 3), normals.reshape(*self.shape, 3)

    def offset_size(self, raw: bool = False) -> np.ndarray:
        """|d| (ns, ny), m."""
        return np.linalg.norm(self.raw_offset if raw else self.offset, axis=-1)

    def rotation_angle(self, raw: bool = False) -> np.ndarray:
        """Angle of R (ns, ny), rad."""
        return quat_angle(self.raw_rotation if raw else self.rotation)


# ---- geometry ------------------------------------------------------------------------

def flap_boundaries(spec: DeviceSpec, widths) -> np.ndarray:
    """s (m) of the flaps' boundaries along the row, (n_flaps + 1,), with s = 0 at the anchor."""
    widths = np.asarray(widths, float)
    edges = np.concatenate([[0.0], np.cumsum(widths)])
    return edges - (edges[spec.root_flap] + widths[spec.root_flap] / 2)


def surface_points(frames: np.ndarray, s_edges: np.ndarray, s, y) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) m and unit normals (N, 3) of the touch surface at unrolled coordinates s, y (m).

    s beyond the ends continues the end flaps' planes. On a boundary between two flaps
    the normal is the mean of theirs (the proxy's pseudonormal there)."""
    s, y = np.asarray(s, float), np.asarray(y, float)
    n = len(frames)
    flap = np.clip(np.searchsorted(s_edges, s, side="right") - 1, 0, n - 1)
    centre = (s_edges[:-1] + s_edges[1:]) / 2
    local = np.stack([s - centre[flap], y, np.zeros_like(s)], axis=1)
    rot, origin = frames[flap, :3, :3], frames[flap, :3, 3]
    points = np.einsum("nij,nj->ni", rot, local) + origin
    normals = rot[:, :, 2].copy()
    inner = s_edges[1:-1]
    k = np.searchsorted(inner, s)  # the boundary at or after s
    on_edge = (k < len(inner)) & np.isclose(s, inner[np.minimum(k, len(inner) - 1)], rtol=0, atol=1e-9)
    if on_edge.any():
        left, right = k[on_edge], k[on_edge] + 1
        mean = frames[left, :3, 2] + frames[right, :3, 2]
        normals[on_edge] = mean / np.linalg.norm(mean, axis=1, keepdims=True)
    return points, normals


def project_along_normals(fields: Fields, mesh: trimesh.Trimesh, points: np.ndarray, normals: np.ndarray,
                          reach: float = REACH) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest crossing of the target surface along each line p + t n, |t| <= reach.

    Returns t (N,) m (NaN where none), hit (N,) bool and the target's outward unit
    normal there (N, 3). The SDF grid brackets the crossing (1 mm steps); the exact
    mesh closes it (safeguarded Newton, to NEWTON_TOL).
    """
    n = len(points)
    step = min(0.001, fields.spacing / 2)
    k = int(math.ceil(reach / step))
    t_grid = step * np.arange(-k, k + 1)
    values = fields.sdf_values((points[:, None, :] + t_grid[None, :, None] * normals[:, None, :]).reshape(-1, 3))
    values = values.reshape(n, -1)
    crossing = (values[:, :-1] <= 0) & (values[:, 1:] > 0)  # inside -> outside along +n: facing the proxy's way
    nearness = np.where(crossing, np.minimum(np.abs(t_grid[:-1]), np.abs(t_grid[1:]))[None, :], np.inf)
    nearness[crossing & (t_grid[:-1] < 0) & (t_grid[1:] > 0)] = 0.0
    j = np.argmin(nearness, axis=1)
    hit = np.isfinite(nearness[np.arange(n), j])
    t = np.full(n, np.nan)
    target_normals = np.zeros((n, 3))
    if not hit.any():
        return t, hit, target_normals

    idx = np.flatnonzero(hit)
    p, nv, jj = points[idx], normals[idx], j[idx]

    def exact(tt, rows=slice(None)):
        return exact_surface_query(mesh, p[rows] + tt[:, None] * nv[rows])[0]

    # bracket on the exact mesh: the grid's, widened by a step for its error, else the grid's own
    lo, hi = t_grid[jj] - step, t_grid[jj + 1] + step
    f_lo, f_hi = exact(lo), exact(hi)
    bad = ~((f_lo <= 0) & (f_hi > 0))
    if bad.any():
        lo[bad], hi[bad] = t_grid[jj[bad]], t_grid[jj[bad] + 1]
        f_lo[bad], f_hi[bad] = exact(lo[bad], bad), exact(hi[bad], bad)
    ok = (f_lo <= 0) & (f_hi > 0)
    v0, v1 = values[idx, jj], values[idx, jj + 1]
    tt = t_grid[jj] + step * v0 / np.where(v0 != v1, v0 - v1, 1.0)  # the grid's linear estimate
    tt = np.clip(tt, lo, hi)
    normal = np.zeros((len(idx), 3))
    active = ok.copy()
    for _ in range(60):
        if not active.any():
            break
        a = np.flatnonzero(active)
        s, closest, nrm = exact_surface_query(mesh, p[a] + tt[a, None] * nv[a])
        normal[a] = nrm
        done = np.abs(s) <= NEWTON_TOL
        same = np.sign(s) == np.sign(f_lo[a])
        lo[a] = np.where(same, tt[a], lo[a])
        f_lo[a] = np.where(same, s, f_lo[a])
        hi[a] = np.where(same, hi[a], tt[a])
        safe = np.where(np.abs(s) > 1e-12, s, 1.0)
        grad = np.where((np.abs(s) > 1e-12)[:, None], (p[a] + tt[a, None] * nv[a] - closest) / safe[:, None], nrm)
        slope = np.einsum("ij,ij->i", grad, nv[a])
        newton = tt[a] - s / np.where(np.abs(slope) > 1e-6, slope, np.nan)
        inside = np.isfinite(newton) & (newton > lo[a]) & (newton < hi[a])
        tt[a] = np.where(done, tt[a], np.where(inside, newton, (lo[a] + hi[a]) / 2))
        active[a] = ~done & (hi[a] - lo[a] > NEWTON_TOL)
    if active.any():  # closed by the bracket's width: the normal where it ended
        a = np.flatnonzero(active)
        normal[a] = exact_surface_query(mesh, p[a] + tt[a, None] * nv[a])[2]
    t[idx[ok]] = tt[ok]
    target_normals[idx[ok]] = normal[ok]
    hit[idx[~ok]] = False
    return t, hit, target_normals


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Quaternions (N, 4) w,x,y,z of the smallest rotations taking unit vectors a onto b (N, 3); w >= 0."""
    dot = np.einsum("ij,ij->i", a, b)
    q = np.concatenate([(1.0 + dot)[:, None], np.cross(a, b)], axis=1)
    opposite = dot < -1 + 1e-12  # half a turn: about any axis perpendicular to a
    if opposite.any():
        axis = np.cross(a[opposite], [1.0, 0.0, 0.0])
        small = np.linalg.norm(axis, axis=1) < 1e-6
        axis[small] = np.cross(a[opposite][small], [0.0, 1.0, 0.0])
        q[opposite] = np.concatenate([np.zeros((len(axis), 1)), axis], axis=1)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def quat_angle(q: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) of quaternions (..., 4), w first."""
    return 2.0 * np.arctan2(np.linalg.norm(q[..., 1:], axis=-1), np.abs(q[..., 0]))


# ---- the field -------------------------------------------------------------------------

def _axis(lo: float, hi: float, spacing: float, padding: float) -> tuple[float, float, int, int]:
    """Node axis covering [lo, hi] with whole cells and `padding` beyond: (start, step, nodes, first device node)."""
    cells = max(1, math.ceil((hi - lo) / spacing - 1e-9))
    step = (hi - lo) / cells
    pad = math.ceil(padding / step - 1e-9)
    return lo - pad * step, step, cells + 1 + 2 * pad, pad


def build_field(spec: DeviceSpec, root_pose, angles, widths, mesh: trimesh.Trimesh, fields: Fields,
                sigma: float = SIGMA, padding: float = PADDING, spacing: float = NODE_SPACING,
                reach: float = REACH) -> RedirectionField:
    """The redirection field of a proxy (root pose 4x4 m, hinge angles rad, flap widths m) on a target.

    fields: the target's SDF grid (brackets the projections); mesh: the target itself.
    sigma: Gaussian blur, m (0: none); padding: field beyond the device's edges, m.
    """
    if sigma < 0 or padding < 0 or spacing <= 0 or reach <= 0:
        raise ValueError("sigma and padding must be >= 0, spacing and reach > 0 (m)")
    t0 = time.perf_counter()
    widths = np.asarray(widths, float)
    frames = flap_frames(spec, angles, root_pose, widths)
    s_edges = flap_boundaries(spec, widths)
    s0, ds, ns, ps = _axis(s_edges[0], s_edges[-1], spacing, padding)
    y0, dy, ny, py = _axis(-spec.usable_depth / 2, spec.usable_depth / 2, spacing, padding)
    on_device = np.zeros((ns, ny), bool)
    on_device[ps:ns - ps, py:ny - py] = True

    s, y = s0 + ds * np.arange(ns), y0 + dy * np.arange(ny)
    ss, yy = np.meshgrid(s, y, indexing="ij")
    points, normals = surface_points(frames, s_edges, ss[on_device], yy[on_device])
    t, found, target_normals = project_along_normals(fields, mesh, points, normals, reach)

    raw_offset = np.zeros((ns, ny, 3))
    raw_rotation = np.zeros((ns, ny, 4))
    raw_rotation[..., 0] = 1.0
    raw_offset[on_device] = np.where(found[:, None], t[:, None] * normals, 0.0)
    raw_rotation[on_device] = np.where(found[:, None], rotation_between(normals, np.where(
        found[:, None], target_normals, normals)), raw_rotation[on_device])
    hit = np.zeros((ns, ny), bool)
    hit[on_device] = found

    # padding: every node without a value (off the device, or no target) takes its nearest node's
    if hit.any():
        nearest = ndimage.distance_transform_edt(~hit, sampling=(ds, dy), return_distances=False, return_indices=True)
        raw_offset = raw_offset[nearest[0], nearest[1]]
        raw_rotation = raw_rotation[nearest[0], nearest[1]]
    blur = (sigma / ds, sigma / dy, 0)
    offset = ndimage.gaussian_filter(raw_offset, blur, mode="nearest") if sigma > 0 else raw_offset.copy()
    rotation = ndimage.gaussian_filter(raw_rotation, blur, mode="nearest") if sigma > 0 else raw_rotation.copy()
    rotation /= np.linalg.norm(rotation, axis=-1, keepdims=True)
    return RedirectionField(np.asarray(root_pose, float), frames, widths, s_edges, s0, y0, ds, dy, offset, rotation, raw_offset, raw_rotation,
                            on_device, hit, sigma, padding, time.perf_counter() - t0)


# ---- pen samples -------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Redirected:
    """Redirected pen samples (N rows): virtual pose, and the redirection applied (SI)."""

    position: np.ndarray  # (N, 3) m, virtual pen tip in the world
    orientation: np.ndarray  # (N, 4) w,x,y,z, virtual pen
    offset: np.ndarray  # (N,) m, |d| at the sample's foot point
    angle: np.ndarray  # (N,) rad, angle of R there
    height: np.ndarray  # (N,) m, above (+) or below (-) the touch surface
    flap: np.ndarray  # (N,) int, the flap the sample is placed on
    s: np.ndarray  # (N,) m, unrolled coordinate along the row
    y: np.ndarray  # (N,) m, along the hinge axes


def redirect(field: RedirectionField, positions, orientations, device_poses=None) -> Redirected:
    """Redirect pen samples: positions (N, 3) m and orientations (N, 4) w,x,y,z in the world.

    device_poses: optional (N, 4, 4), the tracked device pose per sample; the pen is then
    taken relative to the device and the field used as if the device were where the
    approximation put it. Compiled: about 1 us per sample in a batch (see benchmarks).
    """
    positions = np.ascontiguousarray(np.atleast_2d(positions), dtype=np.float64)
    orientations = np.ascontiguousarray(np.atleast_2d(orientations), dtype=np.float64)
    if positions.shape[1:] != (3,) or orientations.shape != (len(positions), 4):
        raise ValueError(f"expected positions (N, 3) and orientations (N, 4); got {positions.shape}, "
                         f"{orientations.shape}")
    if device_poses is None:
        carry = np.zeros((0, 4, 4))
    else:
        device_poses = np.asarray(device_poses, float).reshape(-1, 4, 4)
        if len(device_poses) != len(positions):
            raise ValueError(f"expected one device pose per sample ({len(positions)}), got {len(device_poses)}")
        carry = np.ascontiguousarray(field.root_pose @ np.linalg.inv(device_poses))
    n = len(positions)
    out_p, out_q = np.empty((n, 3)), np.empty((n, 4))
    info = np.empty((n, 6))
    redirect_kernel(np.ascontiguousarray(field.frames[:, :3, :3]), np.ascontiguousarray(field.frames[:, :3, 3]),
                     field.s_edges, field.s0, field.ds, field.y0, field.dy, field.offset, field.rotation,
                     positions, orientations, carry, out_p, out_q, info)
    return Redirected(out_p, out_q, info[:, 0], info[:, 1], info[:, 2], info[:, 3].astype(int), info[:, 4],
                      info[:, 5])


@numba.njit(cache=True, inline="always")
def _qmul(a0, a1, a2, a3, b0, b1, b2, b3):
    return (a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3, a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
            a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1, a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0)


@numba.njit(cache=True, inline="always")
def _qrotate(w, x, y, z, vx, vy, vz):
    """v rotated by the unit quaternion (w, x, y, z)."""
    tx, ty, tz = 2.0 * (y * vz - z * vy), 2.0 * (z * vx - x * vz), 2.0 * (x * vy - y * vx)
    return (vx + w * tx + (y * tz - z * ty), vy + w * ty + (z * tx - x * tz), vz + w * tz + (x * ty - y * tx))


@numba.njit(cache=True)
def redirect_kernel(rot, origin, s_edges, s0, ds, y0, dy, offset, rotation, positions, orientations, carry,
                    out_p, out_q, info):
    """`redirect`'s compiled core on a RedirectionField's arrays: each pen sample (positions m, orientations
    wxyz) redirected into out_p, out_q and info, allocating nothing (the live service's pen path calls it on
    arrays it keeps: twin.live.pens)."""
    n_flaps = rot.shape[0]
    ns, ny = offset.shape[0], offset.shape[1]
    for k in range(positions.shape[0]):
        q = positions[k]
        qw, qx, qy, qz = orientations[k, 0], orientations[k, 1], orientations[k, 2], orientations[k, 3]
        px, py, pz = q[0], q[1], q[2]
        if carry.shape[0] > 0:  # the pen relative to the tracked device, put where the approximation has it
            c = carry[k]
            px, py, pz = (c[0, 0] * q[0] + c[0, 1] * q[1] + c[0, 2] * q[2] + c[0, 3],
                          c[1, 0] * q[0] + c[1, 1] * q[1] + c[1, 2] * q[2] + c[1, 3],
                          c[2, 0] * q[0] + c[2, 1] * q[1] + c[2, 2] * q[2] + c[2, 3])
            # rotation matrix -> quaternion (Shepperd), then compose
            tr = c[0, 0] + c[1, 1] + c[2, 2]
            if tr > 0:
                r = math.sqrt(tr + 1.0) * 2
                cw, cx, cy, cz = 0.25 * r, (c[2, 1] - c[1, 2]) / r, (c[0, 2] - c[2, 0]) / r, (c[1, 0] - c[0, 1]) / r
            elif c[0, 0] > c[1, 1] and c[0, 0] > c[2, 2]:
                r = math.sqrt(1.0 + c[0, 0] - c[1, 1] - c[2, 2]) * 2
                cw, cx, cy, cz = (c[2, 1] - c[1, 2]) / r, 0.25 * r, (c[0, 1] + c[1, 0]) / r, (c[0, 2] + c[2, 0]) / r
            elif c[1, 1] > c[2, 2]:
                r = math.sqrt(1.0 + c[1, 1] - c[0, 0] - c[2, 2]) * 2
                cw, cx, cy, cz = (c[0, 2] - c[2, 0]) / r, (c[0, 1] + c[1, 0]) / r, 0.25 * r, (c[1, 2] + c[2, 1]) / r
            else:
                r = math.sqrt(1.0 + c[2, 2] - c[0, 0] - c[1, 1]) * 2
                cw, cx, cy, cz = (c[1, 0] - c[0, 1]) / r, (c[0, 2] + c[2, 0]) / r, (c[1, 2] + c[2, 1]) / r, 0.25 * r
            qw, qx, qy, qz = _qmul(cw, cx, cy, cz, qw, qx, qy, qz)
        # the flap the pen is closest to (inner edges clamp, the end flaps and y extend)
        best, best_d, best_lx, best_ly, best_lz = 0, np.inf, 0.0, 0.0, 0.0
        for f in range(n_flaps):
            dx, dy_, dz = px - origin[f, 0], py - origin[f, 1], pz - origin[f, 2]
            lx = rot[f, 0, 0] * dx + rot[f, 1, 0] * dy_ + rot[f, 2, 0] * dz
            ly = rot[f, 0, 1] * dx + rot[f, 1, 1] * dy_ + rot[f, 2, 1] * dz
            lz = rot[f, 0, 2] * dx + rot[f, 1, 2] * dy_ + rot[f, 2, 2] * dz
            half = 0.5 * (s_edges[f + 1] - s_edges[f])
            cx_ = lx
            if f > 0 and cx_ < -half:
                cx_ = -half
            if f < n_flaps - 1 and cx_ > half:
                cx_ = half
            d = (lx - cx_) ** 2 + lz * lz
            if d < best_d:
                best, best_d, best_lx, best_ly, best_lz = f, d, cx_, ly, lz
        f = best
        s = 0.5 * (s_edges[f] + s_edges[f + 1]) + best_lx
        y = best_ly
        fx = origin[f, 0] + rot[f, 0, 0] * best_lx + rot[f, 0, 1] * best_ly
        fy = origin[f, 1] + rot[f, 1, 0] * best_lx + rot[f, 1, 1] * best_ly
        fz = origin[f, 2] + rot[f, 2, 0] * best_lx + rot[f, 2, 1] * best_ly
        # bilinear lookup, clamped to the grid
        gi = min(max((s - s0) / ds, 0.0), ns - 1.000001)
        gj = min(max((y - y0) / dy, 0.0), ny - 1.000001)
        i, j = int(gi), int(gj)
        a, b = gi - i, gj - j
        w00, w10, w01, w11 = (1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b
        d0 = w00 * offset[i, j, 0] + w10 * offset[i + 1, j, 0] + w01 * offset[i, j + 1, 0] + w11 * offset[i + 1, j + 1, 0]
        d1 = w00 * offset[i, j, 1] + w10 * offset[i + 1, j, 1] + w01 * offset[i, j + 1, 1] + w11 * offset[i + 1, j + 1, 1]
        d2 = w00 * offset[i, j, 2] + w10 * offset[i + 1, j, 2] + w01 * offset[i, j + 1, 2] + w11 * offset[i + 1, j + 1, 2]
        r = np.empty(4)
        for m in range(4):
            r[m] = (w00 * rotation[i, j, m] + w10 * rotation[i + 1, j, m] + w01 * rotation[i, j + 1, m]
                    + w11 * rotation[i + 1, j + 1, m])
        norm = math.sqrt(r[0] ** 2 + r[1] ** 2 + r[2] ** 2 + r[3] ** 2)
        rw, rx, ry, rz = r[0] / norm, r[1] / norm, r[2] / norm, r[3] / norm
        vx, vy, vz = _qrotate(rw, rx, ry, rz, px - fx, py - fy, pz - fz)
        out_p[k, 0], out_p[k, 1], out_p[k, 2] = fx + d0 + vx, fy + d1 + vy, fz + d2 + vz
        ow, ox, oy, oz = _qmul(rw, rx, ry, rz, qw, qx, qy, qz)
        out_q[k, 0], out_q[k, 1], out_q[k, 2], out_q[k, 3] = ow, ox, oy, oz
        info[k, 0] = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        info[k, 1] = 2.0 * math.atan2(math.sqrt(rx * rx + ry * ry + rz * rz), abs(rw))
        info[k, 2] = best_lz
        info[k, 3] = f
        info[k, 4] = s
        info[k, 5] = y


def largest_virtual_step(field: RedirectionField, step: float = 0.0005, margin: float = 0.03) -> float:
    """Largest move (m) of the virtual pen for one `step` m of a pen on the touch surface, walking
    along s across every hinge and `margin` m beyond both ends (at three y), and along y `margin` m
    beyond both sides (at three s): how continuous the redirection is where the pen crosses flap
    edges and leaves the device."""
    lo, hi = field.s_edges[0], field.s_edges[-1]
    half = field.axes()[1][field.on_device.any(axis=0)].max()  # half the usable depth
    s = np.arange(lo - margin, hi + margin, step)
    y = np.arange(-half - margin, half + margin, step)
    walks = [(s, np.full_like(s, v)) for v in (-half - margin / 3, 0.0, 0.8 * half)]
    walks += [(np.full_like(y, v), y) for v in (field.s_edges[1] + 0.001, 0.0, hi + margin / 3)]
    largest = 0.0
    for ss, yy in walks:
        pens, _ = surface_points(field.frames, field.s_edges, ss, yy)
        out = redirect(field, pens, np.tile([1.0, 0.0, 0.0, 0.0], (len(pens), 1)))
        largest = max(largest, float(np.linalg.norm(np.diff(out.position, axis=0), axis=1).max()))
    return largest


# ---- perception thresholds ----------------------------------------------------------------

def threshold_summary(field: RedirectionField, thresholds: Thresholds | None = None) -> dict:
    """How much of the device's touch surface the redirection keeps within the thresholds.

    Shares are of the usable touch surface's nodes (a uniform grid: node shares are area
    shares), with the blurred field (what the user sees) and the raw one (`raw_` keys).
    """
    thresholds = thresholds or load_thresholds()
    dev = field.on_device
    out = {"position_threshold_mm": round(thresholds.position * 1e3, 3),
           "rotation_threshold_deg": round(math.degrees(thresholds.rotation), 3),
           "no_target_share": round(float(1 - field.hit[dev].mean()), 4)}
    for name, raw in (("", False), ("raw_", True)):
        size, angle = field.offset_size(raw)[dev], field.rotation_angle(raw)[dev]
        out.update({f"{name}share_within": round(float(within_flags(field, thresholds, raw)[dev].mean()), 4),
                    f"{name}largest_offset_mm": round(float(size.max()) * 1e3, 3),
                    f"{name}largest_rotation_deg": round(math.degrees(float(angle.max())), 3),
                    f"{name}mean_offset_mm": round(float(size.mean()) * 1e3, 3),
                    f"{name}mean_rotation_deg": round(math.degrees(float(angle.mean())), 3)})
    return out


def within_flags(field: RedirectionField, thresholds: Thresholds | None = None, raw: bool = False) -> np.ndarray:
    """Per node (ns, ny): the redirection (blurred, or raw) is within both thresholds, and on the
    device the target was found along the normal."""
    thresholds = thresholds or load_thresholds()
    return ((field.hit | ~field.on_device) & (field.offset_size(raw) <= thresholds.position)
            & (field.rotation_angle(raw) <= thresholds.rotation))


def within_samples(redirected: Redirected, thresholds: Thresholds | None = None) -> np.ndarray:
    """Per pen sample: the redirection it got is within both thresholds."""
    thresholds = thresholds or load_thresholds()
    return (redirected.offset <= thresholds.position) & (redirected.angle <= thresholds.rotation)
