"""Replay of timed hinge targets on the twin: a recorded run's targets, each taking effect at the
device time the device acknowledged it, played at the firmware rate.

`twin_at_start` gives a twin in the state the device was in when the run began; `replay_targets`
plays the targets on it. `vrscroll hil` plays them as the device's telemetry comes in (a stretch
at a time), calibration plays a whole recorded run at once: both through `replay_targets`.
"""

from __future__ import annotations

import numpy as np

from controllers.encoder import angle_from_counts
from twin.device.spec import DeviceSpec
from twin.formats.run import RunStart
from twin.sim.twin import Twin

REST = 1.0  # s the twin spends on each leg of the device's history before a run


def twin_at_start(plant: DeviceSpec, gains, start: RunStart, spec: DeviceSpec | None = None,
                  hinges: list[DeviceSpec] | None = None) -> Twin:
    """A twin at the device's start with the device's recent history, so its firmware state matches.

    start: where the device was (twin.formats.run.RunStart), with its state just before.
    The device's PID integral carries the flaps' weight, and where in its friction band it sits
    depends on how the hinge came to rest (a twin started with an empty integral sags, then
    overshoots the first step). So the twin lives the run's prelude as the device did (start's
    before_*): resting at the device's pose before the run (holding its targets if it was ACTIVE;
    limp and with a fresh PID, as after IDLE, if not), then brought to the start targets (REST s
    each); finally its hinges are put exactly where the device's encoders say (mid-count: the
    encoder floors), its firmware state kept. Where the device reported its PID integral (start.integral,
    from STATE since protocol 3), the twin is put there with it instead. plant: the physics (hinges: each
    hinge's own, where they differ); spec: the device's encoder (default: the plant's).
    """
    spec = spec or plant
    twin = Twin(plant, gains, hinges=hinges)

    def put(counts):
        return np.clip(angle_from_counts(spec, np.asarray(counts) + 0.5), -spec.hinge_limit, spec.hinge_limit)

    if start.integral is not None:  # the device said what its PID holds: no history to guess it from
        twin.reset(put(start.counts), start.integral)
        return twin
    twin.reset(put(start.before_counts))
    if start.before_state == "ACTIVE":
        twin.move_to(angle_from_counts(spec, start.before_target_counts), max_time=REST, stop_when_settled=False)
    twin.move_to(angle_from_counts(spec, start.target_counts), max_time=REST, stop_when_settled=False)
    integral = twin.pid.integral.copy()
    twin.reset(put(start.counts))
    twin.pid.integral[:] = integral
    return twin


def replay_targets(twin: Twin, changes, start_tick: int, stop_tick: int) -> list:
    """Play firmware ticks [start_tick, stop_tick) of timed targets on the twin; [(first tick, Trace)].

    changes: [(t s, targets rad)], the first at t = 0; the target of tick i is that of the last
    change at or before tick i (each change's time rounded to the nearest tick). The twin must
    have played ticks 0 .. start_tick - 1 already (or be at the start, for start_tick 0).
    """
    dt = twin.spec.firmware_dt
    switch = [int(round(t / dt)) for t, _ in changes]
    out = []
    tick = start_tick
    while tick < stop_tick:
        j = max(i for i, s in enumerate(switch) if s <= tick)
        end = min([stop_tick] + [s for s in switch[j + 1:] if s > tick])
        trace = twin.move_to(changes[j][1], max_time=(end - tick) * dt, stop_when_settled=False)
        out.append((tick, trace))
        tick += len(trace.time)
    return out
