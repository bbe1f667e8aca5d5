"""The MorphPatch pipeline (twin/morphpatch/approximation.py), the proxy's metrics and the CLI command."""

import json
import math

import numpy as np
import pytest

from twin import cli
from twin.formats.target import approximation_json, approximation_record
from twin.morphpatch.approximation import approximate, frames, measured, pose_from_mm_deg
from twin.records.approximation import Approximation
from twin.morphpatch.fields import build_fields
from twin.device.kinematics import hinge_axis_sign, pose_matrix
from twin.morphpatch.shapes import load_shape, shape_names
from twin.evaluation.starts import approach_starts
from twin.morphpatch.sampling import touch_surface_points
from twin.morphpatch.surface_metrics import match, msd_hd

EVAL_SPACING = 0.005  # m: coarser fields for the all-shapes test keep this file fast (about 5 s to build)
HCEVF_MARGIN = 0.5e-3  # m: "full" may be at most this much worse than "no_hcevf" in mean MSD


def fields_of(name, spacing=0.003):
    mesh = load_shape(name)
    return mesh, build_fields(mesh, spacing=spacing)


def level(x, y, z):
    return pose_matrix([x, y, z], np.eye(3))


def test_lying_on_a_cube_face_fits_exactly(spec):
    mesh, fields = fields_of("cube")
    for variant in ("full", "no_hcevf"):
        result = measured(spec, mesh, approximate(fields, level(0.003, -0.002, 0.23), spec, variant))
        assert result.msd < 0.2e-3 and result.hd < 0.5e-3, variant
        assert np.all(np.abs(result.angles) < math.radians(0.5))
        assert result.root_pose[2, 3] == pytest.approx(0.2, abs=0.2e-3)


def test_hinges_follow_a_cylinders_chords(spec):
    """Flaps as chords of a circle of radius R turn by 2 asin(p / 2R) at each hinge, convex = negative.

    Tolerance 1 degree: the root flap is tangent (its centre, the anchor, is snapped
    onto the surface), not a chord, and the grid's gradients are interpolated.
    """
    mesh, fields = fields_of("cylinder")
    radius = 0.075
    chord = 2 * math.asin(spec.flap_pitch / (2 * radius))
    for variant in ("full", "no_hcevf"):
        result = measured(spec, mesh, approximate(fields, level(0.004, 0.01, 0.19), spec, variant))
        assert np.degrees(result.angles) == pytest.approx(np.full(spec.n_hinges, -math.degrees(chord)), abs=1.0)
        assert result.msd < 1e-3


def test_pipeline_lowers_msd_on_every_shape(spec):
    """From 4 seeded starts 2-6 cm off and tilted up to 30 degrees (twin.evaluation.starts), on all eight shapes."""
    for name in shape_names():
        mesh, fields = fields_of(name, EVAL_SPACING)
        for start in approach_starts(mesh, 4, seed=3):
            before, _ = msd_hd(spec, mesh, start, np.zeros(spec.n_hinges))
            for variant in ("full", "no_hcevf"):
                result = approximate(fields, start, spec, variant)
                assert np.all(np.abs(result.angles) <= spec.hinge_limit)
                after, _ = msd_hd(spec, mesh, result.root_pose, result.angles, result.widths)
                assert after < before, (name, variant, before, after)


@pytest.mark.parametrize("name", ["stairs", "curved_stairs"])
def test_hcevf_is_not_worse_on_stairs(spec, name):
    mesh, fields = fields_of(name)
    msd = {"full": [], "no_hcevf": []}
    for start in approach_starts(mesh, 12, seed=7):
        for variant in msd:
            result = approximate(fields, start, spec, variant)
            msd[variant].append(msd_hd(spec, mesh, result.root_pose, result.angles, result.widths)[0])
    assert np.mean(msd["full"]) <= np.mean(msd["no_hcevf"]) + HCEVF_MARGIN


def test_hcevf_widths_stay_in_range(spec):
    mesh, fields = fields_of("stairs")
    for start in approach_starts(mesh, 10, seed=1):
        result = approximate(fields, start, spec, "full")
        assert np.all(result.widths >= 0.5 * spec.flap_pitch - 1e-12)
        assert np.all(result.widths <= 1.5 * spec.flap_pitch + 1e-12)
    assert np.all(approximate(fields, start, spec, "no_hcevf").widths == spec.flap_pitch)


def test_surface_metrics_of_a_device_hovering_over_a_face(spec):
    """Flat, 10 mm above the cube's top face: every sample is 10 mm away, so MSD = HD = 10 mm."""
    mesh = load_shape("cube")
    msd, hd = msd_hd(spec, mesh, level(0.0, 0.0, 0.21), np.zeros(spec.n_hinges))
    assert msd == pytest.approx(0.01, abs=1e-9) and hd == pytest.approx(0.01, abs=1e-9)
    assert match(spec, mesh, level(0.0, 0.0, 0.21), np.zeros(spec.n_hinges))[2:] == (0.0, 0.0)


def test_the_touch_surface_inside_the_target_is_measured(spec):
    """Flat, 10 mm below the cube's top face: all of it inside, 10 mm deep; the middle flaps flat 3 mm above
    the face and the outer ones turned down into the cube: some of it inside, no deeper than the tips went."""
    mesh = load_shape("cube")
    pressed = match(spec, mesh, level(0.0, 0.0, 0.19), np.zeros(spec.n_hinges))
    assert pressed.inside == 1.0 and pressed.depth == pytest.approx(0.01, abs=1e-9)
    assert pressed.msd <= pressed.depth
    angles = np.zeros(spec.n_hinges)
    angles[[0, -1]] = np.radians(30) * np.array([-1, 1]) * hinge_axis_sign(spec)[[0, -1]]
    bent = Approximation(level(0.0, 0.0, 0.203), angles, np.full(spec.n_flaps, spec.flap_pitch), 0.0, "full")
    bent = measured(spec, mesh, bent)
    tips = touch_surface_points(spec, frames(spec, bent), bent.widths)[:, 2]
    assert 0.0 < bent.inside < 0.5 and 0.005 < bent.depth <= 0.2 - tips.min() + 1e-9  # (the cube's sides are near)
    out = approximation_json(bent)
    assert out["inside_percent"] == pytest.approx(bent.inside * 100, abs=0.01) and out["inside_depth_mm"] > 0
    assert approximation_record(out, spec, "bent").depth == pytest.approx(bent.depth, abs=1e-6)


def test_to_json_has_units_in_keys(spec):
    _, fields = fields_of("cylinder")
    out = approximation_json(approximate(fields, pose_from_mm_deg([0, 0, 190, 0, 0, 0]), spec))
    assert set(out) == {"variant", "root_position_mm", "root_quat_wxyz", "angles_deg", "widths_mm",
                        "msd_mm", "hd_mm", "inside_percent", "inside_depth_mm", "time_ms"}
    assert out["root_position_mm"][2] == pytest.approx(150.0, abs=0.2)
    assert out["widths_mm"][0] == pytest.approx(spec.flap_pitch * 1e3, abs=1e-3)
    assert np.linalg.norm(out["root_quat_wxyz"]) == pytest.approx(1.0, abs=1e-5)
    assert out["time_ms"] > 0
    json.dumps(out)


def test_start_as_position_and_rotation(spec):
    _, fields = fields_of("cylinder")
    a = approximate(fields, (np.array([0.0, 0.0, 0.19]), np.eye(3)), spec)
    b = approximate(fields, level(0.0, 0.0, 0.19), spec)
    assert np.allclose(a.root_pose, b.root_pose) and np.allclose(a.angles, b.angles)


def test_bad_variant_and_start(spec):
    _, fields = fields_of("cylinder")
    with pytest.raises(ValueError, match="unknown variant"):
        approximate(fields, level(0, 0, 0.2), spec, "best")
    with pytest.raises(ValueError, match="6 finite numbers"):
        pose_from_mm_deg([0, 0, 1])


def test_frames_of_a_result(spec):
    _, fields = fields_of("cylinder")
    result = approximate(fields, level(0, 0, 0.19), spec)
    assert isinstance(result, Approximation)
    assert np.allclose(frames(spec, result)[spec.root_flap], result.root_pose)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """One cache folder for this module's commands, not the user's: the cylinder's fields are built once (the
    second variant's run read them: 60 s of the default suite where each built its own)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("VRSCROLL_CACHE", str(tmp_path_factory.mktemp("cache")))
        yield


@pytest.mark.parametrize("variant", ["no_hcevf", "refined"])
def test_cli_prints_json(tmp_path, capsys, cache, variant):
    path = tmp_path / "out.json"
    assert cli.main(["approximate", "--shape", "cylinder", "--start", "0,0,190,0,0,0", "--variant", variant,
                     "--json", str(path)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads(path.read_text())
    assert printed["variant"] == variant and printed["msd_mm"] < 1.0


def test_cli_user_errors(tmp_path, capsys, cache):
    assert cli.main(["approximate", "--shape", "cube", "--start", "1,2,3"]) == 2
    assert "six" in capsys.readouterr().err
    bad = tmp_path / "bad.stl"
    bad.write_text("not a mesh")
    assert cli.main(["approximate", "--mesh", str(bad)]) == 2
    assert "no triangles" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_png(tmp_path, cache):
    path = tmp_path / "cube.png"
    assert cli.main(["approximate", "--shape", "cube", "--png", str(path)]) == 0
    assert path.stat().st_size > 10_000


def test_the_approximation_never_imports_mujoco():
    import subprocess
    import sys

    code = ("import sys, twin.morphpatch.approximation, twin.morphpatch.fields, twin.morphpatch.shapes, "
            "twin.morphpatch.surface_metrics, twin.morphpatch.refinement; "
            "assert not any(m.startswith('mujoco') for m in sys.modules)")
    subprocess.run([sys.executable, "-c", code], check=True)
