"""Shapes nobody tuned the approximation for (twin/evaluation/shape_corpus.py): from seeded starts all round each, no
variant's anchor crosses the solid, ours passes no more flaps through it than full (its flaps apart), and each shape's side
starts are outside it; lowered onto a cup narrower than the device, no variant goes into it. The default suite takes a
bowl and a cup (the concave families, where crossing is possible); the slow suite the whole corpus, 10 starts
each. How well each variant fits them is measured, not asserted: benchmarks/bench_corpus.py,
docs/approximation.md "Shapes nobody tuned for"."""

import igl
import numpy as np
import pytest

from twin.device.flap_collision import collides, flap_boxes
from twin.evaluation.shape_corpus import corpus, crossed, person_starts, starts
from twin.morphpatch.approximation import VARIANTS, approximate, measured, pose_from_mm_deg, root_pose
from twin.morphpatch.default_start import default_start
from twin.morphpatch.fields import build_fields
from twin.morphpatch.refinement import flaps_through, uncurled
from twin.morphpatch.resting import refusal, resting
from twin.morphpatch.shapes import side_starts
from twin.morphpatch.surface_metrics import match


def check_shapes(spec, shapes, n_starts):
    for i, (name, mesh) in enumerate(shapes):
        fields = build_fields(mesh)
        sides = np.array([pose_from_mm_deg(s)[:3, 3] for s in side_starts(mesh)])
        assert igl.signed_distance(sides, mesh.vertices, mesh.faces)[0].min() > 0.03, name
        for start in starts(mesh, n_starts, seed=100 + i):
            snapped = root_pose(fields, start, spec)[:3, 3]
            assert not crossed(mesh, start[:3, 3], snapped), (name, start[:3, 3])
            through = {}
            for variant in VARIANTS:
                a = approximate(fields, start, spec, variant)
                assert not crossed(mesh, snapped, a.root_pose[:3, 3]), (name, variant, start[:3, 3], a.root_pose)
                angles = uncurled(spec, a.angles)  # full's pose as the device can take it: its flaps apart
                through[variant] = flaps_through(fields, spec, a.root_pose, angles, a.widths)
            assert through["refined"] <= through["full"], (name, start[:3, 3], through)  # ours adds no flap through it


def over_the_rim(mesh) -> list[float]:
    """A start 40 mm above a corpus cup's rim, level, over the middle of its wall's top on the side away from the
    handle (the handle is on +x, the cup's axis at y = 0), [mm, deg]."""
    v = mesh.vertices
    rim = v[(v[:, 2] > v[:, 2].max() - 1e-4) & (np.abs(v[:, 1]) < 2e-3)]
    left = rim[rim[:, 0] < np.median(rim[:, 0])]
    x = float(left[:, 0].min() + left[:, 0].max()) / 2
    return [x * 1e3, 0.0, float(mesh.bounds[1, 2] + 0.04) * 1e3, 0.0, 0.0, 0.0]


CAVITY = 6e-3  # m: an anchor this far inside a cup's convex hull is down in its cavity (the rim is on the hull)


@pytest.mark.parametrize("seed", [
    pytest.param(0, marks=pytest.mark.slow),  # failed (cup_3, 11.6 mm in) while the turned refinement was gated
    3])  # 0: the cups looked at first
def test_lowered_onto_a_cup_narrower_than_the_device_no_variant_goes_into_it(spec, seed):
    """Cups with a handle, 60-120 mm across (the device 188 x 175 mm), lowered from above onto the rim:
    every variant's anchor ends on the rim or the outer wall, not down in the cavity with the flaps through the
    wall (ours went 12-17 mm into seed 0's cups before its flaps were kept from passing through the target)."""
    for name, mesh in corpus(seed=seed, families=("cup",)):
        fields = build_fields(mesh)
        hull = mesh.convex_hull
        start = pose_from_mm_deg(over_the_rim(mesh))
        for variant in VARIANTS:
            anchor = approximate(fields, start, spec, variant).root_pose[:3, 3]
            depth = -igl.signed_distance(anchor[None], hull.vertices, hull.faces)[0][0]
            assert depth <= CAVITY, (name, variant, anchor, depth)


def test_a_bowl_and_a_cup_nobody_tuned_for(spec):
    check_shapes(spec, corpus(seed=7, families=("bowl", "cup"), per_family=1), 5)


@pytest.mark.slow
def test_the_whole_corpus(spec):
    check_shapes(spec, corpus(seed=0), 10)


@pytest.mark.slow  # about 10 s: cup_1's fields and ten approximations
def test_where_no_start_rests_near_the_cup_ours_anchor_keeps_to_the_side_it_came_from(spec):
    """Seed 0's cup_1 from bench_corpus.py's ten starts (where issue 37's fifth session found one of ours' anchors
    across the wall: on start 2 no start rested within the anchor's ball, the ball's centre went up with the lift,
    and the search kept its anchor's line to that lifted centre clear, not its line to the snapped point): the
    straight line from the snapped point to ours' anchor stays out of the solid (exact mesh, 2.5 mm)."""
    index, (name, mesh) = next((i, c) for i, c in enumerate(corpus(seed=0)) if c[0] == "cup_1")
    fields = build_fields(mesh)
    for start in starts(mesh, 10, seed=index):  # the benchmark's starts: seed 0 * 1000 + the shape's index
        snapped = root_pose(fields, start, spec)[:3, 3]
        assert not crossed(mesh, snapped, approximate(fields, start, spec, "refined").root_pose[:3, 3]), start[:3, 3]


@pytest.mark.slow  # about 10 s: height_field_3's fields and one approximation
def test_met_at_a_slabs_bottom_edge_ours_curls_under_it_not_onto_its_side(spec):
    """Seed 0's height_field_3 from bench_reachable's start 1, which meets the slab at its bottom edge (issue 37's
    seventh session: from commit 928d6ca to its mend ours ended standing on the side wall, root normal (0.98, 0.03,
    -0.18), 13.7 mm MSD, where the best poses within its bounds turn the root towards the flat underside, 5 mm):
    the first phase's curl under the slab rests at no lift along the root's normal, so the pipeline's curl is
    searched lifted; ours rests on the exact mesh with its root turned at least half way to the underside, and its
    MSD is under 8 mm."""
    index, (name, mesh) = next((i, c) for i, c in enumerate(corpus(seed=0)) if c[0] == "height_field_3")
    fields = build_fields(mesh)
    a = approximate(fields, starts(mesh, 3, seed=index)[1], spec, "refined")
    assert refusal(spec, mesh, resting(spec, mesh, fields, a), "refined", a.rests) is None
    assert a.root_pose[2, 2] < -0.5, a.root_pose[:3, 2]
    assert match(spec, mesh, a.root_pose, a.angles, a.widths).msd < 8e-3


@pytest.mark.slow  # 9 s: the default suite keeps the unrolling's own test (test_refinement.py)
@pytest.mark.xfail(strict=True, reason=(
    "issue 37: ours rests on the target from outside, and full's pose unrolled lies 6.5-16.7 mm deep in torus_0's "
    "tube; resting, ours ends at 14.2-24.5 mm (torus_0) and 19.6-28.2 mm (torus_2) against that pose's 8.5-11.1 "
    "and 11.4-14.7 (round 4, ours4's measurement): a bound from before the one-sided objective"))
def test_on_tori_whose_full_pose_presses_flaps_together_ours_refines_from_it_unrolled(spec):
    """Seed 7's tori whose tube full wraps until its tips meet (torus_0 and torus_2; the gate refuses such a
    pose): ours unrolls full's pose and refines on from there. On every torus_0 start it ends at least 1 %
    below that pose unrolled (MSD, exact mesh), and on no start of either above it by more than 0.1 mm.
    Before the search held the hinges a step curled into contact, it stopped where it began on every torus_0
    start."""
    boxes = flap_boxes(spec)
    for i, (name, mesh) in enumerate(corpus(seed=7, families=("torus",))):
        if name not in ("torus_0", "torus_2"):
            continue
        fields = build_fields(mesh)
        for start in starts(mesh, 5, seed=100 + i):
            full = approximate(fields, start, spec, "full")
            assert collides(boxes, full.angles, 0.0), (name, start[:3, 3])
            refined = approximate(fields, start, spec, "refined")
            ours = match(spec, mesh, refined.root_pose, refined.angles, refined.widths).msd
            unrolled = match(spec, mesh, full.root_pose, uncurled(spec, full.angles), full.widths).msd
            assert ours <= unrolled + 1e-4, (name, start[:3, 3], ours, unrolled)
            if name == "torus_0":
                assert ours <= 0.99 * unrolled, (name, start[:3, 3], ours, unrolled)


@pytest.mark.slow  # 8 fields built: minutes
def test_the_default_start_does_as_well_as_the_starts_a_person_would_try(spec):
    """Issue 37: on one shape of each corpus family drawn from a seed the default start was not chosen on (3), ours
    from the default start (twin.morphpatch.default_start) against ours from the starts a person would try
    (person_starts: from above and each side, over the middle): delivered wherever one of theirs is, and its MSD
    (exact mesh; a refused pose counts as infinite) at or below the median of theirs on at least 6 of the 8 shapes
    (the broadest side alone: 2 of 8). Seed 0's with benchmarks/bench_default_start.py: docs/approximation.md,
    "Starts"."""
    def ours(mesh, fields, start) -> float:
        a = measured(spec, mesh, approximate(fields, pose_from_mm_deg(start), spec, "refined"))
        refused = refusal(spec, mesh, resting(spec, mesh, fields, a), "refined", a.rests) is not None
        return float("inf") if refused else a.msd
    at_or_below = 0
    for name, mesh in corpus(seed=3, per_family=1):
        fields = build_fields(mesh)
        default = ours(mesh, fields, default_start(mesh, fields, spec))
        theirs = sorted(ours(mesh, fields, s) for s in person_starts(mesh))
        assert default < float("inf") or theirs[0] == float("inf"), (name, theirs)
        at_or_below += default <= theirs[2]
    assert at_or_below >= 6, at_or_below
