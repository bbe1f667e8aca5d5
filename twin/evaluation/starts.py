"""Seeded approach poses for the evaluation: where a user would bring the device to a target.

A start is drawn as the paper's users approached (their trajectories are not
published, so this is our documented stand-in):

1. a point on the target's surface, uniform by area, with its outward normal n;
2. a stand-off distance d, uniform in STANDOFF (m), along n: the anchor sits at p + d n;
3. the device's z axis (touch-surface normal) is n tilted by an angle uniform in
   [0, MAX_TILT] about a random axis perpendicular to n;
4. a yaw about that axis, uniform in [0, 2 pi); hinges flat;
5. only where a user approaches from: a draw whose anchor is below the support plane
   (the plane the target rests on, its lowest z) or inside the target (a stand-off
   across a concave region) is dropped and drawn again, in order, from the same stream.

The same seed gives the same starts on any machine (numpy's PCG64).

`target_and_start` is the one start a command is given (or the target's default) for its target.
"""

from __future__ import annotations

import math

import igl
import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from twin.device.spec import load_spec
from twin.errors import UserError
from twin.morphpatch.approximation import pose_from_mm_deg
from twin.morphpatch.default_start import default_start
from twin.morphpatch.fields import build_fields, exact_signed_distance
from twin.morphpatch.shapes import load_mesh, load_shape, shape_table

STANDOFF = (0.02, 0.06)  # m
MAX_TILT = math.radians(30.0)


def approach_starts(mesh: trimesh.Trimesh, n: int = 50, seed: int = 0) -> np.ndarray:
    """n start poses of the anchor (n, 4, 4), device frame in the world, from a seeded generator."""
    rng = np.random.default_rng(seed)
    support = mesh.bounds[0][2]
    poses = []
    while len(poses) < n:
        batch = _draw(mesh, rng, n)
        anchors = batch[:, :3, 3]
        keep = (anchors[:, 2] > support) & (exact_signed_distance(mesh, anchors)[0] > 0.0)
        poses += list(batch[keep])
    return np.array(poses[:n])


def _draw(mesh: trimesh.Trimesh, rng: np.random.Generator, n: int) -> np.ndarray:
    """n candidate starts (steps 1-4 of the module docstring), (n, 4, 4)."""
    areas = mesh.area_faces
    faces = rng.choice(len(areas), size=n, p=areas / areas.sum())
    tri = mesh.triangles[faces]
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    points = tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])
    normals = mesh.face_normals[faces]
    standoff = rng.uniform(*STANDOFF, n)
    tilt = rng.uniform(0.0, MAX_TILT, n)
    tilt_dir = rng.uniform(0.0, 2 * math.pi, n)
    yaw = rng.uniform(0.0, 2 * math.pi, n)
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        align = _z_to(normals[i])  # z -> n
        r = align * Rotation.from_rotvec(tilt[i] * np.array([math.cos(tilt_dir[i]), math.sin(tilt_dir[i]), 0.0]))
        r = r * Rotation.from_rotvec([0.0, 0.0, yaw[i]])
        poses[i, :3, :3] = r.as_matrix()
        poses[i, :3, 3] = points[i] + standoff[i] * normals[i]
    return poses


def _z_to(n: np.ndarray) -> Rotation:
    """A rotation taking +z to the unit vector n."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, n)
    s, c = np.linalg.norm(axis), float(np.dot(z, n))
    if s < 1e-12:
        return Rotation.identity() if c > 0 else Rotation.from_rotvec([math.pi, 0.0, 0.0])
    return Rotation.from_rotvec(axis / s * math.atan2(s, c))


def parse_start(text: str) -> list[float]:
    """--start's x,y,z (mm), roll,pitch,yaw (deg) as six numbers; UserError for anything else."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise UserError(f"--start {text!r}: expected six numbers x,y,z,roll,pitch,yaw (mm, deg)") from None
    if len(values) != 6 or not np.all(np.isfinite(values)):
        raise UserError(f"--start {text!r}: expected six finite numbers x,y,z,roll,pitch,yaw (mm, deg)")
    return values


def target_and_start(shape: str | None, mesh_path: str | None, start: list[float] | None):
    """(name, mesh, start as [x,y,z mm, roll,pitch,yaw deg], start pose 4x4) of a named shape or a mesh file and
    the start given (None: the shape's own in shapes.toml, or a mesh's twin.morphpatch.default_start). ValueError
    naming --start for a start inside the target."""
    if shape:
        mesh, name = load_shape(shape), shape
        default = shape_table()[shape]["start"]
    else:
        mesh, name = load_mesh(mesh_path), mesh_path
        default = None if start else default_start(mesh, build_fields(mesh), load_spec())
    start = start or default
    pose = pose_from_mm_deg(start)
    if igl.signed_distance(pose[None, :3, 3], mesh.vertices, mesh.faces)[0][0] < 0:
        raise ValueError(f"--start {','.join(f'{v:g}' for v in start)}: the anchor starts inside the target; give a "
                         "start outside it, on the side the device comes from (docs/approximation.md, Starts)")
    return name, mesh, start, pose
