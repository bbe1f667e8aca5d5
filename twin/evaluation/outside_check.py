"""A judge of an approximation's pose written apart from the approximation's own code (issue 37): from an
`approximate` JSON's angles_deg, root_position_mm, root_quat_wxyz and widths_mm alone, with the spec's geometry,
its own flap kinematics (each flap a segment in the root's x-z plane, the chain walked out from the root flap),
the exact signed distance of its touch surface to the mesh (libigl), and the gap between flaps two or more
apart (each flap a rectangle, the flap's length less the gap at its hinges by its thickness behind the touch
surface; the distance of two convex polygons). Nothing here calls twin.device or twin.morphpatch: a check
written apart on purpose (tests/morphpatch/test_resting.py, benchmarks/bench_resting.py), not a second copy of
the kinematics to keep in step."""

from __future__ import annotations

import math
from typing import NamedTuple

import igl
import numpy as np

SPACING = 1e-3  # m between the judged touch-surface samples


class Verdict(NamedTuple):
    deepest: float  # m, the deepest touch-surface sample inside the target (0 if none is)
    share_2mm: float  # share (0..1) of the touch surface more than 2 mm inside
    gap: float  # m, the smallest gap between flaps two or more apart (negative: they overlap)


def _quat_matrix(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def flaps_2d(spec, angles_deg, widths) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per flap (its inner end, its outer end, its touch-side normal) in the root's x-z plane (m). A positive
    angle bends the touch surface concave (the outer flap's free end towards +z)."""
    r, a = spec.root_flap, np.radians(angles_deg)
    out = [None] * spec.n_flaps
    out[r] = (np.array([-widths[r] / 2, 0.0]), np.array([widths[r] / 2, 0.0]), np.array([0.0, 1.0]))
    for side in (1, -1):
        point, phi, i = np.array([side * widths[r] / 2, 0.0]), 0.0, r + side
        while 0 <= i < spec.n_flaps:
            phi += a[i - 1] if side == 1 else a[i]  # hinge k joins flaps k and k + 1
            direction = np.array([side * math.cos(phi), math.sin(phi)])
            normal = np.array([-side * direction[1], side * direction[0]])  # the touch side
            end = point + widths[i] * direction
            out[i] = (point, end, normal)
            point, i = end, i + side
    return out


def touch_points(spec, result: dict) -> np.ndarray:
    """The touch surface (usable depth, every flap) sampled every SPACING, in the world (N, 3), m."""
    widths = np.asarray(result["widths_mm"], float) / 1e3
    rot, pos = _quat_matrix(result["root_quat_wxyz"]), np.asarray(result["root_position_mm"], float) / 1e3
    ys = np.linspace(-spec.usable_depth / 2, spec.usable_depth / 2, int(spec.usable_depth / SPACING) + 1)
    points = []
    for a, b, _ in flaps_2d(spec, result["angles_deg"], widths):
        for t in np.linspace(0, 1, int(np.linalg.norm(b - a) / SPACING) + 1):
            x, z = a + t * (b - a)
            points.append(np.c_[np.full_like(ys, x), ys, np.full_like(ys, z)])
    return np.vstack(points) @ rot.T + pos


def _polygon_gap(p: np.ndarray, q: np.ndarray) -> float:
    """Distance (m) between convex polygons p, q (k, 2) corners in order; minus their overlap where they do."""
    overlap = math.inf
    for poly in (p, q):
        for k in range(len(poly)):
            e = poly[(k + 1) % len(poly)] - poly[k]
            n = np.array([-e[1], e[0]]) / np.linalg.norm(e)
            a, b = p @ n, q @ n
            overlap = min(overlap, min(a.max(), b.max()) - max(a.min(), b.min()))
    if overlap > 0:
        return -overlap

    def point_segment(x, s0, s1):
        d = s1 - s0
        t = np.clip((x - s0) @ d / (d @ d), 0, 1)
        return np.linalg.norm(x - (s0 + t * d))
    return min(point_segment(x, poly[k], poly[(k + 1) % len(poly)])
               for a, poly in ((p, q), (q, p)) for x in a for k in range(len(poly)))


def flap_gap(spec, angles_deg) -> float:
    """The smallest gap (m) between two flaps two or more apart (the physical flaps at the pitch)."""
    rects = []
    for a, b, n in flaps_2d(spec, angles_deg, np.full(spec.n_flaps, spec.flap_pitch)):
        d = (b - a) / np.linalg.norm(b - a)
        a, b = a + d * spec.flap_gap / 2, b - d * spec.flap_gap / 2
        rects.append(np.array([a, b, b - n * spec.thickness, a - n * spec.thickness]))
    return min(_polygon_gap(rects[i], rects[j]) for i in range(len(rects)) for j in range(i + 2, len(rects)))


def judge(spec, mesh, result: dict) -> Verdict:
    """How deep the result's touch surface lies in the mesh and how far apart its flaps are (Verdict)."""
    s = igl.signed_distance(touch_points(spec, result), np.asarray(mesh.vertices, float),
                            np.asarray(mesh.faces, np.int64))[0]
    return Verdict(max(0.0, float(-s.min())), float(np.mean(s < -2e-3)), flap_gap(spec, result["angles_deg"]))


def holds(v: Verdict) -> bool:
    """Issue 37's bar: deepest point inside <= 3 mm, at most 5 % more than 2 mm inside, flaps >= 3 mm apart."""
    return v.deepest <= 3e-3 and v.share_2mm <= 0.05 and v.gap >= 3e-3
