"""Replay of timed hinge targets on the twin: a recorded run's targets, each taking effect at the
device time the device acknowledged it, played at the firmware rate.

`twin_at_start` gives a twin in the state the device was in when the run began; `replay_targets`
plays the targets on it. `vrscroll hil` plays them as the device's telemetry comes in (a stretch
at a time). Calibration plays a whole recorded run at once on many candidate plants (`replay_batch`: the
batch twin, on MuJoCo's thread pool, the same to the count as the single twin). Both start as
`put_at_start` says and play the same stretches (`stretches`).
"""

from __future__ import annotations

import numpy as np

from controllers.encoder import angle_from_counts
from twin.device.mount import DEFAULT_MOUNT
from twin.device.spec import DeviceSpec
from twin.formats.run import RunStart
from twin.sim.batch import TwinBatch
from twin.sim.twin import Twin

REST = 1.0  # s the twin spends on each leg of the device's history before a run


def put_at_start(reset, play, integral, start: RunStart, spec: DeviceSpec) -> None:
    """Put a twin (or a batch of them) in the state the device was in when the run began, with its history.

    The device's PID integral carries the flaps' weight, and where in its friction band it sits
    depends on how the hinge came to rest (a twin started with an empty integral sags, then
    overshoots the first step). So the twin lives the run's prelude as the device did (start's
    before_*): resting at the device's pose before the run (holding its targets if it was ACTIVE;
    limp and with a fresh PID, as after IDLE, if not), then brought to the start targets (REST s
    each); finally its hinges are put exactly where the device's encoders say (mid-count: the
    encoder floors), its firmware state kept. Where the device reported its PID integral (start.integral,
    from STATE since protocol 3), the twin is put there with it instead. reset(angles rad, integral duty),
    play(targets rad, seconds) and integral() are the twin's (Twin's or TwinBatch's); spec: the device's
    encoder.
    """
    def put(counts):
        return np.clip(angle_from_counts(spec, np.asarray(counts) + 0.5), -spec.hinge_limit, spec.hinge_limit)

    if start.integral is not None:  # the device said what its PID holds: no history to guess it from
        reset(put(start.counts), start.integral)
        return
    reset(put(start.before_counts), None)
    if start.before_state == "ACTIVE":
        play(angle_from_counts(spec, start.before_target_counts), REST)
    play(angle_from_counts(spec, start.target_counts), REST)
    reset(put(start.counts), integral())


def twin_at_start(plant: DeviceSpec, gains, start: RunStart, spec: DeviceSpec | None = None,
                  hinges: list[DeviceSpec] | None = None, mount: str = DEFAULT_MOUNT) -> Twin:
    """A twin at the device's start with the device's recent history, so its firmware state matches
    (`put_at_start`). plant: the physics (hinges: each hinge's own, where they differ); spec: the device's
    encoder (default: the plant's); mount: how the device is held (twin.device.mount)."""
    twin = Twin(plant, gains, hinges=hinges, mount=mount)
    put_at_start(twin.reset, lambda targets, s: twin.move_to(targets, max_time=s, stop_when_settled=False),
                 lambda: twin.pid.integral.copy(), start, spec or plant)
    return twin


def stretches(changes, dt: float, start_tick: int, stop_tick: int) -> list:
    """Ticks [start_tick, stop_tick) of timed targets as stretches of one target: [(first tick, ticks,
    targets rad)]. changes: [(t s, targets rad)], the first at t = 0; the target of tick i is that of the last
    change at or before tick i (each change's time rounded to the nearest tick of dt s)."""
    switch = [int(round(t / dt)) for t, _ in changes]
    out = []
    tick = start_tick
    while tick < stop_tick:
        j = max(i for i, s in enumerate(switch) if s <= tick)
        end = min([stop_tick] + [s for s in switch[j + 1:] if s > tick])
        out.append((tick, end - tick, changes[j][1]))
        tick = end
    return out


def replay_batch(plants: list[DeviceSpec], gains, start: RunStart, changes, stop_tick: int, spec: DeviceSpec,
                 hinges: list | None = None, nthread: int = 0,
                 mount: str = DEFAULT_MOUNT) -> tuple[np.ndarray, np.ndarray]:
    """Firmware ticks [0, stop_tick) of timed targets (as `stretches`) played from the device's start
    (`put_at_start`) on one twin per plant, in lockstep on the batch twin: (counts, duty), each (ticks,
    len(plants), n_hinges). gains: the device's (one PidGains or one per hinge); hinges: per plant, each
    hinge's own specs or None; spec: the device (its encoder and firmware); nthread: MuJoCo's threads
    (0: every core); mount: how the device was held (twin.device.mount)."""
    batch = TwinBatch(len(plants), spec, [gains] * len(plants), specs=plants, nthread=nthread, hinges=hinges,
                      mount=mount)
    put_at_start(batch.reset, batch.run, lambda: batch.integral, start, spec)
    out = [batch.run(targets, ticks * spec.firmware_dt) for _, ticks, targets in
           stretches(changes, spec.firmware_dt, 0, stop_tick)]
    return np.concatenate([o["counts"] for o in out]), np.concatenate([o["duty"] for o in out])


def replay_targets(twin: Twin, changes, start_tick: int, stop_tick: int) -> list:
    """Play firmware ticks [start_tick, stop_tick) of timed targets (as `stretches`) on the twin;
    [(first tick, Trace)]. The twin must have played ticks 0 .. start_tick - 1 already (or be at the start,
    for start_tick 0)."""
    return [(tick, twin.move_to(targets, max_time=ticks * twin.spec.firmware_dt, stop_when_settled=False))
            for tick, ticks, targets in stretches(changes, twin.spec.firmware_dt, start_tick, stop_tick)]
