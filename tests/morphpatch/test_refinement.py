"""Ours beyond the paper (variant "refined") and the HCEVF translation along the surface, on all eight shapes.

Starts: 10 per shape from the evaluation's generator with a seed the evaluation does not use
(the committed Table 1 has the 50-start figures); the refinement's bounds also from 50 more per shape
of a seed nothing else uses.
"""

import math

import numpy as np
import pytest
import trimesh

from twin.device.flap_collision import collides, flap_boxes, flap_overlap
from twin.device.kinematics import pose_matrix
from twin.evaluation.starts import approach_starts
from twin.morphpatch.approximation import VARIANTS, approximate, measured, root_pose
from twin.morphpatch.fields import build_fields, exact_signed_distance
from twin.morphpatch.refinement import ANCHOR_DEPTH, ANCHOR_RADIUS, INSIDE_LIMIT, LIFT_REACH, uncurled
from twin.morphpatch.resting import DEEP_SHARE_MAX, DEEPEST_MAX, FLAP_APART_MIN, resting
from twin.morphpatch.shapes import load_shape, shape_names, sweep_solid
from twin.sim.gate import check_move
from twin.sim.twin import Twin

STARTS, SEED = 10, 5
FRESH_STARTS, FRESH_SEED = 50, 13  # starts of a seed no other test, benchmark or evaluation uses
ANCHOR_INSIDE = 1e-3  # m: no anchor ends deeper than this in the target (exact mesh)


@pytest.fixture(scope="module")
def runs(spec):
    """shape -> (mesh, starts, {variant: [measured results]}), every variant from the same starts."""
    out = {}
    for name in shape_names():
        mesh = load_shape(name)
        fields = build_fields(mesh)  # (the session's cache: conftest's VRSCROLL_CACHE)
        starts = approach_starts(mesh, STARTS, seed=SEED)
        out[name] = (mesh, fields, starts, {v: [measured(spec, mesh, approximate(fields, s, spec, v)) for s in starts]
                                            for v in VARIANTS})
    return out


def anchor_depths(mesh, results):
    """How far each result's anchor is inside the target, m (negative: outside)."""
    return -exact_signed_distance(mesh, np.array([r.root_pose[:3, 3] for r in results]))[0]


def test_no_anchor_ends_inside_the_target(runs):
    """Before the HCEVF translation slid along the surface, 19 of 50 ellipsoid starts and 15 of 50 torus
    starts ended with the anchor more than 5 mm inside."""
    for name, (mesh, _, _, results) in runs.items():
        for variant, rs in results.items():
            # ours delivers only a pose that rests; one that does not is refused (`approximate` exits 2, counted in
            # test_ours_refuses_few_of_the_paper_shapes_starts), so it is not the user's anchor
            # ours' anchor is a point of its touch surface, which rests within resting.DEEPEST_MAX of the surface
            # (its search keeps the grid's 1.5 mm); the paper's variants keep the 1 mm the HCEVF fix reached
            delivered = [r for r in rs if variant != "refined" or r.rests]
            limit = DEEPEST_MAX if variant == "refined" else ANCHOR_INSIDE
            assert not delivered or anchor_depths(mesh, delivered).max() < limit, (name, variant)


def test_hcevf_translation_keeps_the_anchor_on_a_wave(spec):
    """A sinusoidal wave (amplitude 25 mm, wavelength 80 mm: its crests and troughs are ridges) from above:
    the paper's 3-D HCEVF move leaves the anchor inside it (a wave: 8.5 mm); moved along the
    surface and re-snapped, it stays on it."""
    x = np.linspace(-0.15, 0.15, 121)
    profile = np.vstack([np.c_[x, 0.06 + 0.025 * np.sin(2 * math.pi * x / 0.08)], [[0.15, 0.0], [-0.15, 0.0]]])
    sections = [np.array([[1.0, 0, 0, 0], [0, 0, 0, y], [0, 1, 0, 0], [0, 0, 0, 1]]) for y in (-0.12, 0.12)]
    wave = sweep_solid(profile, sections)
    if wave.volume < 0:
        wave.invert()
    fields = build_fields(wave, disk_cache=False)
    rng = np.random.default_rng(2)
    for _ in range(8):
        tilt = trimesh.transformations.euler_matrix(*rng.uniform(-0.2, 0.2, 3))[:3, :3]
        start = pose_matrix([rng.uniform(-0.05, 0.05), rng.uniform(-0.03, 0.03), 0.15], tilt)
        result = approximate(fields, start, spec, "full")
        assert abs(exact_signed_distance(wave, result.root_pose[None, :3, 3])[0][0]) < ANCHOR_INSIDE


def assert_rests_and_fits(spec, meshes, results):
    """Ours on {shape: {variant: [measured results]}} (issue 37: the 20 %-below-full goal of issue 22 is retired,
    full goes through the target where ours may not): every result of ours rests on the target from outside
    (twin.morphpatch.resting's bar, exact mesh), and from every start where full's own pose keeps within ours'
    search's bounds too (no deeper than INSIDE_LIMIT, flaps apart), ours' MSD is at most 0.5 mm above full's."""
    refused = 0
    for name, by_variant in results.items():
        for full, ours in zip(by_variant["full"], by_variant["refined"]):
            r = resting(spec, meshes[name], None, ours, through=False)
            if not ours.rests:  # ours found no pose resting from outside: `approximate` refuses it
                refused += 1
                continue
            assert r.deepest <= DEEPEST_MAX and r.deep_share <= DEEP_SHARE_MAX, (name, r)
            f = resting(spec, meshes[name], None, full, through=False)
            if f.deepest <= INSIDE_LIMIT and f.gap >= FLAP_APART_MIN:  # full within ours' own search bounds
                assert ours.msd <= full.msd + 0.5e-3, (name, ours.msd, full.msd)
    return refused


def test_ours_rests_and_fits_where_full_rests_on_every_shape(spec, runs):
    assert_rests_and_fits(spec, {n: m for n, (m, _, _, _) in runs.items()},
                          {name: results for name, (_, _, _, results) in runs.items()})


def test_ours_refuses_few_of_the_paper_shapes_starts(spec, runs):
    """At most 10 % of these 80 starts refused (14 were, before a start could be lifted out of the anchor's ball
    to rest: now none)."""
    refused = assert_rests_and_fits(spec, {n: m for n, (m, _, _, _) in runs.items()},
                                    {name: results for name, (_, _, _, results) in runs.items()})
    assert refused <= 0.1 * len(runs) * STARTS, refused


@pytest.mark.slow  # 11 s; the same bounds on the fixture's starts stay in the default suite
def test_ours_rests_and_fits_from_starts_nobody_tuned_for(spec, runs):
    """The same from FRESH_STARTS more starts per shape of a seed nothing else uses."""
    results = {}
    for name, (mesh, fields, _, _) in runs.items():
        starts = approach_starts(mesh, FRESH_STARTS, seed=FRESH_SEED)
        results[name] = {v: [measured(spec, mesh, approximate(fields, s, spec, v)) for s in starts]
                         for v in ("full", "refined")}
    assert_rests_and_fits(spec, {n: m for n, (m, _, _, _) in runs.items()}, results)


def test_ours_keeps_the_anchor_where_the_user_brought_the_device(spec, runs):
    """Within ANCHOR_RADIUS of where the device snapped onto the target; or, where no pose within that ball rests
    from outside, within the ball lifted with the start by at most LIFT_REACH more, its anchor no deeper in the target
    than any anchor may be (ANCHOR_DEPTH): since the bounded search's step keeps the depth bound, it can bring the
    anchor back down to the surface at the lifted ball's edge (torus start 6: 21.5 mm from the snapped point, 0.29 mm
    in; before, its lifted ends there stood 18.6-23.1 mm off the surface)."""
    for name, (mesh, fields, starts, results) in runs.items():
        snapped = np.array([root_pose(fields, s, spec)[:3, 3] for s in starts])
        anchors = np.array([r.root_pose[:3, 3] for r in results["refined"]])
        away = np.linalg.norm(anchors - snapped, axis=1)
        lifted = away > ANCHOR_RADIUS + 1e-9
        assert away.max() <= ANCHOR_RADIUS + LIFT_REACH + 1e-9, name
        out = [r for r, up in zip(results["refined"], lifted) if up]
        assert not out or anchor_depths(mesh, out).max() < ANCHOR_DEPTH, name


def test_every_result_of_ours_passes_the_gates_range_and_collision_checks(spec, runs):
    twin = Twin(spec)
    for name, (_, _, _, results) in runs.items():
        for r in results["refined"]:
            checks = {c.name: c for c in check_move(spec, np.zeros(spec.n_hinges), r.angles, twin=twin).checks}
            assert checks["range"].passed and checks["collision"].passed, (name, checks)


def test_ours_unrolls_a_curl_the_pipeline_leaves_in_contact(spec):
    """A 20 mm cylinder: the pipeline wraps 188 mm of flaps round its 126 mm circumference, flap 0 into flap 6;
    ours gives a pose the device can take."""
    axis_y = trimesh.transformations.rotation_matrix(math.pi / 2, [1, 0, 0])
    axis_y[2, 3] = 0.05
    rod = trimesh.creation.cylinder(0.02, 0.25, sections=64, transform=axis_y)
    fields = build_fields(rod, disk_cache=False)
    start = pose_matrix([0.003, 0.0, 0.09], np.eye(3))
    assert flap_overlap(spec, approximate(fields, start, spec, "full").angles) > 1e-3
    ours = approximate(fields, start, spec, "refined")
    assert flap_overlap(spec, ours.angles) == 0.0
    checks = {c.name: c for c in check_move(spec, np.zeros(spec.n_hinges), ours.angles).checks}
    assert checks["range"].passed and checks["collision"].passed


def test_a_curl_into_flap_contact_is_unrolled_from_its_tips(spec):
    """Curls drawn at random (each hinge 20-90 deg, one sign, into contact): unrolled, the flaps are apart, no
    hinge turns more or the other way, and the two hinges beside the root flap keep their angles wherever the
    outer ones alone part the flaps (scaling every angle down together, as before, fails this)."""
    boxes = flap_boxes(spec)
    rng = np.random.default_rng(2026)
    inner = [spec.root_flap - 1, spec.root_flap]
    tried = 0
    while tried < 20:
        curled = np.radians(rng.uniform(20, 90, spec.n_hinges)) * rng.choice([-1.0, 1.0])
        if not collides(boxes, curled, 0.0):
            continue
        tried += 1
        a = uncurled(spec, curled)
        assert not collides(boxes, a, 0.0), np.degrees(curled)
        assert np.all(a * curled >= 0) and np.all(np.abs(a) <= np.abs(curled)), (np.degrees(curled), np.degrees(a))
        if not collides(boxes, np.where(np.isin(np.arange(spec.n_hinges), inner), curled, 0.0), 0.0):
            np.testing.assert_array_equal(a[inner], curled[inner])


def test_ours_curls_round_a_can_it_was_brought_to_lengthwise(spec):
    """A closed can 120 mm across, nobody's shape, approached from the side with the row within 30 deg of its
    axis (drawn): the pipeline keeps the row along the side, where it cannot curl (its MSD 9-13 mm); ours, also
    refining from the root turned a quarter about its normal, wraps it (under 4 mm; without the turned start it
    ended at 9-10 mm)."""
    can = trimesh.creation.cylinder(radius=0.06, height=0.12, sections=64)  # its axis z
    fields = build_fields(can, disk_cache=False)
    rng = np.random.default_rng(31)
    for yaw in np.radians(rng.uniform(0, 30, 3)):
        row = np.array([0.0, math.sin(yaw), math.cos(yaw)])
        out = np.array([1.0, 0.0, 0.0])  # the device's +z: it approaches along -x
        start = pose_matrix([0.1, 0.0, 0.0], np.column_stack([row, np.cross(out, row), out]))
        full, ours = (measured(spec, can, approximate(fields, start, spec, v)) for v in ("full", "refined"))
        assert ours.msd < 4e-3 < full.msd, (math.degrees(yaw), ours.msd, full.msd)


def test_the_bounded_step_is_the_models_minimum_with_every_sample_above_the_floor():
    """`_kept_out` (its own factorisation and active set, no LAPACK call) on random models of 2 flaps x 6 samples and
    8 parameters, some directions blocked: the step lies in the basis' span, keeps every sample's linearised S at or
    above the floor (to FLOOR_SLACK), and no feasible step in that span has a lower model value (SLSQP from the same
    problem); with the floor far below every sample it is the unconstrained damped step. (1 to 4 samples active in
    19 of the 20 models.)"""
    from scipy.optimize import minimize

    from twin.morphpatch.refinement import FLOOR_SLACK, _kept_out

    rng = np.random.default_rng(37)
    n_flaps, samples, n = 2, 6, 8
    for case in range(20):
        jac = rng.normal(size=(n + 4, n))
        hessian = jac.T @ jac + 0.1 * np.eye(n)
        grad = rng.normal(size=n)
        lin = np.empty((n_flaps, samples, 7))
        lin[:, :, 0] = rng.uniform(-1e-3, 3e-3, size=(n_flaps, samples))  # S (m)
        lin[:, :, 1:] = rng.normal(scale=3e-3, size=(n_flaps, samples, 6))
        mfs = rng.normal(size=(n_flaps, n, 6))
        basis = np.eye(n)[:, :n - case % 3]  # with the last parameters blocked in some cases
        lhs, reduced = basis.T @ hessian @ basis, basis.T @ grad
        floor = -1.125e-3
        step = _kept_out(lhs, reduced, basis, lin, mfs, floor)
        z = basis.T @ step
        np.testing.assert_allclose(basis @ z, step, atol=1e-12)
        rows = np.concatenate([basis.T @ mfs[f] @ lin[f, :, 1:].T for f in range(n_flaps)], axis=1).T
        s = lin[:, :, 0].ravel()
        assert np.all(s + rows @ z >= floor - FLOOR_SLACK - 1e-12), case  # (at most 4 of ACTIVE_STEPS active here)
        best = minimize(lambda x: 0.5 * x @ lhs @ x + reduced @ x, np.zeros(len(z)), jac=lambda x: lhs @ x + reduced,
                        method="SLSQP", options={"ftol": 1e-14, "maxiter": 500},
                        constraints={"type": "ineq", "fun": lambda x: s + rows @ x - floor, "jac": lambda x: rows})
        value = 0.5 * z @ lhs @ z + reduced @ z
        assert best.success and value <= best.fun + 1e-9 * (1 + abs(best.fun)), (case, value, best.fun)
        free = _kept_out(lhs, reduced, basis, lin, mfs, -1.0)
        np.testing.assert_allclose(free, -basis @ np.linalg.solve(lhs, reduced), rtol=1e-9, atol=1e-12)
