"""The twin with its firmware in the loop: targets, limits, gravity, batch."""

import csv
import math

import numpy as np
import pytest

from twin.formats.trace import write_trace
from twin.sim.batch import TwinBatch
from twin.sim.response import move_report
from twin.sim.targets import TargetError
from twin.sim.twin import Twin

TARGETS_DEG = [60.0, -45.0, 0.0, 30.0, 90.0, -100.0]


@pytest.fixture(scope="module")
def twin():
    return Twin()


def test_every_hinge_reaches_and_settles(twin):
    twin.reset()
    trace = twin.move_to(np.radians(TARGETS_DEG), max_time=1.0)
    report = move_report(twin.spec, trace)
    band = twin.spec.settle_band
    assert np.all(report.settle_time <= 0.5), report
    assert np.all(np.abs(report.steady_state_error_counts) <= band), report
    assert np.all(np.abs(trace.target_counts[-1] - trace.counts[-1]) <= band)
    assert np.degrees(trace.true_angle[-1]) == pytest.approx(TARGETS_DEG, abs=band * 360 / 1204.44 + 0.5)
    # currents stay at or below stall; duty within [-1, 1]
    assert np.abs(trace.current).max() <= twin.spec.stall_current + 1e-9
    assert np.abs(trace.duty).max() <= 1.0


def test_target_beyond_range_is_refused_not_clipped(twin):
    twin.reset()
    with pytest.raises(TargetError, match=r"hinge 4: target 113.00 deg is outside the hinge range \+-112.5 deg"):
        twin.move_to(np.radians([0, 0, 0, 0, 113.0, 0]))
    assert twin.angles == pytest.approx(np.zeros(6))  # nothing moved
    with pytest.raises(TargetError, match="expected 6"):
        twin.move_to([0.1, 0.2])


def test_encoder_counts_are_quantized(spec):
    """The encoder counts the motor's turns (with no backlash the flap turns with it; with backlash see
    tests/device/test_drive_train.py)."""
    twin = Twin(spec.replace(backlash=0.0))
    trace = twin.move_to(np.radians([20.0, 0, 0, 0, 0, 0]), max_time=0.3)
    motor_turns = trace.true_angle[:, 0] * twin.spec.gear_ratio / (2 * math.pi)
    assert np.array_equal(trace.counts[:, 0], np.floor(motor_turns * 12).astype(int))


@pytest.mark.parametrize("quat", [(1, 0, 0, 0), (math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0)],
                         ids=["flat", "on-edge"])
def test_gravity_held_flat(twin, quat):
    """Held flat (or standing on its long edge) with motors holding, the device keeps its shape."""
    twin.reset()
    twin.set_root_pose([0, 0, 0], quat)
    trace = twin.hold(2.0)
    assert np.abs(np.degrees(trace.true_angle)).max() < 1.0  # deg
    twin.set_root_pose([0, 0, 0])


def test_gravity_sags_without_motors(spec):
    """The test above can fail: with the motors unable to push, gravity bends the outer flaps."""
    weak = Twin(spec.replace(drive_cap=0.0001, gear_friction=0.0, gear_stiction=0.0))
    trace = weak.hold(1.0)
    assert np.abs(np.degrees(trace.true_angle[-1])).max() > 5.0


def test_trace_csv(tmp_path, twin, spec):
    twin.reset()
    trace = twin.move_to(np.radians(TARGETS_DEG), max_time=0.2, stop_when_settled=False)
    path = tmp_path / "trace.csv"
    write_trace(path, trace)
    rows = list(csv.DictReader(open(path)))
    assert len(rows) == 200
    assert {"time_s", "h0_target_deg", "h0_angle_deg", "h0_counts", "h0_duty", "h0_current_A", "h5_torque_Nm"} <= set(rows[0])
    assert float(rows[1]["time_s"]) - float(rows[0]["time_s"]) == pytest.approx(0.001)


def test_batch_matches_single_twin(spec):
    twin = Twin(spec)
    single = twin.move_to(np.radians(TARGETS_DEG), max_time=0.3, stop_when_settled=False)
    batch = TwinBatch(3, spec, nthread=1)
    out = batch.run(np.radians(TARGETS_DEG), 0.3)
    for i in range(3):
        assert np.array_equal(out["counts"][:, i], single.counts)
        assert out["angle"][:, i] == pytest.approx(single.true_angle, abs=1e-9)


def test_batch_runs_perturbed_plants(spec):
    slow = spec.replace(gear_friction=spec.gear_friction * 3)
    batch = TwinBatch(2, spec, specs=[spec, slow], nthread=1)
    out = batch.run(np.radians(TARGETS_DEG), 0.1)
    assert not np.array_equal(out["angle"][:, 0], out["angle"][:, 1])


def test_free_root(spec):
    twin = Twin(spec, root="free")
    twin.set_root_pose([0, 0, 0.5])
    trace = twin.hold(0.2)
    assert twin.data.qpos[2] < 0.5 - 0.15  # falls under gravity: 0.5 g t^2 ~ 0.196 m
    assert len(trace.time) == 200
