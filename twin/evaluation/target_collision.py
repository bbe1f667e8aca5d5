"""The target as MuJoCo collision geometry that keeps its true shape.

MuJoCo collides meshes as their convex hulls, so a non-convex target (torus,
arch, stairs) is split into convex parts by CoACD (approximate convex
decomposition, Wei et al. 2022), cached on disk per mesh; a convex target is
used as it is. `collision_error` says how far the parts are from the mesh.
"""

from __future__ import annotations

import dataclasses

import coacd
import mujoco
import numpy as np
import trimesh

from twin.device.mjcf import mjcf
from twin.device.spec import DeviceSpec
from twin.morphpatch.fields import exact_signed_distance, load_npz, mesh_key, save_npz
from twin.paths import cache_dir

COACD_THRESHOLD = 0.03  # CoACD concavity threshold (fraction of the mesh's size): smaller = more, tighter parts


def convex_parts(mesh: trimesh.Trimesh, threshold: float = COACD_THRESHOLD) -> list[trimesh.Trimesh]:
    """Convex pieces whose union is the mesh (the mesh itself if it is convex); cached on disk."""
    if mesh.is_convex:
        return [mesh]
    path = cache_dir("coacd") / f"{mesh_key(mesh, threshold=threshold)}.npz"
    data = load_npz(path, ("n",))
    if data is not None:
        return [trimesh.Trimesh(data[f"v{i}"], data[f"f{i}"]) for i in range(int(data["n"]))]
    coacd.set_log_level("error")
    raw = coacd.run_coacd(coacd.Mesh(mesh.vertices, mesh.faces), threshold=threshold, seed=0)
    parts = [trimesh.Trimesh(v, f).convex_hull for v, f in raw]
    arrays = {"n": len(parts)}
    for i, p in enumerate(parts):
        arrays[f"v{i}"], arrays[f"f{i}"] = p.vertices, p.faces
    save_npz(path, arrays)
    return parts


@dataclasses.dataclass(frozen=True)
class CollisionError:
    """How far the convex parts are from the mesh, m."""

    mesh_to_parts_max: float  # largest gap from a mesh surface point to the parts' surface
    parts_outside_max: float  # largest bulge of the parts outside the mesh
    mean: float  # mean gap from mesh surface samples to the parts' surface


def collision_error(mesh: trimesh.Trimesh, parts: list[trimesh.Trimesh], samples: int = 4000,
                    seed: int = 0) -> CollisionError:
    """Compare the union of convex parts with the mesh on surface samples of both."""
    pts = trimesh.sample.sample_surface(mesh, samples, seed=seed)[0]
    # distance from each mesh point to the union's surface: |signed distance to the union| = |max over parts|
    union_sd = np.max([-_convex_sdf(p, pts) for p in parts], axis=0)  # >0 inside some part
    gap = np.abs(union_sd)
    outside = 0.0
    for p in parts:
        sd, _ = exact_signed_distance(mesh, trimesh.sample.sample_surface(p, max(64, samples // len(parts)),
                                                                          seed=seed)[0])
        outside = max(outside, float(np.max(sd)))
    return CollisionError(float(gap.max()), max(0.0, outside), float(gap.mean()))


def _convex_sdf(part: trimesh.Trimesh, pts: np.ndarray) -> np.ndarray:
    """Signed distance to a convex polytope, approximated by its face planes (exact inside, a bound outside)."""
    offsets = np.einsum("fk,fk->f", part.face_normals, part.triangles[:, 0])
    return np.max(pts @ part.face_normals.T - offsets, axis=1)


def scene_model(spec: DeviceSpec, parts: list[trimesh.Trimesh]) -> mujoco.MjModel:
    """The device (root fixed, posed by Twin.set_root_pose) with the target's parts as static geoms `target{i}`."""
    s = mujoco.MjSpec.from_string(mjcf(spec, root="fixed"))
    for i, p in enumerate(parts):
        mesh = s.add_mesh()
        mesh.name = f"target{i}"
        mesh.uservert = np.asarray(p.vertices, np.float32).ravel()
        mesh.userface = np.asarray(p.faces, np.int32).ravel()
        g = s.worldbody.add_geom()
        g.name = f"target{i}"
        g.type = mujoco.mjtGeom.mjGEOM_MESH
        g.meshname = f"target{i}"
        g.rgba = [0.8, 0.5, 0.3, 1.0]
        g.friction = [0.6, 0.005, 0.0001]
    return s.compile()
