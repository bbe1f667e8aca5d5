"""Grid fields of a target: SDF and gradient against the exact mesh, curvature, HCEVF, caching."""

import numpy as np
import pytest
import trimesh

from twin.morphpatch.fields import GRID_SPACING, build_fields, exact_signed_distance
from twin.morphpatch.shapes import load_shape
import twin.morphpatch.fields as module

# Interpolation error of the 3 mm grid against libigl's exact distance, near the
# surface (-10..+30 mm): benchmarks/bench_approximation.py measures mean about
# 0.02 mm, p99 below 0.6 mm, max about 1.5 mm (at sharp edges and the cone's apex).
MEAN_TOL, P99_TOL, MAX_TOL = 0.05e-3, 0.7e-3, 2.0e-3  # m


def near_surface_points(mesh, n=4000, seed=0):
    rng = np.random.default_rng(seed)
    points, faces = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return points + mesh.face_normals[faces] * rng.uniform(-0.01, 0.03, (n, 1))


@pytest.fixture(scope="module")
def stairs():
    mesh = load_shape("stairs")
    return mesh, build_fields(mesh)


@pytest.fixture(scope="module")
def cube():
    mesh = load_shape("cube")
    return mesh, build_fields(mesh)


@pytest.mark.parametrize("name", ["stairs", "cube"])
def test_sdf_matches_exact_distance(name, request):
    mesh, fields = request.getfixturevalue(name)
    points = near_surface_points(mesh)
    exact, _ = exact_signed_distance(mesh, points)
    err = np.abs(fields.sdf_values(points) - exact)
    assert err.mean() < MEAN_TOL and np.percentile(err, 99) < P99_TOL and err.max() < MAX_TOL


def test_sign_negative_inside(cube):
    mesh, fields = cube
    assert fields.sdf_values(np.array([[0.02, 0.01, 0.15]]))[0] == pytest.approx(-0.05, abs=1e-6)
    assert fields.sdf_values(np.array([[0.0, 0.0, 0.25]]))[0] == pytest.approx(0.05, abs=1e-6)


def test_gradient_is_the_unit_normal_outside(stairs):
    """Outside (5-30 mm off) grad S = (q - closest)/|q - closest|, but where S has a kink
    (the bisectors of the stairs' concave edges), which the grid's central differences smooth."""
    mesh, fields = stairs
    points = near_surface_points(mesh, seed=1)
    exact, closest = exact_signed_distance(mesh, points)
    points, exact, closest = points[exact > 0.005], exact[exact > 0.005], closest[exact > 0.005]
    _, grad = fields.sdf_grad(points)
    normal = (points - closest) / exact[:, None]
    cos = np.sum(grad * normal, axis=1) / np.linalg.norm(grad, axis=1)
    angle = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    assert np.median(angle) < 0.5 and np.percentile(angle, 90) < 2.0
    assert np.median(np.abs(np.linalg.norm(grad, axis=1) - 1)) < 0.01


def test_outside_the_grid_is_an_upper_bound(cube):
    mesh, fields = cube
    far = np.array([[0.0, 0.0, 1.0], [2.0, 0.0, 0.1]])
    exact, _ = exact_signed_distance(mesh, far)
    value = fields.sdf_values(far)
    assert np.all(value >= exact - 1e-9) and np.allclose(value, exact, rtol=0.05)


def test_curvature_is_the_laplacian_of_a_sphere():
    """tr H(S) = 2/r at distance r from a sphere's centre (within 5% in the median: the
    sphere is a polyhedron of 20480 faces, whose S is only piecewise that of a sphere)."""
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=0.08)
    fields = build_fields(mesh, margin=0.03, disk_cache=False)  # the bands reach 100 mm from the centre
    g = fields.grid_points()
    r = np.linalg.norm(g, axis=1)
    for lo, hi in [(0.06, 0.077), (0.083, 0.1)]:  # inside and outside
        band = (r > lo) & (r < hi)
        assert np.median(fields.curvature.ravel()[band] * r[band] / 2) == pytest.approx(1.0, abs=0.05)


def test_high_curvature_points_lie_on_the_cube_edges(cube):
    mesh, fields = cube
    # distance of each edge point to the nearest of the cube's 12 edge lines
    half = np.array([0.1, 0.1, 0.1])
    p = np.abs(fields.edges - [0.0, 0.0, 0.1])
    d = np.sort(half - p, axis=1)[:, :2]  # two smallest distances to the faces' planes
    assert np.all(np.linalg.norm(d, axis=1) < 1.5 * GRID_SPACING)
    assert len(fields.edges) > 12 * 0.2 / GRID_SPACING  # all twelve edges found along their length


@pytest.mark.parametrize("name", [pytest.param("torus", marks=pytest.mark.slow), "ellipsoid"])  # torus: slow suite
def test_smooth_tessellated_shapes_have_no_high_curvature_points(name):
    """Their true |tr H| stays below 41 1/m (torus: 1/40 mm + 1/140 mm at the outer equator), under
    MIN_CURVATURE; the facet edges' one-cell spikes (52 and 1068 points before) must not count."""
    fields = build_fields(load_shape(name))
    assert len(fields.edges) == 0


def test_stairs_edges_are_all_found(stairs):
    """Every one of the stairs' eight profile corners (convex and concave), along the 200 mm width."""
    mesh, fields = stairs
    corners = [(-0.09, 0.0), (-0.09, 0.035), (-0.03, 0.035), (-0.03, 0.07), (0.03, 0.07), (0.03, 0.105),
               (0.09, 0.105), (0.09, 0.0)]
    inner = np.abs(fields.edges[:, 1]) < 0.09  # away from the end caps' own edges
    for x, z in corners:
        near = inner & (np.hypot(fields.edges[:, 0] - x, fields.edges[:, 2] - z) < 1.5 * GRID_SPACING)
        assert near.sum() > 0.18 / GRID_SPACING, (x, z)


def test_hcevf_points_to_the_nearest_edge_within_the_threshold(cube):
    mesh, fields = cube
    q = np.array([[0.09, 0.0, 0.2], [0.0, 0.0, 0.2], [0.093, 0.02, 0.2]])
    v = fields.hcevf(q)
    assert v[0] == pytest.approx([0.01, 0.0, 0.0], abs=2 * GRID_SPACING)  # towards the edge x = 0.1, z = 0.2
    assert np.all(v[1] == 0.0)  # face centre: no edge within edge_radius
    assert fields.edge_radius == pytest.approx(0.188 / 7 / 2)  # half the flap pitch (spec)
    # query points reuse their nearest grid point's target edge: the same e* for q and q + small offset
    grid_q = fields.origin + np.rint((q[2] - fields.origin) / fields.spacing) * fields.spacing
    shifted = np.array([grid_q, grid_q + 0.3 * GRID_SPACING])
    targets = fields.hcevf(shifted) + shifted
    assert targets[0] == pytest.approx(targets[1])


def test_fields_are_cached_in_memory_and_on_disk(tmp_path, monkeypatch):
    monkeypatch.setenv("VRSCROLL_CACHE", str(tmp_path))
    monkeypatch.setattr(module, "_MEMORY", {})  # (the session's cache stays for the other tests)
    mesh = trimesh.creation.box((0.05, 0.05, 0.05))
    first = build_fields(mesh, spacing=0.005, margin=0.02)
    assert build_fields(mesh, spacing=0.005, margin=0.02) is first
    files = list((tmp_path / "fields").glob("*.npz"))
    assert len(files) == 1
    module._MEMORY.clear()
    again = build_fields(mesh, spacing=0.005, margin=0.02)
    assert again is not first and np.array_equal(again.sdf, first.sdf)
    assert np.array_equal(again.edge_index, first.edge_index)


@pytest.mark.parametrize("damage", ["empty", "cut short"])
def test_a_damaged_cache_file_is_built_again_with_a_notice(tmp_path, monkeypatch, capsys, damage):
    """Once a BadZipFile/EOFError on every later run, until the file was deleted by hand."""
    monkeypatch.setenv("VRSCROLL_CACHE", str(tmp_path))
    monkeypatch.setattr(module, "_MEMORY", {})
    mesh = trimesh.creation.icosphere(2, 0.03)
    first = build_fields(mesh, spacing=0.005, margin=0.02)
    [path] = (tmp_path / "fields").glob("*.npz")
    path.write_bytes(b"" if damage == "empty" else path.read_bytes()[: path.stat().st_size // 2])
    module._MEMORY.clear()
    capsys.readouterr()
    again = build_fields(mesh, spacing=0.005, margin=0.02)
    assert np.array_equal(again.sdf, first.sdf) and np.array_equal(again.edge_index, first.edge_index)
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and f"cache file {path} is damaged" in err
    module._MEMORY.clear()
    build_fields(mesh, spacing=0.005, margin=0.02)  # rebuilt on disk: read without a word
    assert capsys.readouterr().err == ""


def test_a_long_field_build_shows_its_progress(monkeypatch, capsys):
    """A 2 M-face mesh took minutes with no sign of life; a build longer than PROGRESS_AFTER reports on stderr
    (here made 0 s, and the chunks small, so that a small build reports)."""
    monkeypatch.setattr(module, "PROGRESS_AFTER", 0.0)
    monkeypatch.setattr(module, "CHUNK", 2000)
    monkeypatch.setattr(module, "_MEMORY", {})
    mesh = trimesh.creation.box((0.04, 0.04, 0.04))
    chunked = build_fields(mesh, spacing=0.004, margin=0.02, disk_cache=False)
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) >= 4 and all("grid points" in ln for ln in lines)
    assert lines[-1].split(":")[1].split("%")[0].strip() == "100"
    monkeypatch.setattr(module, "CHUNK", 1 << 30)
    module._MEMORY.clear()
    whole = build_fields(mesh, spacing=0.004, margin=0.02, disk_cache=False)
    assert np.array_equal(chunked.sdf, whole.sdf) and np.array_equal(chunked.edge_index, whole.edge_index)


def test_a_segments_dip_into_the_target_is_its_deepest_point(cube):
    """_path_dip (how deep a straight line goes into the target, what ours' bounded search holds a kept anchor's
    chord to): on segments drawn about the cube, within the grid's error of the exact deepest point on the segment
    (libigl), 0 where it stays out, and a segment is clear to a depth just below its dip only where `_path_clear`
    says so just above it."""
    mesh, fields = cube
    rng = np.random.default_rng(11)
    centre = mesh.bounds.mean(axis=0)
    for _ in range(20):
        a, b = centre + rng.uniform(-0.12, 0.12, (2, 3))
        dip = module._path_dip(fields.grid, a, b)
        along = a + np.linspace(0, 1, 400)[:, None] * (b - a)
        exact = max(0.0, -float(exact_signed_distance(mesh, along)[0].min()))
        assert dip == pytest.approx(exact, abs=MAX_TOL), (a, b)
        assert module._path_clear(fields.grid, a, b, dip + 1e-4)
        assert dip == 0.0 or not module._path_clear(fields.grid, a, b, dip - 1e-4)
