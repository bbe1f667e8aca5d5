"""The target's fields, sampled once on a grid: signed distance, its gradient, curvature, HCEVF.

Signed distance S (m, negative inside) is computed with libigl's
`igl.signed_distance` (exact closest triangle through an AABB tree; sign from
the angle-weighted pseudonormal, sound for the watertight meshes twin.morphpatch.shapes
accepts). Measured here (2 cores): the cylinder's 0.85e6 grid points take 0.8 s
with the pseudonormal sign, 1.3 s with libigl's default and 8 s with its fast
winding number; trimesh.proximity.signed_distance takes 9.6 s for 2e4 of the
torus's points (about 8 min for a grid) and agrees to 1e-16 m; pysdf does not
build here. The closest surface points libigl returns also put the
high-curvature points exactly on the surface.

Queries are the approximation's hot path:
- `Fields.sdf_grad(points)`: trilinear interpolation of S and of its gradient
  (central differences on the grid), in one numba loop (`_trilinear`): 1500
  points take about 200-350 us as vectorised numpy (eight fancy-index gathers)
  and about 45 us compiled. The compiled approximation and refinement call the
  same kernel, `_interpolate(Fields.grid, x, y, z)`, point by point as they place
  their samples; `_gradient_sum` sums the gradients at rigidly placed points, the
  pipeline's inner step.
  Outside the grid the value is S at the nearest grid point plus the distance to
  it (an upper bound; the grid's margin keeps the device inside in normal use).
- `Fields.hcevf(points)`: the High-Curvature Edge Vector Field as the paper
  defines it. Curvature kappa = tr(H(S)) (7-point Laplacian, 1/m). High-curvature
  points: grid points within one cell of the surface with |kappa| >= `min_curvature`
  both at the point and averaged over CURVATURE_SCALE (a Gaussian), moved onto the
  surface (their exact closest surface point; our refinement, so that hinge lines are
  drawn to the edge itself, not a cell beside it). The average tells a ridge from
  tessellation: each facet edge of a smooth mesh bends S's gradient by a few degrees
  within one cell, so kappa spikes above the threshold there (a tessellated ellipsoid
  had 52 such points, the torus 1068), while over a few facets it is the surface's
  true curvature (below 41 1/m on both); at a real edge it stays in the hundreds.
  For each grid point x_g the nearest high-curvature point e* within `edge_radius` is stored;
  V(x_g) = e* - x_g, or 0 if there is none. A query point q reuses its nearest
  grid point's target edge: V(q) = e*(round(q)) - q (`_hcevf_at(Fields.edge_grid, x, y, z)`,
  compiled).

Size: a grid of more than MAX_GRID_POINTS points is built coarser instead (its spacing
the smallest that stays within it, said on stderr): a 1 m box at 3 mm is 64 million points
and 7.6 GB to build; the device, 188 x 175 mm, lies on a face either way, and trilinear
interpolation of a flat face's distance is exact at any spacing.

Caching: `build_fields` keeps the last MEMORY_ENTRIES built fields in memory, keyed by a
hash of the mesh's vertices and faces and the build parameters, and on disk as .npz under
$VRSCROLL_CACHE (default ~/.cache/vrscroll/fields), so the command line does not
rebuild them on every call. The disk cache is capped (CACHE_CAP bytes: the least
recently used files go first; `vrscroll cache` shows and clears it). A cache file is
trusted only once checked (`_checked`): its version, the mesh's key stored inside it,
every array's shape and type, finite values, the grid the mesh and parameters give
(origin, spacing, size), the distance positive at the grid's corners (outside the mesh by
the margin: a negated field fails), every edge index within the edge list. Anything else
is rebuilt, with a one-line notice; no unchecked array reaches compiled code.
"""

from __future__ import annotations

import hashlib
import math
import os
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import igl
import numba
import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

from twin.device.spec import load_spec
from twin.paths import cache_dir

GRID_SPACING = 0.003  # m, default spacing of the SDF grid
MARGIN = 0.1  # m, grid padding around the mesh's bounding box (the device's half length)
MIN_CURVATURE = 1.0 / 0.015  # 1/m: |tr H| of a ridge sharper than a 15 mm radius cylinder
CURVATURE_SCALE = 0.003  # m: Gaussian sigma over which a ridge's curvature must persist (a few facets' width)
PATH_DEPTH = 1e-3  # m: an anchor's path may graze the target this deep (the grid's error), no deeper
PATH_STEP = 1e-3  # m between the samples of such a path
LIPSCHITZ = 3.0  # S on the grid changes by at most this many metres per metre along a line: the exact distance at
# the grid's points differs by at most the spacing between neighbours, so each component of the trilinear gradient is
# at most 1 (|grad S| <= sqrt 3), and beyond the grid the distance outside adds at most 1. The walks along a line
# (`_path_clear`, `_path_dip`, the refinement's flaps through) skip the samples S cannot change their answer at
CHORD_DEPTH = 2e-3  # m: a straight line across the refinement's whole slide may dip this deep (a chord of a curved
# surface the anchor slid along: 20 mm on a 25 mm radius dips 2 mm), short of the 2.5 mm the exact mesh is held to
_VERSION = 3  # bump when the stored arrays change meaning (3: the key and version stored inside the file)
MAX_GRID_POINTS = 4_000_000  # a grid with more points is built coarser (module docstring): about 0.6 GB to build
MEMORY_ENTRIES = 8  # built fields kept in memory
CACHE_CAP = 1_000_000_000  # bytes: the fields' disk cache is trimmed to this, least recently used first

_MEMORY: dict[str, "Fields"] = {}
FIELD_ARRAYS = ("origin", "spacing", "sdf", "edges", "edge_index", "curvature", "min_curvature", "edge_radius")
CACHE_ARRAYS = FIELD_ARRAYS + ("key", "version")
CHUNK = 1 << 18  # grid points per chunk of a field build
PROGRESS_AFTER = 1.0  # s: a field build that takes longer reports its progress on stderr, about once a second



class Fields:
    """Grids of one target: S, grad S, curvature and the HCEVF's target edges.

    origin (3,) m: world position of grid point (0, 0, 0); spacing m; shape (nx, ny, nz).
    sdf (nx, ny, nz) m; curvature (nx, ny, nz) 1/m; edges (E, 3) m: the
    high-curvature surface points; edge_index (nx, ny, nz) int: per grid point
    the index into `edges` of its target edge, -1 if none within edge_radius.
    """

    def __init__(self, origin, spacing, sdf, edges, edge_index, curvature, min_curvature, edge_radius):
        self.origin = np.asarray(origin, float)
        self.spacing = float(spacing)
        self.sdf = sdf
        self.curvature = curvature
        self.edges = edges
        self.edge_index = edge_index
        self.min_curvature = float(min_curvature)
        self.edge_radius = float(edge_radius)
        self.shape = np.array(sdf.shape)
        self._strides = np.array([sdf.shape[1] * sdf.shape[2], sdf.shape[2], 1])
        grad = np.stack(np.gradient(sdf, self.spacing), axis=-1)
        self._value_grad = np.ascontiguousarray(np.concatenate([sdf[..., None], grad], axis=-1).reshape(-1, 4))
        self._values = np.ascontiguousarray(sdf, dtype=np.float64).ravel()
        # what compiled code reads: S and grad S (`_interpolate`), S alone (`_value`: a quarter of the memory a
        # sum of S reads, 4 samples to a cache line), and the HCEVF's target edges (`_hcevf_at`)
        self.grid = (self._value_grad, self.origin, self.spacing, self.shape, self._strides, self._values)
        self.edge_grid = (np.ascontiguousarray(edge_index.ravel(), dtype=np.int64),
                          np.ascontiguousarray(edges, dtype=np.float64).reshape(-1, 3),
                          self.origin, self.spacing, self.shape, self._strides)

    # ---- queries ---------------------------------------------------------------------
    def sdf_grad(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (N,) m and its gradient (N, 3) at points (N, 3) m, trilinear."""
        out = _trilinear(self.grid, np.ascontiguousarray(points, dtype=np.float64))
        return out[:, 0], out[:, 1:]

    def sdf_values(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (N,) m at points (N, 3) m."""
        return self.sdf_grad(points)[0]

    def hcevf(self, points: np.ndarray) -> np.ndarray:
        """HCEVF vectors (N, 3) m at points (N, 3) m: e*(nearest grid point) - q, 0 where none."""
        return _hcevf(self.edge_grid, np.ascontiguousarray(points, dtype=np.float64))

    def grid_points(self) -> np.ndarray:
        """World positions of all grid points, (nx*ny*nz, 3) m, in C order."""
        axes = [self.origin[d] + self.spacing * np.arange(self.shape[d]) for d in range(3)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)

    # ---- storage ---------------------------------------------------------------------
    def _arrays(self) -> dict[str, np.ndarray]:
        """The arrays stored in the disk cache (FIELD_ARRAYS)."""
        return {"origin": self.origin, "spacing": np.array(self.spacing), "sdf": self.sdf,
                "edges": self.edges, "edge_index": self.edge_index, "curvature": self.curvature,
                "min_curvature": np.array(self.min_curvature), "edge_radius": np.array(self.edge_radius)}

    @classmethod
    def _from_arrays(cls, a) -> "Fields":
        return cls(a["origin"], float(a["spacing"]), a["sdf"], a["edges"], a["edge_index"], a["curvature"],
                   float(a["min_curvature"]), float(a["edge_radius"]))


@numba.njit(cache=True, inline="always")
def _cell(coordinate, origin, spacing, n):
    """Grid cell index, fraction within it, and squared distance outside the grid (grid units)."""
    g = (coordinate - origin) / spacing
    c = min(max(g, 0.0), n - 1.000001)
    i = int(c)
    return i, c - i, (g - c) ** 2


@numba.njit(cache=True, inline="always")
def _interpolate(grid, x, y, z):
    """(S, dS/dx, dS/dy, dS/dz) at (x, y, z), m, trilinear on `Fields.grid`. Summed in scalars: stored
    through an array the compiler must assume may alias the grid, every partial sum went to memory and
    back (73 us for 1568 points where this takes 50)."""
    value_grad, _, spacing, _, strides, _ = grid
    base, fx, fy, fz, outside2 = _located(grid, x, y, z)
    v = gx = gy = gz = 0.0
    for corner in range(8):
        w, idx = _corner(base, strides, fx, fy, fz, corner)
        v += w * value_grad[idx, 0]
        gx += w * value_grad[idx, 1]
        gy += w * value_grad[idx, 2]
        gz += w * value_grad[idx, 3]
    if outside2 > 0.0:
        v += np.sqrt(outside2) * spacing
    return v, gx, gy, gz


@numba.njit(cache=True, inline="always")
def _value(grid, x, y, z):
    """S at (x, y, z), m: `_interpolate`'s first value, the same sum in the same order (so the same number), read
    from the S array alone. A sum over the refinement's 1568 samples is bound by the cells it reads, not by its
    arithmetic: the S and gradient array of a corpus shape (78 MB) does not stay in the cache between trials, S alone
    (20 MB) does."""
    _, _, spacing, _, strides, values = grid
    base, fx, fy, fz, outside2 = _located(grid, x, y, z)
    v = 0.0
    for corner in range(8):
        w, idx = _corner(base, strides, fx, fy, fz, corner)
        v += w * values[idx]
    if outside2 > 0.0:
        v += np.sqrt(outside2) * spacing
    return v


@numba.njit(cache=True, inline="always")
def _located(grid, x, y, z):
    """Where (x, y, z) (m) lies on `Fields.grid`: (its cell's first point's index in the flat arrays, the fractions
    within the cell along x, y, z, the squared distance outside the grid in grid units)."""
    _, origin, spacing, shape, strides, _ = grid
    i, fx, ox = _cell(x, origin[0], spacing, shape[0])
    j, fy, oy = _cell(y, origin[1], spacing, shape[1])
    k, fz, oz = _cell(z, origin[2], spacing, shape[2])
    return i * strides[0] + j * strides[1] + k * strides[2], fx, fy, fz, ox + oy + oz


@numba.njit(cache=True, inline="always")
def _corner(base, strides, fx, fy, fz, corner):
    """The trilinear weight of a cell's corner (0-7: bits x, y, z) and its index in the flat arrays."""
    a, b, e = (corner >> 2) & 1, (corner >> 1) & 1, corner & 1
    w = (fx if a else 1.0 - fx) * (fy if b else 1.0 - fy) * (fz if e else 1.0 - fz)
    return w, base + a * strides[0] + b * strides[1] + e * strides[2]


@numba.njit(cache=True)
def _path_clear(grid, a, b, depth=PATH_DEPTH):
    """Whether the segment a -> b (m) stays out of the target, to `depth` (m), sampled every PATH_STEP: the
    approximation's side guarantee (twin.morphpatch.approximation) and the refinement's steps. Samples S cannot
    reach -depth by (`LIPSCHITZ`) are skipped: the same answer as every sample's."""
    length = math.sqrt((b[0] - a[0]) ** 2 + (b[1] - a[1]) ** 2 + (b[2] - a[2]) ** 2)
    n = int(length / PATH_STEP) + 1
    reach = LIPSCHITZ * length / n  # the most S changes by from one sample to the next
    k = 0
    while k <= n:
        f = k / n
        v = _value(grid, a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2]))
        if v < -depth:
            return False
        k += max(1, int((v + depth) / reach)) if reach > 0.0 else n + 1
    return True


@numba.njit(cache=True)
def _path_dip(grid, a, b):
    """How deep (m) the segment a -> b (m) goes into the target at its deepest, sampled every PATH_STEP; 0 if it
    stays out. Samples S cannot reach the deepest so far by (`LIPSCHITZ`) are skipped: the same depth."""
    length = math.sqrt((b[0] - a[0]) ** 2 + (b[1] - a[1]) ** 2 + (b[2] - a[2]) ** 2)
    n = int(length / PATH_STEP) + 1
    reach = LIPSCHITZ * length / n
    lowest = 0.0
    k = 0
    while k <= n:
        f = k / n
        v = _value(grid, a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2]))
        lowest = min(lowest, v)
        k += max(1, int((v - lowest) / reach)) if reach > 0.0 else n + 1
    return -lowest


@numba.njit(cache=True)
def _trilinear(grid, points):
    """S and grad S (N, 4) at points (N, 3), m; grid: `Fields.grid`."""
    out = np.empty((points.shape[0], 4))
    for p in range(points.shape[0]):
        out[p, 0], out[p, 1], out[p, 2], out[p, 3] = _interpolate(grid, points[p, 0], points[p, 1], points[p, 2])
    return out


@numba.njit(cache=True)
def _gradient_sum(grid, local, rot, pos):
    """Sum (3,) of grad S at rot @ p + pos for the points p (N, 3) of `local`; grid: `Fields.grid`."""
    tx = ty = tz = 0.0
    for p in range(local.shape[0]):
        x = pos[0] + rot[0, 0] * local[p, 0] + rot[0, 1] * local[p, 1] + rot[0, 2] * local[p, 2]
        y = pos[1] + rot[1, 0] * local[p, 0] + rot[1, 1] * local[p, 1] + rot[1, 2] * local[p, 2]
        z = pos[2] + rot[2, 0] * local[p, 0] + rot[2, 1] * local[p, 1] + rot[2, 2] * local[p, 2]
        _, gx, gy, gz = _interpolate(grid, x, y, z)
        tx += gx
        ty += gy
        tz += gz
    return np.array([tx, ty, tz])


@numba.njit(cache=True, inline="always")
def _nearest(coordinate, origin, spacing, n):
    """Index of the grid point nearest to a coordinate, clipped into the grid."""
    return int(min(max(np.rint((coordinate - origin) / spacing), 0.0), n - 1.0))


@numba.njit(cache=True, inline="always")
def _hcevf_at(edge_grid, x, y, z):
    """The HCEVF vector (m) at (x, y, z), its nearest grid point's target edge minus the point, as (vx, vy,
    vz); 0 where there is none. edge_grid: `Fields.edge_grid`."""
    edge_index, edges, origin, spacing, shape, strides = edge_grid
    flat = (_nearest(x, origin[0], spacing, shape[0]) * strides[0] + _nearest(y, origin[1], spacing, shape[1])
            * strides[1] + _nearest(z, origin[2], spacing, shape[2]) * strides[2])
    e = edge_index[flat]
    if e < 0:
        return 0.0, 0.0, 0.0
    return edges[e, 0] - x, edges[e, 1] - y, edges[e, 2] - z


@numba.njit(cache=True)
def _hcevf(edge_grid, points):
    out = np.empty((points.shape[0], 3))
    for p in range(points.shape[0]):
        out[p, 0], out[p, 1], out[p, 2] = _hcevf_at(edge_grid, points[p, 0], points[p, 1], points[p, 2])
    return out


def mesh_key(mesh: trimesh.Trimesh, **params) -> str:
    """Hash of a mesh's geometry and the build parameters (hex string)."""
    h = hashlib.sha1()
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    h.update(repr(sorted(params.items()) + [_VERSION]).encode())
    return h.hexdigest()


def save_npz(path: Path, arrays: dict) -> None:
    """Write arrays to path atomically; concurrent writers (worker processes) each use their own temp file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".npz.part")
    with os.fdopen(fd, "wb") as f:
        np.savez(f, **arrays)
    os.replace(tmp, path)


def load_npz(path: Path, required=()) -> dict | None:
    """A cache file's arrays, or None when there is none or it is damaged (cut short, empty, keys
    missing): then a one-line notice goes to stderr, and the caller builds and saves it again."""
    if not path.is_file():
        return None
    try:
        with np.load(path) as data:
            arrays = {k: data[k] for k in data.files}
        missing = [k for k in required if k not in arrays]
        if missing:
            raise KeyError(f"no {missing[0]!r}")
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as exc:
        print(f"vrscroll: cache file {path} is damaged ({type(exc).__name__}: {exc}); building it again",
              file=sys.stderr, flush=True)
        return None
    return arrays


def build_fields(mesh: trimesh.Trimesh, spacing: float = GRID_SPACING, margin: float = MARGIN,
                 min_curvature: float = MIN_CURVATURE, edge_radius: float | None = None,
                 disk_cache: bool = True) -> Fields:
    """The fields of a watertight mesh (metres) on a grid of `spacing` m (coarser where that grid would have
    more than MAX_GRID_POINTS points: `grid_spacing`) padded by `margin` m.

    edge_radius: the HCEVF's distance threshold, m; default half the device's flap
    pitch, so that any edge attracts the one hinge line nearest to it.
    Cached in memory and (unless disk_cache is False) on disk; see the module docstring.
    """
    if edge_radius is None:
        edge_radius = load_spec().flap_pitch / 2
    spacing = grid_spacing(mesh, spacing, margin)
    key = mesh_key(mesh, spacing=spacing, margin=margin, min_curvature=min_curvature, edge_radius=edge_radius)
    if key in _MEMORY:
        _MEMORY[key] = _MEMORY.pop(key)  # the most recently used last
        return _MEMORY[key]
    path = cache_dir("fields") / f"{key}.npz"
    arrays = load_npz(path, CACHE_ARRAYS) if disk_cache else None
    fields = _checked(arrays, key, mesh, spacing, margin, path) if arrays is not None else None
    if fields is not None:
        os.utime(path)  # used now: trimmed last
    else:
        fields = _compute(mesh, spacing, margin, min_curvature, edge_radius)
        if disk_cache:
            save_npz(path, {**fields._arrays(), "key": np.array(key), "version": np.array(_VERSION)})
            trim_cache(cache_dir("fields"), CACHE_CAP, keep=path)
    _MEMORY[key] = fields
    while len(_MEMORY) > MEMORY_ENTRIES:
        del _MEMORY[next(iter(_MEMORY))]
    return fields


def grid_spacing(mesh: trimesh.Trimesh, spacing: float = GRID_SPACING, margin: float = MARGIN) -> float:
    """The spacing (m) of a mesh's grid: `spacing`, or where that grid over the bounding box padded by `margin`
    would have more than MAX_GRID_POINTS points, the smallest (to 0.1 mm) that keeps it within them."""
    size = np.asarray(mesh.extents, float) + 2 * margin
    fine = spacing

    def points(h):
        return float(np.prod(np.ceil(size / h) + 1))
    if points(spacing) > MAX_GRID_POINTS:
        spacing = math.ceil(float(np.prod(size) / MAX_GRID_POINTS) ** (1 / 3) * 1e4) / 1e4
        while points(spacing) > MAX_GRID_POINTS:
            spacing += 1e-4
    if spacing != fine:
        print(f"vrscroll: the target is {size.max() - 2 * margin:.3g} m across: its fields on a {spacing * 1e3:.1f} mm "
              f"grid, not {fine * 1e3:g} mm (at most {MAX_GRID_POINTS:,} grid points)", file=sys.stderr, flush=True)
    return spacing


def _checked(arrays: dict, key: str, mesh: trimesh.Trimesh, spacing: float, margin: float, path: Path) -> Fields | None:
    """Fields from a cache file's arrays if they are this mesh's as `_compute` would build them (module
    docstring), else None with a one-line notice on stderr."""
    why = _cache_problem(arrays, key, mesh, spacing, margin)
    if why is None:
        return Fields._from_arrays(arrays)
    print(f"vrscroll: cache file {path} is not this target's fields ({why}); building it again", file=sys.stderr,
          flush=True)
    return None


def _cache_problem(a: dict, key: str, mesh: trimesh.Trimesh, spacing: float, margin: float) -> str | None:
    """What is wrong with a cache file's arrays, or None."""
    def scalar(name, kind):
        v = a[name]
        return v.shape == () and v.dtype.kind in kind
    if not (scalar("version", "iu") and int(a["version"]) == _VERSION):
        return "another version"
    if not (scalar("key", "U") and str(a["key"]) == key):
        return "another mesh's or parameters' key"
    for name in ("spacing", "min_curvature", "edge_radius"):
        if not (scalar(name, "f") and math.isfinite(float(a[name])) and float(a[name]) > 0):
            return f"{name} is not a positive number"
    lo, shape = _grid_of(mesh, spacing, margin)
    if float(a["spacing"]) != spacing or a["origin"].shape != (3,) or a["origin"].dtype.kind != "f" or \
            not np.allclose(a["origin"], lo, rtol=0, atol=1e-9):
        return "another grid's origin or spacing"
    for name in ("sdf", "curvature"):
        if a[name].shape != tuple(shape) or a[name].dtype.kind != "f" or not np.all(np.isfinite(a[name])):
            return f"{name} is not finite numbers on the grid"
    sdf = a["sdf"]
    if min(sdf[i, j, k] for i in (0, -1) for j in (0, -1) for k in (0, -1)) <= 0 or sdf.min() >= 0:
        return "the distance's sign is wrong"
    edges, index = a["edges"], a["edge_index"]
    if edges.ndim != 2 or edges.shape[1] != 3 or edges.dtype.kind != "f" or not np.all(np.isfinite(edges)):
        return "the edges are not finite points"
    if index.shape != tuple(shape) or index.dtype.kind not in "iu" or index.min() < -1 or index.max() >= len(edges):
        return "an edge index is outside the edge list"
    return None


def _grid_of(mesh: trimesh.Trimesh, spacing: float, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """The grid's origin (3,) m and shape (3,) for a mesh: its bounding box padded by margin, at spacing."""
    lo = mesh.bounds[0] - margin
    return lo, np.ceil((mesh.bounds[1] + margin - lo) / spacing).astype(int) + 1


def cache_files(folder: Path) -> list[Path]:
    """The cache's files under a folder, least recently used first (modification time: a load touches it)."""
    files = [p for p in folder.rglob("*") if p.is_file()] if folder.is_dir() else []
    return sorted(files, key=lambda p: p.stat().st_mtime)


def trim_cache(folder: Path, cap: int, keep: Path | None = None) -> list[Path]:
    """Remove the least recently used files under folder until they take at most `cap` bytes (never `keep`);
    the files removed."""
    files = cache_files(folder)
    total = sum(p.stat().st_size for p in files)
    removed = []
    for p in files:
        if total <= cap:
            break
        if p == keep:
            continue
        total -= p.stat().st_size
        p.unlink(missing_ok=True)
        removed.append(p)
    return removed


def exact_signed_distance(mesh: trimesh.Trimesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact signed distance (N,) m, negative inside, and closest surface points (N, 3) m."""
    s, closest, _ = exact_surface_query(mesh, points)
    return s, closest


def exact_surface_query(mesh: trimesh.Trimesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact signed distance (N,) m, closest surface points (N, 3) m and the surface's outward
    pseudonormal there (N, 3): the face normal inside a face, the mean of the faces' normals on an
    edge, their angle-weighted mean at a vertex."""
    s, _, closest, normals = _signed_distance(mesh, points)
    return s, closest, normals


def exact_closest_faces(mesh: trimesh.Trimesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact signed distance (N,) m and the index (N,) of the mesh's face nearest each point."""
    s, faces, _, _ = _signed_distance(mesh, points)
    return s, faces


def _signed_distance(mesh: trimesh.Trimesh, points: np.ndarray):
    """libigl's signed distance (pseudonormal sign): distances, nearest faces, closest points, pseudonormals."""
    return igl.signed_distance(np.ascontiguousarray(points, dtype=np.float64),
                               np.ascontiguousarray(mesh.vertices, dtype=np.float64),
                               np.ascontiguousarray(mesh.faces, dtype=np.int64),
                               sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)


class _Progress:
    """Prints "<what>: NN % (T s)" on stderr about once a second, once the build has taken
    PROGRESS_AFTER s; done and total count grid points whose distance is known (most of a build's time)."""

    def __init__(self, total: int, what: str):
        self.total, self.what = total, what
        self.start = self.last = time.perf_counter()

    def __call__(self, done: int) -> None:
        now = time.perf_counter()
        if now - self.start >= PROGRESS_AFTER and now - self.last >= min(PROGRESS_AFTER, 1.0):
            self.last = now
            print(f"{self.what}: {min(done, self.total) / self.total:4.0%} ({now - self.start:.0f} s)",
                  file=sys.stderr, flush=True)


def _compute(mesh, spacing, margin, min_curvature, edge_radius) -> Fields:
    lo, shape = _grid_of(mesh, spacing, margin)
    empty = Fields(lo, spacing, np.zeros(shape), np.zeros((0, 3)), np.full(shape, -1), np.zeros(shape),
                   min_curvature, edge_radius)
    points = empty.grid_points()
    progress = _Progress(len(points), f"fields of a {len(mesh.faces):,}-face mesh on {len(points):,} grid points")
    # in chunks: a large mesh's build shows its progress, and the distance query's scratch stays small
    sdf, closest = np.empty(len(points)), np.empty((len(points), 3))
    for i in range(0, len(points), CHUNK):
        sdf[i:i + CHUNK], closest[i:i + CHUNK] = exact_signed_distance(mesh, points[i:i + CHUNK])
        progress(i + CHUNK)
    sdf = sdf.reshape(shape)
    padded = np.pad(sdf, 1, mode="edge")
    curvature = (padded[2:, 1:-1, 1:-1] + padded[:-2, 1:-1, 1:-1] + padded[1:-1, 2:, 1:-1]
                 + padded[1:-1, :-2, 1:-1] + padded[1:-1, 1:-1, 2:] + padded[1:-1, 1:-1, :-2]
                 - 6.0 * sdf) / spacing**2
    high = (np.abs(sdf) <= spacing) & (np.abs(curvature) >= min_curvature) & (
        np.abs(ndimage.gaussian_filter(curvature, CURVATURE_SCALE / spacing, mode="nearest")) >= min_curvature)
    edges = np.unique(np.round(closest[high.ravel()] / 1e-6) * 1e-6, axis=0)  # on the surface, deduplicated
    edge_index = np.full(sdf.size, -1, dtype=np.int32)
    if len(edges):
        tree = cKDTree(edges)
        for i in range(0, len(points), CHUNK):
            dist, idx = tree.query(points[i:i + CHUNK], distance_upper_bound=edge_radius, workers=-1)
            found = np.isfinite(dist)
            edge_index[i:i + CHUNK][found] = idx[found]
    return Fields(lo, spacing, sdf, edges, edge_index.reshape(shape), curvature, min_curvature, edge_radius)
