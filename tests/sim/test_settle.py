"""The settle rule has one home (twin.sim.settle): the twin's stop (the compiled loop, tick by tick), a tracker fed
samples as they come (the device's watch) and the settle time read back from a whole recording
(twin.sim.response) agree on a real twin move (MuJoCo, the C firmware) to targets nobody tuned for."""

import numpy as np
import pytest

from twin.sim.response import move_settle_time
from twin.sim.settle import SettleTracker, hold_samples
from twin.sim.twin import Twin


@pytest.mark.parametrize("seed", [3, 17])
def test_the_twins_stop_a_tracker_and_the_recordings_settle_time_agree(spec, seed):
    targets = np.radians(np.random.default_rng(seed).uniform(-40, 40, spec.n_hinges))
    whole = Twin(spec).move_to(targets, max_time=1.0, stop_when_settled=False)
    looked_back = move_settle_time(spec, whole.time, whole.counts, whole.target_counts)
    assert np.isfinite(looked_back)
    tracker = SettleTracker(whole.target_counts[0], spec.settle_band, spec.settle_hold, spec.firmware_dt)
    fed = next(s for t, c in zip(whole.time, whole.counts) if (s := tracker.feed(t, c)) is not None)
    assert fed == pytest.approx(whole.time[0] + looked_back, abs=1e-12)
    stopped = Twin(spec).move_to(targets, max_time=1.0, stop_when_settled=True)  # the compiled loop's own stop
    assert np.array_equal(stopped.counts, whole.counts[:len(stopped.time)])
    assert stopped.time[-1] == pytest.approx(fed + spec.settle_hold - spec.firmware_dt, abs=1e-9)


@pytest.mark.parametrize("period", [0.001, 0.002, 0.003, 0.0111])
def test_the_compiled_loops_hold_count_is_the_trackers_hold(spec, period):
    """The twin's stop counts ticks in the band (hold_samples); a tracker fed samples at that period, every one
    in the band after some outside it, settles on the same sample: the hold as a count is the tracker's rule,
    for periods the hold is and is not a whole multiple of."""
    need = hold_samples(spec.settle_hold, period)
    target = np.zeros(spec.n_hinges, np.int64)
    tracker = SettleTracker(target, spec.settle_band, spec.settle_hold, period)
    outside = np.full(spec.n_hinges, spec.settle_band + 1)
    times = np.arange(3 + 2 * need) * period
    fed = [tracker.feed(t, outside if k < 3 else target) for k, t in enumerate(times)]
    first = next(k for k, s in enumerate(fed) if s is not None)
    assert first - 3 + 1 == need and fed[first] == pytest.approx(times[3], abs=1e-12)
