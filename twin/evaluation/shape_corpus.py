"""A corpus of shapes nobody tuned the approximation for, drawn from a seed (issue 22): many families, sized like
what a hand-held display meets (5-40 cm across), every one watertight. Used by tests/morphpatch/test_corpus.py
and benchmarks/bench_corpus.py; docs/approximation.md reports on it.

Families: superquadrics, bumpy and displaced spheres, organic blobs (star-shaped surfaces: an icosphere's
vertices moved along their directions), height fields (a closed slab whose top is a random smooth surface),
bowls and cups with handles (revolved profiles; the handle joined with manifold3d, trimesh's boolean engine),
thin plates, tori of many ratios. Sizes and parameters are drawn, the families fixed. (manifold3d, for the cups'
handles, comes with the test extra: pip install '.[test]'.)
"""

from __future__ import annotations

import math

import igl
import numpy as np
import trimesh

PATH_TOLERANCE = 2.5e-3  # m, exact: the grid's PATH_DEPTH (1 mm) plus its rounding of sharp edges
FAMILIES = ("superquadric", "bumpy_sphere", "blob", "height_field", "bowl", "cup", "plate", "torus")
PER_FAMILY = 5  # 8 families x 5 = 40 shapes


def _star(rng, radius_of, subdivisions: int = 4) -> trimesh.Trimesh:
    """An icosphere whose vertex along unit direction d is moved to radius_of(d) (m): watertight, star-shaped."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    d = sphere.vertices / np.linalg.norm(sphere.vertices, axis=1, keepdims=True)
    return trimesh.Trimesh(d * radius_of(d)[:, None], sphere.faces, process=True)


def superquadric(rng) -> trimesh.Trimesh:
    a = rng.uniform(0.04, 0.15, 3)  # semi-axes, m
    e = rng.uniform(0.3, 2.0, 2)  # shape exponents: < 1 boxy, 1 an ellipsoid, > 1 pinched

    def r(d):
        x, y, z = np.abs(d.T) + 1e-12
        f = ((x / a[0]) ** (2 / e[1]) + (y / a[1]) ** (2 / e[1])) ** (e[1] / e[0]) + (z / a[2]) ** (2 / e[0])
        return f ** (-e[0] / 2)
    return _star(rng, r)


def bumpy_sphere(rng) -> trimesh.Trimesh:
    radius = rng.uniform(0.04, 0.15)
    k = rng.normal(size=(int(rng.integers(3, 9)), 3))
    k /= np.linalg.norm(k, axis=1, keepdims=True)
    amp, sharp = rng.uniform(0.05, 0.25), rng.uniform(4, 20)
    return _star(rng, lambda d: radius * (1 + amp * np.exp(sharp * (d @ k.T - 1)).sum(axis=1)), subdivisions=5)


def blob(rng) -> trimesh.Trimesh:
    radius = rng.uniform(0.05, 0.15)
    waves = rng.normal(size=(6, 3)) * rng.uniform(1, 3)
    phase, amp = rng.uniform(0, 2 * math.pi, 6), rng.uniform(0.03, 0.1, 6)
    return _star(rng, lambda d: radius * (1 + (amp * np.sin(d @ waves.T + phase)).sum(axis=1)), subdivisions=5)


def height_field(rng) -> trimesh.Trimesh:
    """A slab (0.1-0.4 m square) whose top is a sum of random smooth bumps, its bottom flat."""
    size, n = rng.uniform(0.1, 0.4), 48
    u = np.linspace(-size / 2, size / 2, n)
    x, y = np.meshgrid(u, u, indexing="ij")
    z = 0.03 + np.zeros_like(x)
    for _ in range(int(rng.integers(2, 7))):
        cx, cy = rng.uniform(-size / 2, size / 2, 2)
        z += rng.uniform(-0.02, 0.05) * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * rng.uniform(0.02, 0.08) ** 2))
    return slab(x, y, np.maximum(z, 0.01))


def slab(x, y, z) -> trimesh.Trimesh:
    """The closed solid between z = 0 and a height field z (m) over a square grid x, y (n x n, ij-indexed)."""
    n = len(x)
    top = np.c_[x.ravel(), y.ravel(), z.ravel()]
    bottom = np.c_[x.ravel(), y.ravel(), np.zeros(n * n)]
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = [np.c_[a, b, c], np.c_[a, c, d], np.c_[a, c, b] + n * n, np.c_[a, d, c] + n * n]
    ring = np.r_[idx[:, 0], idx[-1, 1:], idx[-2::-1, -1], idx[0, -2:0:-1]]
    nxt = np.roll(ring, -1)
    faces += [np.c_[ring, nxt + n * n, nxt], np.c_[ring, ring + n * n, nxt + n * n]]
    mesh = trimesh.Trimesh(np.vstack([top, bottom]), np.vstack(faces), process=True)
    trimesh.repair.fix_normals(mesh)
    return mesh


def _revolved(profile) -> trimesh.Trimesh:
    return trimesh.creation.revolve(np.asarray(profile, float), sections=64)


def bowl(rng) -> trimesh.Trimesh:
    """A spherical-cap bowl with a wall of 4-10 mm, its opening up."""
    radius, wall = rng.uniform(0.05, 0.2), rng.uniform(0.004, 0.01)
    depth = radius * rng.uniform(0.4, 0.9)
    t = np.linspace(0, math.acos(1 - depth / radius), 24)
    outer = np.c_[radius * np.sin(t), radius * (1 - np.cos(t))]
    inner = np.c_[(radius - wall) * np.sin(t), radius * (1 - np.cos(t)) + wall][::-1]
    inner = inner[inner[:, 1] <= outer[-1, 1]]
    return _revolved(np.vstack([outer, [[inner[0, 0], outer[-1, 1]]], inner[1:]]))


def cup(rng) -> trimesh.Trimesh:
    """A cup (60-120 mm across, 80-150 mm high, wall 3-8 mm) with a ring handle on its side."""
    outer, wall, height = rng.uniform(0.03, 0.06), rng.uniform(0.003, 0.008), rng.uniform(0.08, 0.15)
    body = _revolved([[0, 0], [outer, 0], [outer, height], [outer - wall, height], [outer - wall, wall],
                      [0, wall]])
    ring = trimesh.creation.torus(height * 0.3, rng.uniform(0.004, 0.008), major_sections=48, minor_sections=16)
    ring.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, (1, 0, 0)))
    ring.apply_translation((outer + height * 0.2, 0, height * 0.5))
    return trimesh.boolean.union([body, ring], engine="manifold")


def plate(rng) -> trimesh.Trimesh:
    """A thin plate, 3-10 mm thick, 0.1-0.4 m across, tilted."""
    mesh = trimesh.creation.box((rng.uniform(0.1, 0.4), rng.uniform(0.1, 0.4), rng.uniform(0.003, 0.01)))
    mesh.apply_transform(trimesh.transformations.euler_matrix(*rng.uniform(-0.6, 0.6, 2), 0.0))
    return mesh


def torus(rng) -> trimesh.Trimesh:
    """A torus of ratio major/minor 1.5-8, 0.1-0.4 m across."""
    across, ratio = rng.uniform(0.1, 0.4), rng.uniform(1.5, 8.0)
    minor = across / (2 * (ratio + 1))
    return trimesh.creation.torus(ratio * minor, minor, major_sections=64, minor_sections=24)


def starts(mesh: trimesh.Trimesh, n: int, seed: int) -> list[np.ndarray]:
    """n start poses (4x4) outside the mesh, all round it: from a random direction, 40 mm beyond the bounding
    sphere, the device's -z pointing at the mesh's centre, turned about it at random."""
    rng = np.random.default_rng(seed)
    centre, reach = mesh.bounds.mean(axis=0), np.linalg.norm(mesh.extents) / 2 + 0.04
    out = []
    for _ in range(n):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        z = d  # the device's +z points away from the target: it approaches along -z
        helper = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        x = np.cross(helper, z)
        x /= np.linalg.norm(x)
        turn = rng.uniform(0, 2 * math.pi)
        x = math.cos(turn) * x + math.sin(turn) * np.cross(z, x)
        pose = np.eye(4)
        pose[:3, :3] = np.column_stack([x, np.cross(z, x), z])
        pose[:3, 3] = centre + reach * d
        out.append(pose)
    return out


def person_starts(mesh: trimesh.Trimesh) -> list[list[float]]:
    """The starts a person would try on an object lying on a table (issue 37), [x, y, z mm, roll, pitch, yaw deg]:
    from above and from each of its four sides, the device square to that face of the bounding box, over its
    middle, 40 mm out from it, the row level; never from below. Written apart from twin.morphpatch.shapes.side_starts
    (no principal axes, no depth images): what the default start is judged against."""
    lo, hi = mesh.bounds * 1e3
    mid = (lo + hi) / 2
    return [[mid[0], mid[1], hi[2] + 40, 0, 0, 0],  # from above, level
            [hi[0] + 40, mid[1], mid[2], 0, 90, 0], [lo[0] - 40, mid[1], mid[2], 0, -90, 0],  # -z along -x, +x
            [mid[0], hi[1] + 40, mid[2], -90, 0, 0], [mid[0], lo[1] - 40, mid[2], 90, 0, 0]]  # -z along -y, +y


def corpus(seed: int = 0, families=FAMILIES, per_family: int = PER_FAMILY) -> list[tuple[str, trimesh.Trimesh]]:
    """[(name, mesh)]: per_family shapes of each family, drawn from `seed`, each resting on z = 0, centred."""
    rng = np.random.default_rng(seed)
    out = []
    for family in families:
        for i in range(per_family):
            mesh = globals()[family](rng)
            mesh.apply_translation([-mesh.bounds.mean(axis=0)[0], -mesh.bounds.mean(axis=0)[1], -mesh.bounds[0, 2]])
            assert mesh.is_watertight and mesh.volume > 0, (family, i)
            out.append((f"{family}_{i}", mesh))
    return out


def crossed(mesh: trimesh.Trimesh, a, b, tolerance: float = PATH_TOLERANCE) -> bool:
    """Whether the segment a -> b (m) goes deeper than `tolerance` into the solid (exact, every 0.5 mm): the
    approximation checks its anchor's paths on the 3 mm grid to 1 mm, which rounds a sharp edge off."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = max(2, int(np.linalg.norm(b - a) / 5e-4) + 1)
    return bool(igl.signed_distance(np.linspace(a, b, n), mesh.vertices, mesh.faces)[0].min() < -tolerance)
