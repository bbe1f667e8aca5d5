"""Skipping collision detection while the flaps are apart: the bound against MuJoCo's own geometry, and the
twin that uses it against the batch twin, which never skips."""

import mujoco
import numpy as np

from twin.device.flap_collision import APART_CLEARANCE, apart, apart_spreads
from twin.device.mjcf import load_model, mjcf
from twin.sim.batch import TwinBatch
from twin.sim.hinges import Hinges, contact_free_spreads, place_hinges
from twin.sim.twin import Twin


def flap_distances(spec, model, data, hinges, angles) -> float:
    """MuJoCo's smallest distance (m) between the boxes of any two flaps two or more apart."""
    mujoco.mj_resetData(model, data)
    place_hinges(data.qpos, hinges, angles)
    mujoco.mj_forward(model, data)
    g = [model.geom(f"flap{i}_collision").id for i in range(spec.n_flaps)]
    return min(mujoco.mj_geomDistance(model, data, g[i], g[j], 0.1, None)
               for i in range(spec.n_flaps) for j in range(i + 2, spec.n_flaps))


def test_flaps_the_bound_calls_apart_are_apart_in_mujoco(spec):
    """Random poses, and each of them scaled to just inside the bound (where it is tightest): wherever `apart`
    holds, MuJoCo's boxes are at least the clearance apart; and it does hold for a fair share of poses."""
    model = load_model(spec)
    data, hinges = mujoco.MjData(model), Hinges(model, spec.n_hinges)
    spreads = apart_spreads(spec)
    rng = np.random.default_rng(3)
    held = 0
    for _ in range(300):
        angles = rng.uniform(-1, 1, spec.n_hinges) * spec.hinge_limit * (rng.random(spec.n_hinges) < 0.8)
        lo, hi = 0.0, 1.0  # the largest scale of this pose that the bound still calls apart
        if apart(spreads, angles):
            held += 1
            lo = 1.0
        else:
            for _ in range(30):
                mid = (lo + hi) / 2
                lo, hi = (mid, hi) if apart(spreads, mid * angles) else (lo, mid)
        for pose in {1.0, lo} - {0.0}:
            if apart(spreads, pose * angles):
                assert flap_distances(spec, model, data, hinges, pose * angles) >= APART_CLEARANCE, np.degrees(angles)
    assert held > 60


def test_flaps_folded_back_to_back_touch_and_the_bound_says_so(spec):
    """Two flaps folded back onto their neighbour (convex, the boxes' backs meeting): the bound gives way
    before MuJoCo finds them touching, and refuses them once they do."""
    model = load_model(spec)
    data, hinges = mujoco.MjData(model), Hinges(model, spec.n_hinges)
    spreads = apart_spreads(spec)
    fold = np.zeros(spec.n_hinges)
    fold[4:] = -spec.hinge_limit
    assert flap_distances(spec, model, data, hinges, fold) <= 0 and not apart(spreads, fold)
    fold[4:] = -np.radians(60)
    assert apart(spreads, fold)


def test_the_twin_skipping_collisions_moves_as_the_batch_twin_to_the_bit(spec):
    """Random targets and one that curls flaps into each other: the twin (which skips collision detection
    where the flaps are apart) and the batch twin (which never skips) give the same angles to the bit."""
    rng = np.random.default_rng(7)
    curl = np.zeros(spec.n_hinges)
    curl[:3] = np.radians(112)
    targets = [curl] + [rng.uniform(-1, 1, spec.n_hinges) * spec.hinge_limit for _ in range(3)]
    twin, batch = Twin(spec), TwinBatch(1, spec, nthread=1)
    spreads = contact_free_spreads(spec, twin.model)
    skipped = touched = False
    for t in targets:
        twin.reset()
        single = twin.move_to(t, max_time=0.6, stop_when_settled=False)
        touched |= twin.data.ncon > 0
        skipped |= any(apart(spreads, a) for a in single.true_angle)
        batch.reset()
        np.testing.assert_array_equal(batch.run(t, 0.6)["angle"][:, 0], single.true_angle)
    assert skipped and touched


def test_a_scene_with_more_to_collide_never_skips(spec):
    assert len(contact_free_spreads(spec, load_model(spec))) == spec.n_flaps - 1
    target = mjcf(spec).replace("<worldbody>", '<worldbody>\n    <geom type="sphere" size="0.01" pos="0 0 0.1"/>')
    assert len(contact_free_spreads(spec, mujoco.MjModel.from_xml_string(target))) == 0
    neighbours_collide = "\n".join(line for line in mjcf(spec).splitlines() if "<exclude" not in line)
    assert len(contact_free_spreads(spec, mujoco.MjModel.from_xml_string(neighbours_collide))) == 0
