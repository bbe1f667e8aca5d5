"""Pen redirection: identity on an exact proxy, known offsets under a cylinder, continuity, files, command."""

import csv
import json
import math

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from twin.device.spec import load_spec
from twin.morphpatch.approximation import approximate, pose_from_mm_deg
from twin.cli import main
from twin.morphpatch.fields import build_fields
from twin.perception.thresholds import load_thresholds
from twin.formats.pen import read_pen_samples
from twin.formats.target import approximation_json, read_approximation
from twin.morphpatch.redirection import (build_field, largest_virtual_step, redirect, surface_points,
                              threshold_summary, within_samples)
from twin.morphpatch.shapes import load_shape, shape_table, sweep_solid

SPEC = load_spec()
FLAT = np.zeros(SPEC.n_hinges)
PITCH = np.full(SPEC.n_flaps, SPEC.flap_pitch)


def _random_pens(rng, n, spread=0.12):
    positions = rng.uniform(-spread, spread, (n, 3))
    return positions, Rotation.random(n, random_state=rng).as_quat(scalar_first=True)


def _solid_under(angles, thickness=0.01, half_depth=0.1):
    """The device's own bent touch surface made a solid: a strip `thickness` m deep under it."""
    frames = np.asarray(default_spec_frames(angles))
    s_edges = np.concatenate([[0.0], np.cumsum(PITCH)]) - (3 * SPEC.flap_pitch + SPEC.flap_pitch / 2)
    s = np.concatenate([[s_edges[0] - 0.02], s_edges, [s_edges[-1] + 0.02]])  # 20 mm longer than the device
    top, _ = surface_points(frames, s_edges, s, np.zeros_like(s))
    flap_normals = np.vstack([frames[:1, :3, 2]] * 2 + [frames[:, :3, 2]] + [frames[-1:, :3, 2]] * 2)
    normals = flap_normals[:-1] + flap_normals[1:]
    normals /= np.einsum("ij,ij->i", normals, flap_normals[:-1])[:, None]
    bottom = top - thickness * normals  # mitred, so the strip is `thickness` deep under every flap
    profile = np.vstack([top[:, [0, 2]], bottom[::-1, [0, 2]]])
    sections = [np.array([[1.0, 0, 0, 0], [0, 0, 0, y], [0, 1, 0, 0], [0, 0, 0, 1]]) for y in (-half_depth, half_depth)]
    mesh = sweep_solid(profile, sections)
    if mesh.volume < 0:
        mesh.invert()
    assert mesh.is_watertight
    return mesh


def default_spec_frames(angles):
    from twin.device.kinematics import flap_frames

    return flap_frames(SPEC, angles, None, PITCH)


@pytest.mark.parametrize("angles_deg", [[0] * 6, [25, -15, 10, 20, -10, 30]])
def test_redirection_on_an_exact_proxy_is_the_identity(angles_deg):
    angles = np.radians(angles_deg)
    mesh = _solid_under(angles)
    fields = build_fields(mesh, disk_cache=False)
    field = build_field(SPEC, np.eye(4), angles, PITCH, mesh, fields)
    assert field.hit[field.on_device].all()
    assert np.abs(field.offset).max() < 1e-7  # m
    assert field.rotation_angle().max() < 1e-6  # rad
    rng = np.random.default_rng(1)
    positions, orientations = _random_pens(rng, 500)
    out = redirect(field, positions, orientations)
    assert np.abs(out.position - positions).max() < 1e-7
    same = np.abs(np.einsum("ij,ij->i", out.orientation, orientations))  # q and -q are one rotation
    assert same.min() > 1 - 1e-9


@pytest.fixture(scope="module")
def cylinder():
    """A flat device tangent to a cylinder of radius 100 mm lying along the device's x, under its centre."""
    radius = 0.1
    place = trimesh.transformations.translation_matrix([0, 0, -radius]) @ trimesh.transformations.rotation_matrix(
        math.pi / 2, [0, 1, 0])
    mesh = trimesh.creation.cylinder(radius, 0.4, sections=720, transform=place)
    return radius, mesh, build_fields(mesh, spacing=0.005, disk_cache=False)  # a smooth 100 mm radius: 5 mm is fine


def test_flat_proxy_under_a_cylinder_gets_the_offsets_of_its_geometry(cylinder):
    radius, mesh, fields = cylinder
    raw = build_field(SPEC, np.eye(4), FLAT, PITCH, mesh, fields, sigma=0.0)
    points, _ = raw.surface()
    y = points[raw.on_device][:, 1]
    depth = np.sqrt(radius**2 - y**2) - radius  # the cylinder's top under (x, y), relative to the plane z = 0
    offset = raw.offset[raw.on_device]
    assert np.abs(offset[:, :2]).max() < 1e-9  # along the proxy's normal only
    assert np.abs(offset[:, 2] - depth).max() < 0.05e-3  # 0.05 mm: a 720-gon's sagitta is 0.001 mm
    angle = raw.rotation_angle()[raw.on_device]
    assert np.abs(angle - np.arcsin(np.abs(y) / radius)).max() < math.radians(0.3)  # half a facet is 0.25 deg

    # a pen touching the device at (x, y) is seen on the cylinder, along its normal there
    pens = points[raw.on_device][::37]
    out = redirect(raw, pens, np.tile([1.0, 0, 0, 0], (len(pens), 1)))
    on_cylinder = np.hypot(out.position[:, 1], out.position[:, 2] + radius)
    assert np.abs(on_cylinder - radius).max() < 0.05e-3
    pen_axis = Rotation.from_quat(out.orientation, scalar_first=True).apply([0, 0, 1])
    normal = np.c_[np.zeros(len(pens)), out.position[:, 1], out.position[:, 2] + radius] / radius
    assert np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", pen_axis, normal), -1, 1))).max() < 0.3


def test_blur_changes_the_cylinders_offsets_only_as_much_as_its_curvature_says(cylinder):
    radius, mesh, fields = cylinder
    sigma = 0.005
    field = build_field(SPEC, np.eye(4), FLAT, PITCH, mesh, fields, sigma=sigma)
    points, _ = field.surface()
    inner = field.on_device & (np.abs(points[..., 1]) < 0.055)  # 3 sigma clear of the padded edges
    y = points[inner][:, 1]
    depth = np.sqrt(radius**2 - y**2) - radius
    # a Gaussian blur moves a smooth f by about sigma^2/2 f''; |f''| <= R^2 / (R^2 - y^2)^1.5
    reach = 0.055 + 3 * sigma
    bound = sigma**2 / 2 * radius**2 / (radius**2 - reach**2) ** 1.5
    assert np.abs(field.offset[inner][:, 2] - depth).max() < bound + 0.05e-3


def test_threshold_share_matches_the_geometry():
    """A cylinder of radius 80 mm: the normal turns past 64.87 deg where |y| > 80 sin(64.87 deg) = 72.4 mm."""
    radius = 0.08
    place = trimesh.transformations.translation_matrix([0, 0, -radius]) @ trimesh.transformations.rotation_matrix(
        math.pi / 2, [0, 1, 0])
    mesh = trimesh.creation.cylinder(radius, 0.4, sections=360, transform=place)
    field = build_field(SPEC, np.eye(4), FLAT, PITCH, mesh, build_fields(mesh, disk_cache=False), sigma=0.0)
    summary = threshold_summary(field)
    t = load_thresholds()
    y_limit = min(radius * math.sin(t.rotation), math.sqrt(radius**2 - (radius - t.position) ** 2))
    expected = 2 * y_limit / SPEC.usable_depth
    assert summary["raw_share_within"] == pytest.approx(expected, abs=2 * field.dy / SPEC.usable_depth)
    assert summary["raw_largest_rotation_deg"] > 64.87

    # the gate reports it: a warning by default, a refusal when strict
    from twin.sim.gate import GateRefused, GateReport, enforce, redirection_check

    warn, strict = redirection_check(summary), redirection_check(summary, strict=True)
    assert warn.passed and warn.warning and warn.line().startswith("WARN")
    assert not strict.passed and strict.line().startswith("FAIL")
    enforce(GateReport(FLAT, FLAT, [warn], None))
    with pytest.raises(GateRefused, match="redirection"):
        enforce(GateReport(FLAT, FLAT, [strict], None))
    assert not redirection_check({**summary, "share_within": 1.0}, strict=True).warning


@pytest.fixture(scope="module")
def stairs():
    mesh = load_shape("stairs")
    fields = build_fields(mesh)
    approx = approximate(fields, pose_from_mm_deg(shape_table()["stairs"]["start"]), SPEC)
    return mesh, fields, approx


BOUND = 0.002  # m: the virtual point moves at most this much for a 0.5 mm pen step with the default blur


def test_the_smoothed_field_has_no_jumps_across_hinges_or_off_the_device(stairs):
    mesh, fields, approx = stairs
    raw = build_field(SPEC, approx.root_pose, approx.angles, approx.widths, mesh, fields, sigma=0.0)
    smooth = build_field(SPEC, approx.root_pose, approx.angles, approx.widths, mesh, fields)
    assert largest_virtual_step(raw, step=0.0005) > 2 * BOUND  # without the blur the pen jumps at the hinges
    assert largest_virtual_step(smooth, step=0.0005) < BOUND


def test_a_pen_carried_with_the_device_is_redirected_the_same(stairs):
    mesh, fields, approx = stairs
    field = build_field(SPEC, approx.root_pose, approx.angles, approx.widths, mesh, fields)
    rng = np.random.default_rng(2)
    positions, orientations = _random_pens(rng, 200, spread=0.08)
    positions += approx.root_pose[:3, 3]
    move = np.eye(4)
    move[:3, :3] = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix()
    move[:3, 3] = [0.3, -0.1, 0.2]
    moved_p = positions @ move[:3, :3].T + move[:3, 3]
    moved_q = (Rotation.from_matrix(move[:3, :3]) * Rotation.from_quat(orientations, scalar_first=True)).as_quat(
        scalar_first=True)
    device = np.tile(move @ approx.root_pose, (len(positions), 1, 1))
    a = redirect(field, positions, orientations)
    b = redirect(field, moved_p, moved_q, device)
    assert np.abs(a.position - b.position).max() < 1e-9
    assert np.abs(np.einsum("ij,ij->i", a.orientation, b.orientation)).min() > 1 - 1e-9


def _write_pens(path, positions, orientations):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_s", "x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz"])
        for k, (p, q) in enumerate(zip(positions * 1e3, orientations)):
            w.writerow([k / 360, *p, *q])


def test_redirect_command_writes_the_samples_and_the_picture(stairs, tmp_path, capsys):
    mesh, fields, approx = stairs
    approx_json = tmp_path / "a.json"
    approx_json.write_text(json.dumps({"target": "stairs", **approximation_json(approx)}))
    rng = np.random.default_rng(3)
    positions, orientations = _random_pens(rng, 50, spread=0.08)
    positions += approx.root_pose[:3, 3]
    pens = tmp_path / "pens.csv"
    _write_pens(pens, positions, orientations)
    out, png, summary = tmp_path / "out.csv", tmp_path / "field.png", tmp_path / "s.json"
    assert main(["redirect", str(approx_json), str(pens), "--out", str(out), "--png", str(png),
                 "--json", str(summary)]) == 0
    with open(out) as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 50 and rows[0]["t_s"] == "0.0"
    field = build_field(SPEC, *(lambda a: (a.root_pose, a.angles, a.widths))(read_approximation(approx_json, SPEC)),
                        mesh, fields)
    samples = read_pen_samples(pens)
    expected = redirect(field, samples.position, samples.orientation)
    got = np.array([[float(r[f"virtual_{c}_mm"]) for c in "xyz"] for r in rows]) / 1e3
    assert np.abs(got - expected.position).max() < 1e-6
    assert [int(r["within_thresholds"]) for r in rows] == within_samples(expected).astype(int).tolist()
    assert png.stat().st_size > 10_000
    assert json.loads(summary.read_text())["samples"] == 50
    assert "within" in capsys.readouterr().out


@pytest.mark.parametrize("content, message", [
    ("x_mm,y_mm\n1,2\n", "missing column"),
    ("x_mm,y_mm,z_mm,qw,qx,qy,qz\n1,2,3,1,0,0,zero\n", ":2: expected numbers"),
    ("x_mm,y_mm,z_mm,qw,qx,qy,qz\n1,2,3,0,0,0,0\n", "zero quaternion"),
    ("x_mm,y_mm,z_mm,qw,qx,qy,qz\n", "no pen samples"),
    ("x_mm,y_mm,z_mm,qw,qx,qy,qz,device_x_mm\n1,2,3,1,0,0,0,4\n", "device pose columns"),
    ("x_mm,y_mm,z_mm,qw,qx,qy,qz,x_mm\n1,2,3,1,0,0,0,9\n", "x_mm given twice"),  # which x was the pen's?
    ("x_mm,y_mm,z_mm,qw,qx,qy,qz,note\n1,2,3,1,0,0,0,a,b\n", ":2: 9 fields, the header has 8"),  # not dropped
])
def test_bad_pen_files_are_refused_with_the_reason(tmp_path, content, message):
    path = tmp_path / "pens.csv"
    path.write_text(content)
    with pytest.raises(ValueError, match=message):
        read_pen_samples(path)


def test_redirect_command_refuses_a_bad_approximation(tmp_path, capsys):
    bad = tmp_path / "a.json"
    bad.write_text(json.dumps({"target": "stairs", "angles_deg": [0] * 6}))
    assert main(["redirect", str(bad)]) == 2
    assert "not an approximation result" in capsys.readouterr().err


def test_redirect_refuses_hinge_angles_outside_the_hinge_range(tmp_path, capsys):
    """An approximation with a 500 deg hinge was once redirected as if the device could take it."""
    path = tmp_path / "a.json"
    path.write_text(json.dumps({"target": "stairs", "variant": "full", "root_position_mm": [0, 0, 50],
                                "root_quat_wxyz": [1, 0, 0, 0], "angles_deg": [0, 0, 500, 0, 0, 0],
                                "widths_mm": [26.857] * 7}))
    assert main(["redirect", str(path)]) == 2
    err = capsys.readouterr().err
    assert f"{path}: angles_deg: hinge 2 at 500 deg is outside the hinge range +-112.5 deg" in err
