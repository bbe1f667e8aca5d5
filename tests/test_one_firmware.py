"""One firmware: the single twin, the batch twin and the emulator's device run the same control step on the
same plant, so they agree to the encoder count."""

import numpy as np
import pytest

from controllers.encoder import target_counts
from twin.link import protocol as P
from twin.link.emulator import Emulator, EmulatorOptions
from twin.link.faults import FaultOptions
from twin.link.plant import IDEAL
from twin.sim.simulation import Twin, TwinBatch

MOVE_DEG = [60.0, -45.0, 20.0, 30.0, 90.0, -100.0]  # every hinge moves
AS_TWIN = EmulatorOptions(plant=IDEAL, faults=FaultOptions(latency_ms=0.0))  # the twin's plant, no latency


def emulated_counts(spec, targets, ticks: int) -> np.ndarray:
    """Encoder counts the emulated device reads each tick, commanded in process (no pty, no pacing)."""
    emu = Emulator(spec, AS_TWIN)
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
