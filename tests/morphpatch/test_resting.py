"""Ours rests on the target from outside, never through it (issue 37): from the default start, on shapes made
here that nobody tuned for (a fat torus, bars thinner than the device, a 12 mm sphere, a noisy sphere, a saddle,
a cup, a thin plate) and on the corpus, ours' pose, judged by kinematics written apart from the approximation's
(twin/evaluation/outside_check.py, from the JSON's angles_deg, root_position_mm, root_quat_wxyz), has its deepest point inside
at most 3 mm, at most 5 % of its touch surface more than 2 mm inside, flaps two or more apart at least 3 mm
apart; or `approximate` refuses it in one line. A pose whose flaps meet is refused for any variant."""

import dataclasses
import json

import numpy as np
import pytest
import trimesh

from cli import vrscroll
from twin.evaluation.made_shapes import SHAPES, fat_torus
from twin.evaluation.outside_check import flap_gap, holds, judge
from twin.evaluation.shape_corpus import corpus
from twin.formats.target import approximation_json
from twin.morphpatch.approximation import approximate, measured, pose_from_mm_deg
from twin.morphpatch.default_start import default_start
from twin.morphpatch.fields import build_fields
from twin.morphpatch.refinement import flap_gap as ours_flap_gap
from twin.morphpatch.resting import refusal, resting
from twin.morphpatch.shapes import side_starts
from twin.records.approximation import Approximation


def resting_on(spec, name, mesh):
    """Ours from the mesh's default start: its JSON judged apart (outside_check), or a refusal that says why."""
    fields = build_fields(mesh)
    result = measured(spec, mesh, approximate(fields, pose_from_mm_deg(default_start(mesh, fields, spec)), spec,
                                              "refined"))
    why = refusal(spec, mesh, resting(spec, mesh, fields, result), "refined", result.rests)
    if why is not None:
        assert "cannot rest on this target from outside" in why and "\n" not in why, (name, why)
        return None
    verdict = judge(spec, mesh, approximation_json(result))
    assert holds(verdict), (name, verdict)
    return verdict


def test_ours_flap_gap_is_the_one_judged_apart(spec):
    """The search's flap gap (compiled) against outside_check's, on curls drawn at random, both signs."""
    rng = np.random.default_rng(37)
    for _ in range(200):
        angles = np.radians(rng.uniform(-112, 112, spec.n_hinges)) * rng.choice([1.0, 0.4])  # curled, or not
        assert ours_flap_gap(spec, angles) == pytest.approx(flap_gap(spec, np.degrees(angles)), abs=1e-6)


def test_the_fat_torus_from_the_command_line_and_full_refused_where_its_flaps_meet(spec, tmp_path):
    """The issue's fat torus (R 85 mm, r 28 mm): ours, before 37 % of its touch surface inside and 26.3 mm
    deep, rests on it from outside, judged from the JSON a user gets; full, which curls the flaps into the
    tube until they meet from above (the broadest side's start; not from the default start, which ours' fit
    picks), is refused in one line."""
    fat_torus().export(tmp_path / "torus.stl")
    out = vrscroll("approximate", "--mesh", tmp_path / "torus.stl", "--variant", "refined", "--json",
                   tmp_path / "ours.json", timeout=300)
    if out.returncode:
        assert out.returncode == 2 and "cannot rest" in out.stderr and len(out.stderr.strip().splitlines()) == 1
    else:
        result = json.loads((tmp_path / "ours.json").read_text())
        assert holds(judge(spec, fat_torus(), result)), result
        assert result["flap_gap_mm"] >= 3.0 and result["inside_depth_mm"] <= 3.0 and result["flaps_through"] == 0
    above = ",".join(f"{v:g}" for v in side_starts(fat_torus())[0])  # from above, onto the tube
    out = vrscroll("approximate", "--mesh", tmp_path / "torus.stl", "--variant", "full", "--start", above, "--json",
                   tmp_path / "full.json", timeout=300)
    assert out.returncode == 2 and "flaps meet" in out.stderr and "Traceback" not in out.stderr, out.stderr
    assert not (tmp_path / "full.json").exists()


@pytest.mark.parametrize("name", ["bar", "sphere_12mm", "plate"])
def test_ours_rests_on_thin_and_small_shapes(spec, name):
    resting_on(spec, name, SHAPES[name]())


def test_a_pose_pressed_into_a_box_is_refused_saying_why(spec):
    """Ours' bar judged on a pose it did not make: flat 10 mm into a box's top is too deep; flaps curled into
    each other meet."""
    box = trimesh.creation.box((0.3, 0.3, 0.1))
    fields = build_fields(box)
    level = pose_from_mm_deg([0, 0, 40, 0, 0, 0])
    pressed = Approximation(level, np.zeros(spec.n_hinges), np.full(spec.n_flaps, spec.flap_pitch), 0.0, "refined")
    why = refusal(spec, box, resting(spec, box, fields, pressed), "refined")
    assert "too thin or too curved" in why and "10.0 mm inside" in why
    curled = Approximation(pose_from_mm_deg([0, 0, 60, 0, 0, 0]), np.radians(np.full(spec.n_hinges, 100.0)),
                           np.full(spec.n_flaps, spec.flap_pitch), 0.0, "full")
    assert "flaps meet" in refusal(spec, box, resting(spec, box, fields, curled), "full")
    full = dataclasses.replace(pressed, variant="full")  # the paper's variants: reported, not refused for depth
    assert refusal(spec, box, resting(spec, box, fields, full), "full") is None


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SHAPES))
def test_ours_rests_on_every_generated_shape(spec, name):
    resting_on(spec, name, SHAPES[name]())


@pytest.mark.slow
def test_ours_rests_on_the_whole_corpus(spec):
    refused = [name for name, mesh in corpus(seed=0) if resting_on(spec, name, mesh) is None]
    assert len(refused) <= 4, refused  # a refusal must be rare, not the way out
