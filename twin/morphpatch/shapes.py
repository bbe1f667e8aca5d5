"""Target shapes for the surface approximation: the paper's eight, and any mesh file.

`load_shape(name)` builds one of the shapes in models/shapes/shapes.toml as a
watertight trimesh (metres, resting on z = 0). `load_mesh(path)` reads any file
trimesh reads (STL, OBJ, PLY, GLB, ...) and checks it is usable as a target;
anything wrong raises `MeshError` with a message saying what and how to fix it.
"""

from __future__ import annotations

import math
import tomllib
import warnings
from functools import lru_cache
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from twin.paths import MODELS_DIR

SHAPES_PATH = MODELS_DIR / "shapes" / "shapes.toml"

START_HEIGHT = 0.04  # m: a mesh's starts are this far out from the side each faces (side_starts)
SIDE_BAND = 0.05  # m: an open cell's surface lies within this of the convex hull (a cup's floor is 92 mm below its
# rim, a saddle's centre 42 mm below the hull over its high corners: the device curls into a saddle, not a cup)
SIDE_FACING = math.radians(30)  # an open cell's surface faces the device within this (a torus's top, not its slope)
SIDE_CELL = 0.005  # m: the cells of the depth image a side is seen in ...
SIDE_CELLS = 200  # ... or the mesh's size over this, where larger (a 5 m mesh: 25 mm)
SIDE_SAMPLES = 50_000  # surface samples (and the vertices) the sides are seen by
SIDE_TIE = 0.9  # of the sides at least this share of the broadest one's area, the one most from above
AXES_TIE = 0.02  # principal moments within this share of the largest are equal (`_principal_axes`)
FROM_BELOW = 0.5  # no default start approaches upwards by more than this sine (30 deg): from under an object
MIN_SIZE = 0.002  # m: a target whose bounding box is smaller than this is an error (a 1 cm sphere is a target)
MAX_SIZE = 5.0  # m: ... or larger than this


class MeshError(ValueError):
    """A target mesh that cannot be used (empty, not a mesh, not closed, absurd size, NaN)."""


@lru_cache(maxsize=1)
def shape_table() -> dict[str, dict]:
    """Name -> entry of models/shapes/shapes.toml (lengths in m, `start` in mm and deg)."""
    with open(SHAPES_PATH, "rb") as f:
        return tomllib.load(f)


def shape_names() -> list[str]:
    return list(shape_table())


def load_shape(name: str) -> trimesh.Trimesh:
    """The named evaluation shape as a watertight mesh, metres."""
    table = shape_table()
    if name not in table:
        raise MeshError(f"unknown shape {name!r}; known shapes: {', '.join(table)}")
    entry = table[name]
    mesh = _BUILDERS[entry["kind"]](entry)
    if mesh.volume < 0:  # sweeps come out consistently wound, but maybe inside out
        mesh.invert()
    return check_mesh(mesh, name)


def side_starts(mesh: trimesh.Trimesh) -> list[list[float]]:
    """The starts a person would bring the device to a mesh from, [x, y, z mm, roll, pitch, yaw deg] each, the
    broadest side's first: each facing one of the mesh's sides, over the open surface nearest its middle,
    START_HEIGHT out from it (issue 37; twin.morphpatch.default_start picks among them).

    The sides are seen along the mesh's principal axes (of inertia), both ways, and straight down (a hand
    lowering the device onto an object on a table); none from below (approaching upwards by more than
    FROM_BELOW). Each side is a depth image of square cells (SIDE_CELL, or 1/SIDE_CELLS of the mesh's size where
    that is larger): its area is the mesh's silhouette seen that way; its open cells are those whose surface,
    first met, faces the device (within SIDE_FACING) and lies within SIDE_BAND of the convex hull met on the
    same line (not down a cavity: a cup's floor, a torus's hole). Sides come broadest first (of those within
    SIDE_TIE of the broadest, the one most from above first: a sphere, a bar, a box from above; a plate on its
    face; a cup taller than wide on its wall). Each start is over its side's open cell nearest the silhouette's
    middle (a saddle's centre, a point of a cup's rim, never its open middle), START_HEIGHT beyond the side's
    nearest point, the device's -z along the side's direction, its row (x) along the larger of the side's two
    extents. Ties go to the larger coordinates, and the surface samples are seeded: the same mesh gives the
    same starts."""
    samples, faces = trimesh.sample.sample_surface(mesh, SIDE_SAMPLES, seed=0)
    points = np.vstack([samples, mesh.vertices]) - mesh.center_mass
    normals = np.vstack([mesh.face_normals[faces], mesh.vertex_normals])
    hull = mesh.convex_hull
    planes = np.c_[hull.face_normals, np.einsum("ij,ij->i", hull.face_normals, hull.triangles[:, 0] - mesh.center_mass)]
    cell = max(SIDE_CELL, float(mesh.extents.max()) / SIDE_CELLS)
    axes = _principal_axes(mesh)
    sides = [(sign * axes[i], axes[(i + 1) % 3]) for i in range(3) for sign in (1.0, -1.0)]
    sides.append((np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, 0.0])))
    seen = [(d, a) + _side(points, normals, planes, d, a, cell) for d, a in sides if d[2] <= FROM_BELOW]
    broadest = max(s[2] for s in seen)
    seen.sort(key=lambda s: (s[2] < SIDE_TIE * broadest, round(float(s[0][2]), 6) if s[2] >= SIDE_TIE * broadest
                             else -s[2]))  # stable: the first of equals
    return [_start(mesh, points, *s) for s in seen]


def _start(mesh, points, d, a, area, near, middle, across) -> list[float]:
    """The start facing a side (`_side`'s results along d, a) over its open cell nearest its middle."""
    distance = np.round(np.linalg.norm(across - middle, axis=1), 4)  # to 0.1 mm: ties
    u, v = across[np.lexsort((-across[:, 1], -across[:, 0], distance))[0]]
    b = np.cross(d, a)
    position = mesh.center_mass + u * a + v * b + (near - START_HEIGHT) * d
    x = a if np.ptp(points @ a) >= np.ptp(points @ b) else b
    rotation = np.column_stack([x, np.cross(-d, x), -d])
    with warnings.catch_warnings():  # a gimbal lock (pitch +-90 deg) is said by an angle of 0, which is right
        warnings.simplefilter("ignore", UserWarning)
        angles = Rotation.from_matrix(rotation).as_euler("xyz", degrees=True)
    return [round(float(c), 3) for c in position * 1e3] + [round(float(c), 3) for c in angles]


def _principal_axes(mesh: trimesh.Trimesh) -> np.ndarray:
    """The mesh's principal axes of inertia (rows), each sign fixed (its largest component positive). Where moments
    are within AXES_TIE of each other their axes are any in their plane (a body of revolution, a cube, a sphere),
    and a file read again (an STL's float32 vertices) turns them at random: there they are the world's axes
    (all three equal), or the unequal one and the world axis (z, x, y first) nearest the plane of the two equal."""
    moments = np.asarray(mesh.principal_inertia_components, float)
    axes = np.array(mesh.principal_inertia_vectors, float)
    tie = AXES_TIE * moments.max()
    equal = [abs(moments[(i + 1) % 3] - moments[(i + 2) % 3]) <= tie for i in range(3)]
    if sum(equal) >= 2:
        return np.eye(3)
    if any(equal):
        unique = axes[equal.index(True)]
        world = np.eye(3)[[2, 0, 1]]
        along = np.linalg.norm(world - np.outer(world @ unique, unique), axis=1)
        e = world[np.flatnonzero(along >= along.max() - 1e-3)[0]]
        a = e - (e @ unique) * unique
        a /= np.linalg.norm(a)
        axes = np.array([unique, a, np.cross(unique, a)])
    return axes * np.sign(axes[np.arange(3), np.argmax(np.abs(axes) + 1e-9 * np.arange(3), axis=1)])[:, None]


def _side(points, normals, planes, d, a, cell):
    """The mesh's side seen along d (a unit vector; a, another, across it) from its surface `points` (m) and
    their `normals`, its convex hull's `planes` (n, 4: unit normal, offset m): (its area m^2, the depth along d
    of its nearest point m, its silhouette's middle (u, v) m, its open cells' (u, v) (k, 2) m, along a and
    d x a)."""
    b = np.cross(d, a)
    uv, depth = np.c_[points @ a, points @ b], points @ d
    index = np.floor(uv / cell).astype(np.int64)
    low = index.min(axis=0)
    key = (index[:, 0] - low[0]) * (index[:, 1].max() - low[1] + 1) + index[:, 1] - low[1]
    order = np.lexsort((depth, key))
    first = order[np.r_[True, key[order][1:] != key[order][:-1]]]  # per cell, the sample met first along d
    centre = (index[first] + 0.5) * cell
    facing = normals[first] @ -d >= math.cos(SIDE_FACING)
    open_ = facing & (depth[first] - _hull_depth(planes, centre, d, a, b) <= SIDE_BAND)
    if not open_.any():  # nothing faces the device: its nearest surface then
        open_ = depth[first] == depth[first].min()
    return len(first) * cell ** 2, float(depth[first].min()), centre.mean(axis=0), uv[first[open_]]


def _hull_depth(planes, uv, d, a, b):
    """Where lines along d through (u, v) (k, 2) m first meet a convex hull of `planes` (n, 4): the depth along
    d (m), in chunks of cells (the hull of a scanned mesh has thousands of faces)."""
    out = np.empty(len(uv))
    facing = planes[planes[:, :3] @ d < 0]  # a line along d enters through the planes facing against it
    nd = facing[:, :3] @ d
    for lo in range(0, len(uv), 4096):
        p = uv[lo:lo + 4096, :1] * a + uv[lo:lo + 4096, 1:] * b  # the lines' points at depth 0
        out[lo:lo + 4096] = ((facing[:, 3] - p @ facing[:, :3].T) / nd).max(axis=1)
    return out


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """Read a mesh file (metres) and check it: MeshError if it cannot serve as a target."""
    path = Path(path)
    if path.is_dir():
        raise MeshError(f"{path}: is a directory, not a mesh file")
    if not path.is_file():
        raise MeshError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise MeshError(f"{path}: the file is empty")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)  # unprocessed: NaN vertices still there
    except Exception as exc:  # trimesh raises many types for unreadable input
        raise MeshError(f"{path}: not a mesh trimesh can read ({type(exc).__name__}: {exc})") from exc
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshError(f"{path}: holds no triangle mesh (got {type(loaded).__name__})")
    check_finite(loaded, str(path))
    loaded.process()  # merge duplicate vertices (STL stores each triangle's own)
    return check_mesh(loaded, str(path))


def check_finite(mesh: trimesh.Trimesh, name: str = "mesh") -> None:
    """MeshError unless the mesh has triangles and all its vertices are finite numbers."""
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise MeshError(f"{name}: no triangles (empty or not a mesh)")
    bad = int(np.sum(~np.isfinite(mesh.vertices).all(axis=1)))
    if bad:
        raise MeshError(f"{name}: {bad} vertices are NaN or infinite")


def check_mesh(mesh: trimesh.Trimesh, name: str = "mesh") -> trimesh.Trimesh:
    """Validate a target mesh; returns it unchanged or raises MeshError."""
    check_finite(mesh, name)
    size = float(np.max(mesh.extents))
    if size < MIN_SIZE or size > MAX_SIZE:  # the size as read, in metres and in mm; no guess at the file's units
        raise MeshError(f"{name}: largest extent {size:.4g} m ({size * 1e3:.4g} mm, the file read in metres) is "
                        + (f"below the {MIN_SIZE * 1e3:g} mm" if size < MIN_SIZE else f"above the {MAX_SIZE:g} m")
                        + " a target may span")
    if not mesh.is_watertight:
        raise MeshError(f"{name}: not watertight ({len(mesh.faces)} faces, open or non-manifold edges); "
                        "its inside is undefined, so no signed distance: close the holes first")
    volume = float(mesh.volume)
    if not volume > 0:  # inside-out: every signed distance flips, the device fits "inside" what it should rest on
        raise MeshError(f"{name}: " + ("inside-out (its faces' normals point inwards, volume "
                                       f"{volume * 1e9:.4g} mm^3): flip its faces (trimesh: mesh.invert())"
                                       if volume < 0 else "of zero volume: nothing to rest on"))
    return mesh


# ---- builders ---------------------------------------------------------------------------


def _box(e):
    return trimesh.creation.box(extents=e["size"], transform=_lift(e["size"][2] / 2))


def _torus(e):
    return trimesh.creation.torus(e["major_radius"], e["minor_radius"], major_sections=96, minor_sections=48,
                                  transform=_lift(e["minor_radius"]))


def _cone(e):
    return trimesh.creation.cone(e["radius"], e["height"], sections=96)


def _cylinder(e):
    along_y = trimesh.transformations.rotation_matrix(math.pi / 2, [1, 0, 0])
    along_y[2, 3] = e["radius"]
    return trimesh.creation.cylinder(e["radius"], e["length"], sections=96, transform=along_y)


def _ellipsoid(e):
    mesh = trimesh.creation.icosphere(subdivisions=4)
    mesh.apply_scale(e["radii"])
    mesh.apply_translation([0, 0, e["radii"][2]])
    return mesh


def _arch(e):
    """Half annulus in the x-z plane (centre at the origin), swept along y."""
    t = np.linspace(0.0, math.pi, 65)
    outer = e["outer_radius"] * np.c_[np.cos(t), np.sin(t)]
    inner = e["inner_radius"] * np.c_[np.cos(t[::-1]), np.sin(t[::-1])]
    half = e["depth"] / 2
    return sweep_solid(np.vstack([outer, inner]), [_xz_plane_at(y) for y in (-half, half)])


def _stairs_profile(steps, run, rise, start=0.0, descending=False):
    """Closed staircase polygon (u, z): `steps` treads of `run` from u = start, each `rise` higher."""
    heights = [(steps - i if descending else i + 1) * rise for i in range(steps)]
    pts = [(start, 0.0)]
    for i, h in enumerate(heights):
        pts += [(start + i * run, h), (start + (i + 1) * run, h)]
    pts.append((start + steps * run, 0.0))
    return np.array(pts)


def _stairs(e):
    n, run = e["steps"], e["run"]
    profile = _stairs_profile(n, run, e["rise"], start=-n * run / 2)
    return sweep_solid(profile, [_xz_plane_at(y) for y in (-e["width"] / 2, e["width"] / 2)])


def _curved_stairs(e):
    """Staircase profile in (radius, z), rising inwards, revolved about z over `sweep_deg`."""
    profile = _stairs_profile(e["steps"], e["run"], e["rise"], start=e["inner_radius"], descending=True)
    sweep = math.radians(e["sweep_deg"])
    angles = np.linspace(-sweep / 2, sweep / 2, 49)
    return sweep_solid(profile, [trimesh.transformations.rotation_matrix(a, [0, 0, 1]) @ _xz_plane_at(0.0)
                            for a in angles])


def _lift(z):
    t = np.eye(4)
    t[2, 3] = z
    return t


def _xz_plane_at(y):
    """Transform taking profile coordinates (u, v, 0) to the world point (u, y, v)."""
    t = np.array([[1.0, 0, 0, 0], [0, 0, 0, y], [0, 1, 0, 0], [0, 0, 0, 1]])
    return t


def sweep_solid(profile: np.ndarray, sections: list[np.ndarray]) -> trimesh.Trimesh:
    """Closed solid swept by a simple polygon (n, 2) through the 4x4 `sections`, capped at both ends."""
    if _area(profile) < 0:
        profile = profile[::-1]  # counter-clockwise, so sides and caps wind alike
    n, k = len(profile), len(sections)
    ring = np.c_[profile, np.zeros(n), np.ones(n)]
    vertices = np.vstack([(s @ ring.T).T[:, :3] for s in sections])
    i = np.arange(n)
    j = (i + 1) % n
    sides = []
    for s in range(k - 1):
        a, b = s * n + i, s * n + j
        sides += [np.c_[a, b, b + n], np.c_[a, b + n, a + n]]
    cap = _ear_clip(profile)
    faces = np.vstack(sides + [cap[:, ::-1], cap + (k - 1) * n])
    return trimesh.Trimesh(vertices, faces, process=True)


def _area(poly: np.ndarray) -> float:
    """Signed area of a polygon (n, 2): positive when counter-clockwise."""
    return 0.5 * float(np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1]))


def _ear_clip(poly: np.ndarray) -> np.ndarray:
    """Triangulate a simple counter-clockwise polygon (n, 2) by ear clipping: (n-2, 3) vertex indices."""
    idx = list(range(len(poly)))

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    tris = []
    while len(idx) > 3:
        for m in range(len(idx)):
            p, c, q = idx[m - 1], idx[m], idx[(m + 1) % len(idx)]
            if cross(poly[p], poly[c], poly[q]) <= 1e-15:
                continue  # reflex or flat corner: not an ear
            others = [r for r in idx if r not in (p, c, q)]
            if any(cross(poly[p], poly[c], poly[r]) >= 0 and cross(poly[c], poly[q], poly[r]) >= 0
                   and cross(poly[q], poly[p], poly[r]) >= 0 for r in others):
                continue
            tris.append((p, c, q))
            del idx[m]
            break
        else:
            raise MeshError("profile polygon is not simple")
    tris.append(tuple(idx))
    return np.array(tris)


_BUILDERS = {
    "box": _box,
    "torus": _torus,
    "cone": _cone,
    "cylinder": _cylinder,
    "ellipsoid": _ellipsoid,
    "arch": _arch,
    "stairs": _stairs,
    "curved_stairs": _curved_stairs,
}
