"""The stage clock of the live service's paths (twin/live/stages.py), on real time."""

import time

import pytest

from twin.live.stages import PEN_STAGES, StageTimes, percentiles_ms


def _sample(pauses) -> list[float]:
    stamps = [time.perf_counter()]
    for pause in pauses:
        time.sleep(pause)
        stamps.append(time.perf_counter())
    return stamps


def test_stages_split_a_sample_and_add_up_to_its_total():
    times = StageTimes(PEN_STAGES, window=1)
    times.record(_sample((0.002, 0.0, 0.004, 0.001)))
    summary = times.summary()
    assert tuple(summary) == PEN_STAGES
    # the stages tile the sample's total (3-decimal ms each); slept stages take at least their sleep
    assert sum(summary[name]["p50"] for name in PEN_STAGES[:-1]) == pytest.approx(summary["total"]["p50"], abs=0.003)
    assert summary["socket"]["p50"] >= 2.0 and summary["redirect"]["p50"] >= 4.0 and summary["send"]["p50"] >= 1.0


def test_only_the_window_is_kept():
    times = StageTimes(PEN_STAGES, window=3)
    for pause in (0.02, 0.0, 0.0, 0.0):  # the slow first sample leaves the window
        times.record(_sample((pause, 0.0, 0.0, 0.0)))
    assert len(times.total()) == 3 and times.summary()["socket"]["p99"] < 20.0
    assert percentiles_ms([]) is None
