"""Target shapes for the surface approximation: the paper's eight, and any mesh file.

`load_shape(name)` builds one of the shapes in models/shapes/shapes.toml as a
watertight trimesh (metres, resting on z = 0). `load_mesh(path)` reads any file
trimesh reads (STL, OBJ, PLY, GLB, ...) and checks it is usable as a target;
anything wrong raises `MeshError` with a message saying what and how to fix it.
"""

from __future__ import annotations

import math
import tomllib
from functools import lru_cache
from pathlib import Path

import igl
import numpy as np
import trimesh

from twin.paths import MODELS_DIR

SHAPES_PATH = MODELS_DIR / "shapes" / "shapes.toml"

START_HEIGHT = 0.04  # m: a mesh's default start is this far above its top (mesh_start)
TOP_BAND = 0.002  # m: the top of a mesh is its upward faces within this of its highest point
TOP_SUPPORT = 0.002  # m: a start is over a point of the top with solid this far under it (at least half of it)
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


def mesh_start(mesh: trimesh.Trimesh) -> list[float]:
    """The default start for a mesh file, [x, y, z mm, roll, pitch, yaw deg]: the device level (its touch
    surface facing down, -z), START_HEIGHT above the top of the object, over the point of the top nearest
    the top's middle that has solid under it (TOP_SUPPORT): where a hand lowering the device onto the object
    first meets it (a box's top face's middle, a sphere's pole, a point of a cup's rim, never the open middle
    of a cup). Ties go to the larger x, then y, so the start does not depend on the order of the faces."""
    top = mesh.vertices[:, 2].max()
    up = (mesh.face_normals[:, 2] > 0.5) & (mesh.triangles_center[:, 2] >= top - TOP_BAND)
    if not up.any():  # no upward face at the top (a point, an edge): over its highest vertex
        x, y = mesh.vertices[np.argmax(mesh.vertices[:, 2]), :2]
        return [float(x) * 1e3, float(y) * 1e3, float(top + START_HEIGHT) * 1e3, 0.0, 0.0, 0.0]
    triangles = mesh.triangles[up]
    middle = np.average(mesh.triangles_center[up], axis=0, weights=mesh.area_faces[up])
    nearest = trimesh.triangles.closest_point(triangles, np.tile(middle, (len(triangles), 1)))
    candidates = np.vstack([nearest, mesh.triangles_center[up]])
    below = candidates - [0.0, 0.0, TOP_SUPPORT]
    supported = igl.signed_distance(below, mesh.vertices, mesh.faces)[0] < -TOP_SUPPORT / 2
    if supported.any():
        candidates = candidates[supported]
    d = np.round(np.linalg.norm(candidates[:, :2] - middle[:2], axis=1), 4)  # to 0.1 mm: ties
    x, y = candidates[np.lexsort((-candidates[:, 1], -candidates[:, 0], d))[0], :2]
    return [float(x) * 1e3, float(y) * 1e3, float(top + START_HEIGHT) * 1e3, 0.0, 0.0, 0.0]


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
