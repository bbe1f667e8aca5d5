"""The gate on its own: each check, its numbers, and the override."""

import math

import mujoco
import numpy as np
import pytest

from controllers.pid import PidGains
from twin.device.flap_collision import CONTACT_DEPTH, flap_overlap
from twin.sim.gate import GateRefused, check_move, enforce, flap_contacts
from twin.sim.twin import Twin


@pytest.fixture(scope="module")
def twin(spec):
    return Twin(spec)


def by_name(report):
    return {c.name: c for c in report.checks}


def test_safe_move_passes_every_check_with_numbers(spec, twin):
    r = check_move(spec, np.zeros(6), np.radians([30, 10, 0, 0, -10, -30]), twin=twin)
    assert r.passed, r.text()
    c = by_name(r)
    assert set(c) == {"range", "collision", "settle", "peak_current", "hold_current", "i2t"}
    assert c["settle"].value < 2.0 and c["peak_current"].limit == spec.driver_peak_current
    assert 0 < c["i2t"].value < 100 and c["i2t"].unit == "%"
    assert c["hold_current"].limit == spec.continuous_current
    assert r.prediction is not None and len(r.prediction.time) > 10
    assert enforce(r) is r


def test_the_gate_predicts_the_firmwares_i2t_derating(spec):
    """The firmware's I2t protection runs in the twin: a motor with a small overload budget (0.02 s at stall
    current) is derated during a fast 60 deg move, and the gate names the hinge; the same move with the
    spec's budget passes. (A jam held at duty 0.45 is tests/firmware/test_firmware_core.py's.)"""
    small = spec.replace(overload_time=0.02)
    targets = np.radians([60, 0, 0, 0, 0, 0])
    i2t = by_name(check_move(small, np.zeros(6), targets))["i2t"]
    assert not i2t.passed and i2t.detail == "hinge 0: derated to its continuous current"
    assert by_name(check_move(spec, np.zeros(6), targets))["i2t"].passed


def test_out_of_range_is_refused_naming_hinge_and_limit(spec, twin):
    r = check_move(spec, np.zeros(6), np.radians([0, 0, 0, 0, 0, 120]), twin=twin)
    assert not r.passed and [c.name for c in r.failed] == ["range"]
    with pytest.raises(GateRefused, match=r"range 120.000 deg over limit 112.500 deg \(hinge 5\)"):
        enforce(r)


def test_curling_into_itself_is_a_collision(spec, twin):
    r = check_move(spec, np.zeros(6), np.radians([60] * 6), twin=twin)
    c = by_name(r)["collision"]
    assert not c.passed and c.value > 0 and "flap0 and flap6" in c.detail


def test_settle_and_current_limits_are_checked(spec, twin):
    r = check_move(spec, np.zeros(6), np.radians([90, 0, 0, 0, 0, 0]), twin=twin, settle_limit=0.02,
                   peak_current_limit=0.5, hold_current_limit=0.01)
    failed = {c.name for c in r.failed}
    assert failed == {"settle", "peak_current", "hold_current"}
    # a step from rest: the drive cap across the winding and the driver's FETs (less the pack's sag in the
    # tick before the firmware reads it)
    assert by_name(r)["peak_current"].value == pytest.approx(spec.drive_cap / spec.drive_resistance, rel=0.05)


def test_override_is_the_only_way_past_and_is_marked(spec, twin):
    r = check_move(spec, np.zeros(6), np.radians([60] * 6), twin=twin)
    with pytest.raises(GateRefused):
        enforce(r)
    assert enforce(r, override=True).overridden
    assert r.to_dict()["overridden"] is True


def test_gate_uses_the_device_gains(spec, twin):
    slow = PidGains.from_spec(spec).replace(kp=spec.kp / 20, ki=0.0)
    fast = check_move(spec, np.zeros(6), np.radians([40, 0, 0, 0, 0, 0]), twin=twin)
    weak = check_move(spec, np.zeros(6), np.radians([40, 0, 0, 0, 0, 0]), [slow] * 6, twin=twin)
    assert by_name(weak)["settle"].value > by_name(fast)["settle"].value or not weak.passed
    assert math.isfinite(by_name(fast)["settle"].value)


def test_geometric_flap_overlap_agrees_with_the_gates_mujoco_check(spec, twin):
    """Random curls (half of them deep enough to collide): the separating-axis depth and MuJoCo's
    flap-on-flap contacts say the same, but within 0.05 mm of the threshold, where either may tip."""
    rng = np.random.default_rng(11)
    data = mujoco.MjData(twin.model)
    hits = 0
    for _ in range(400):
        angles = rng.uniform(0.3, 1.0, spec.n_hinges) * spec.hinge_limit * rng.choice([-1, 1]) * (
            rng.random(spec.n_hinges) < 0.8)
        depth = flap_overlap(spec, angles)
        contacts = flap_contacts(twin.model, data, twin.hinges.qadr, angles)
        mj_depth = max((c[2] for c in contacts), default=0.0)
        hits += bool(contacts)
        if abs(depth - CONTACT_DEPTH) > 5e-5:
            assert (depth > CONTACT_DEPTH) == bool(contacts), (np.degrees(angles), depth, mj_depth)
        if contacts:
            assert depth == pytest.approx(mj_depth, abs=0.5e-3)
    assert hits > 100
