"""Shapes made for issue 37's tests and benchmarks/bench_resting.py, nobody tuned for: a fat torus, bars thinner
than the device, small spheres, a noisy sphere, a saddle, a cup narrower than the device, a thin plate (m)."""

import math

import numpy as np
import trimesh

from twin.evaluation.shape_corpus import slab


def fat_torus():
    return trimesh.creation.torus(0.085, 0.028, major_sections=96, minor_sections=32)


def bar():
    """A straight bar of radius 22 mm (the device is 188 x 175 mm), 300 mm long, lying along x."""
    m = trimesh.creation.cylinder(0.022, 0.3, sections=48)
    m.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, (0, 1, 0)))
    return m


def bent_bar():
    """A bar of radius 22 mm bent round a 150 mm radius (a thin torus)."""
    return trimesh.creation.torus(0.15, 0.022, major_sections=96, minor_sections=24)


def sphere(radius):
    return trimesh.creation.icosphere(4, radius)


def noisy_sphere(seed=0):
    """A 70 mm sphere whose vertices are moved along their directions by 1.5 mm of noise (a scan's)."""
    m = trimesh.creation.icosphere(5, 0.07)
    d = m.vertices / np.linalg.norm(m.vertices, axis=1, keepdims=True)
    m.vertices = d * (0.07 + np.random.default_rng(seed).normal(0, 0.0015, len(d)))[:, None]
    return m


def saddle():
    """A slab 200 mm square whose top is the saddle z = 60 mm + (x^2 - y^2) / (2 x 120 mm)."""
    n, size = 48, 0.2
    u = np.linspace(-size / 2, size / 2, n)
    x, y = np.meshgrid(u, u, indexing="ij")
    return slab(x, y, 0.06 + (x ** 2 - y ** 2) / 0.24)


def cup():
    """A cup 90 mm across, 100 mm high, its wall 5 mm: narrower than the device."""
    profile = [[0, 0], [0.045, 0], [0.045, 0.1], [0.04, 0.1], [0.04, 0.008], [0, 0.008]]
    return trimesh.creation.revolve(np.array(profile), sections=64)


def plate():
    """A plate 250 x 200 x 4 mm, tilted."""
    m = trimesh.creation.box((0.25, 0.2, 0.004))
    m.apply_transform(trimesh.transformations.euler_matrix(0.3, -0.2, 0))
    return m


SHAPES = {"fat_torus": fat_torus, "bar": bar, "bent_bar": bent_bar, "sphere_12mm": lambda: sphere(0.006),
          "sphere_24mm": lambda: sphere(0.012), "noisy_sphere": noisy_sphere, "saddle": saddle, "cup": cup,
          "plate": plate}
