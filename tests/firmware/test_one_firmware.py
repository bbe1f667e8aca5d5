"""One firmware: the single twin, the batch twin and the emulator's device run the same control step on the
same plant, so they agree to the encoder count."""

import numpy as np
import pytest

from controllers.encoder import target_counts
from controllers.pid import PidGains
from twin.link import protocol as P
from twin.link.emulator import Emulator, EmulatorOptions
from twin.device.variation import scaled
from twin.formats.run import RunStart
from twin.link.faults import FaultOptions
from twin.sim.plant import as_twin
from twin.sim.batch import TwinBatch
from twin.sim.replay import replay_batch, replay_targets, twin_at_start
from twin.sim.targets import TargetError
from twin.sim.twin import Twin

MOVE_DEG = [60.0, -45.0, 20.0, 30.0, 90.0, -100.0]  # every hinge moves


def emulated_counts(spec, targets, ticks: int) -> np.ndarray:
    """Encoder counts the emulated device reads each tick, commanded in process (no pty, no pacing)."""
    emu = Emulator(spec, EmulatorOptions(plant=as_twin(spec), faults=FaultOptions(latency_ms=0.0), zeroed=True))  # no latency
    emu.receive(P.encode(P.SetTargets(tuple(int(c) for c in target_counts(spec, targets))), 1))
    out = np.zeros((ticks, spec.n_hinges), np.int64)
    for i in range(ticks):
        if i and i % 100 == 0:  # the host's heartbeat, well inside the watchdog
            emu.receive(P.encode(P.Heartbeat(), i // 100 + 1))
        emu.step()
        out[i] = emu.counts
    assert emu.take_output()  # the ACK of SET_TARGETS
    return out


@pytest.mark.parametrize("timestep", [0.001, 0.0005])
def test_twin_batch_and_emulator_agree_to_the_count(spec, timestep):
    spec = spec.replace(timestep=timestep)
    targets = np.radians(MOVE_DEG)
    single = Twin(spec).move_to(targets, max_time=1.0, stop_when_settled=False)
    assert np.abs(single.counts[-1] - single.target_counts[-1]).max() <= spec.settle_band  # it did move
    batch = TwinBatch(2, spec, nthread=1).run(targets, 1.0)
    emulated = emulated_counts(spec, targets, len(single.time))
    for i in range(2):
        np.testing.assert_array_equal(batch["counts"][:, i], single.counts)
    np.testing.assert_array_equal(emulated, single.counts)


@pytest.mark.parametrize("reported", [True, False], ids=["integral reported", "history replayed"])
def test_a_recorded_run_replays_alike_on_the_single_and_the_batch_twin(spec, reported):
    """Calibration replays a run on many candidate plants at once (replay_batch), `vrscroll hil` on one twin as
    the telemetry comes in (twin_at_start, replay_targets): from the same start, with the integral the device
    reported or with the history before it, on plants that differ (one with each hinge its own motor), they
    agree to the count and the duty, tick by tick."""
    counts = target_counts(spec, np.radians([5.0, -3.0, 12.0, -12.0, 4.0, 0.0]))
    start = RunStart(counts, counts, "ACTIVE", counts + 40, counts + 60,
                     np.linspace(-0.2, 0.3, spec.n_hinges) if reported else None)
    changes = [(0.0, np.radians([5.0, -3.0, 12.0, -12.0, 4.0, 0.0])), (0.0304, np.radians(MOVE_DEG) / 3),
               (0.2, np.radians(MOVE_DEG) / 2)]
    plants = [spec, scaled(spec, {"gear_friction": 1.3, "no_load_speed": 0.8}), spec]
    hinges = [None, None, [scaled(spec, {"rotor_inertia": 0.8 + 0.1 * k}) for k in range(spec.n_hinges)]]
    gains = PidGains.from_spec(spec)
    ticks = 400
    batch_counts, batch_duty = replay_batch(plants, gains, start, changes, ticks, spec, hinges, nthread=2)
    for i, (plant, own) in enumerate(zip(plants, hinges)):
        twin = twin_at_start(plant, gains, start, spec, own)
        traces = [tr for _, tr in replay_targets(twin, changes, 0, ticks)]
        np.testing.assert_array_equal(batch_counts[:, i], np.concatenate([tr.counts for tr in traces]))
        np.testing.assert_array_equal(batch_duty[:, i], np.concatenate([tr.duty for tr in traces]))
    assert not np.array_equal(batch_counts[:, 0], batch_counts[:, 1])  # the plants differ, and it shows
    assert not np.array_equal(batch_counts[:, 0], batch_counts[:, 2])


def test_the_twins_firmware_faults_as_the_devices_does(spec):
    """The twin runs the core's supervisor: with stall detection on, motors too weak to lift the flaps stall,
    the core stops them (STALL), and refuses the next targets until the twin is reset. Off (the default, for
    runs into contact on purpose), the same twin keeps driving. (No cogging: its detents would hold the light end
    flaps, and every flap must sag here.)"""
    spec = spec.replace(drive_cap=0.0001, cogging=0.0)
    assert np.all(Twin(spec).hold(1.5).duty[-1] != 0.0)
    weak = Twin(spec, stall_detection=True)
    trace = weak.hold(1.5)
    assert weak.firmware.state == P.State.FAULT and weak.firmware.faults & P.Fault.STALL
    driven = np.flatnonzero(np.any(trace.duty != 0.0, axis=1))
    assert 0.3 < driven[-1] * spec.firmware_dt < 1.4  # driven hard until the stall time passed, then stopped
    with pytest.raises(TargetError, match="refused"):
        weak.move_to(np.zeros(spec.n_hinges))
    weak.reset()
    assert weak.firmware.state == P.State.ACTIVE


def test_twin_gains_outside_the_firmwares_bounds_are_refused_and_nothing_changes(spec):
    twin = Twin(spec)
    good = PidGains.from_spec(spec)
    with pytest.raises(ValueError, match="hinge 3: the firmware refuses"):
        twin.set_gains([good] * 3 + [good.replace(kp=2.0**31 - 1)] + [good] * 2)
    assert twin.gains == [good] * spec.n_hinges
    assert [twin.firmware.gains(k).kp for k in range(spec.n_hinges)] == pytest.approx([good.kp] * spec.n_hinges)
    batch = TwinBatch(2, spec, nthread=1)
    with pytest.raises(ValueError, match="simulation 1: hinge 0: the firmware refuses"):
        batch.set_gains([[good] * spec.n_hinges, [good.replace(integral_limit=2.0)] * spec.n_hinges])
    with pytest.raises(ValueError, match="simulation 0: hinge 0: the firmware refuses"):
        batch.set_gains([[good.replace(kd=-1e-4)] * spec.n_hinges, [good] * spec.n_hinges])
    assert batch.gains == [[good] * spec.n_hinges] * 2


def test_the_twins_pid_memory_is_the_cores(spec):
    """Twin.pid views the core's own PID memory (the HIL runs carry the integral across a reset)."""
    start = np.radians([10.0, 0, 0, 0, 0, -10.0])
    plain, pushed = Twin(spec), Twin(spec)
    for twin in (plain, pushed):
        twin.reset(start)
        assert list(twin.pid.prev) == list(twin.counts)
        assert np.all(twin.pid.integral == 0.0) and np.all(twin.pid.rate == 0.0)
    pushed.pid.integral[:] = 0.2  # written into the core: the next tick's duty carries it
    extra = pushed.hold(0.001).duty[0] - plain.hold(0.001).duty[0]
    assert np.all((extra >= 0.2 * (1 - spec.deadband_duty) - 1e-6) & (extra <= 0.2 + 1e-6)), extra


def test_the_emulator_answers_with_the_cores_bytes(spec):
    """Software in the loop: a SET_TARGETS repeated with its sequence number 50 ms later gets the core's
    original ACK (the same device time), and a device -> host message sent to it gets NACK UNKNOWN_MESSAGE."""
    emu = Emulator(spec, EmulatorOptions(plant=as_twin(spec), faults=FaultOptions(latency_ms=0.0), zeroed=True))  # no latency
    frame = P.encode(P.SetTargets((30, 0, 0, 0, 0, -30)), 7)
    replies = []
    for wait in (0, 50):
        for _ in range(wait):
            emu.receive(P.encode(P.Heartbeat(), 8))
            emu.step()
        emu.receive(frame)
        emu.step()
        replies.append(P.Decoder().feed(emu.take_output()))
    assert replies[0] == replies[1] == [(7, P.Ack(P.MsgId.SET_TARGETS, 0))]
    emu.receive(P.encode(P.Ack(P.MsgId.HELLO, 0), 9))
    emu.step()
    assert P.Decoder().feed(emu.take_output()) == [(9, P.NackMsg(P.MsgId.ACK, P.Nack.UNKNOWN_MESSAGE, 0))]
