"""Mirror a target onto the device: read its state, gate the move on the twin, send it,
and compare the device with the twin's prediction as it moves.

Time base: the device's ACK of SET_TARGETS carries the device time (us) at which
the targets took effect; telemetry frame times are taken relative to it, so
device and prediction share t = 0. Both are compared in encoder counts turned
into angles (what the device can report). When a hinge parts from the prediction
by more than `tolerance_deg`, the host sends ESTOP and names the hinge. A hinge's
deviation is its distance from the range the prediction spans within TIME_SLACK
of the frame's time: a device a few milliseconds ahead of or behind the twin in a
fast move (the link's latency, the telemetry period) is not parting from it; a
hinge that jams or runs away is, whatever the shift.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from controllers.encoder import angle_from_counts, target_counts
from twin.device.mount import DEFAULT_MOUNT
from twin.device.spec import DeviceSpec
from twin.formats.run import run_start
from twin.records.trace import Trace, joined
from twin.hil.device_gains import device_gains
from twin.hil.rest import REST_COUNTS, REST_TIME, motion
from twin.link import protocol as P
from twin.link.serial_link import Link
from twin.sim.gate import GateRefused, GateReport, check_move, enforce
from twin.sim.settle import SettleTracker
from twin.sim.twin import Twin


class DeviceNotReady(RuntimeError):
    """The device is in ESTOP or FAULT; clear it first."""


@dataclasses.dataclass
class MirrorResult:
    report: GateReport
    outcome: str  # "settled", "diverged" (host e-stopped), "device_fault", "timeout"
    hinge: int | None  # the hinge that diverged or faulted
    max_deviation_deg: np.ndarray  # per hinge, over the run: distance from the prediction within TIME_SLACK
    elapsed: float  # s of device time watched
    settle_time: float  # s, the device's settle time (twin.sim.response.settle_time); NaN unless settled
    twin_settle_time: float  # s, the twin's for the same move (NaN: not simulated or not settled)
    frames: int
    final_deg: np.ndarray  # device hinge angles at the end, deg
    message: str
    telemetry: Trace | None = None  # the device's frames, time s from the moment the targets took effect

    @property
    def ok(self) -> bool:
        return self.outcome == "settled"


def faults_text(faults: int) -> str:
    """The fault bits by name ("none"); bits this host does not know (a newer device's) in hex."""
    names = [f.name for f in P.Fault if f and faults & f]
    unknown = faults & ~sum(f for f in P.Fault)
    return "|".join(names + ([f"0x{unknown:X}"] if unknown else [])) or "none"


TIME_SLACK = 0.02  # s the device may lead or lag the prediction before a difference counts as a deviation
STALE_FRAMES_S = 0.5  # s of host time a run goes on skipping frames stamped before its t = 0
HOST_SLACK_S = 2.0  # s of host time a move is watched beyond its deadline in device time (a backlog of frames)


class FrameTimes:
    """Telemetry frame times (s) since t = 0, the device time (us) the targets took effect (the ACK's).

    A frame stamped before t = 0 was queued before the ACK and is skipped, but only for STALE_FRAMES_S of host
    time: a device whose frames stay stamped before it (a clock glitch, a restart) is one the host cannot watch,
    and DeviceUntrusted is raised (the device e-stopped, its watchdog no longer fed) instead of skipping every
    frame, the FAULT frames and the settle deadline with them, while heartbeats keep the device driving."""

    def __init__(self, link: Link, t0_us: int):
        self.link, self.t0 = link, t0_us
        self.last_use = time.monotonic()

    def since(self, fr: P.Telemetry) -> float | None:
        """s from t = 0 to the frame; None for a frame from before it."""
        since = P.elapsed_s(self.t0, fr.time_us)
        now = time.monotonic()
        if since <= 3600:  # after t = 0 (a frame before it wraps to ~71 min)
            self.last_use = now
            return since
        if now - self.last_use > STALE_FRAMES_S:
            raise self.link.distrust(f"its telemetry has been stamped before the targets took effect ({self.t0} us) "
                                     f"for {now - self.last_use:.2f} s (the last at {fr.time_us} us)")
        return None


def wait_for_rest(link: Link, spec: DeviceSpec, timeout: float = 3.0) -> P.StateMsg:
    """The device's state once it is at rest (twin.hil.rest) over REST_TIME s or more; DeviceNotReady after
    `timeout` s."""
    state = link.get_state()
    deadline = time.monotonic() + timeout
    while True:  # judged at least once, whatever the timeout
        time.sleep(REST_TIME)
        now = link.get_state()
        moved = motion(state, now)
        if moved.at_rest:
            return now
        if time.monotonic() >= deadline:
            raise DeviceNotReady(f"the device is still moving after {timeout:.0f} s ({moved.text(spec)}); "
                                 "nothing was sent")
        state = now


def start_meta(prior: P.StateMsg, state: P.StateMsg) -> dict:
    """run.json's entries for where the device is at a run's start (state: its counts, targets and PID
    integral) and was just before it (prior); twin.formats.run.run_start reads them."""
    return {"start_counts": list(state.counts), "start_target_counts": list(state.targets),
            "start_integral_duty": [round(x, 6) for x in state.integral_duty],
            "before": {"state": P.enum_name(P.State, prior.state), "counts": list(prior.counts),
                       "target_counts": list(prior.targets)}}


def mirror(link: Link, spec: DeviceSpec, targets, tolerance_deg: float = 5.0, settle_limit: float = 2.0,
           override: bool = False, telemetry_hz: int = 500, on_frame=None, hinges=None,
           mount: str = DEFAULT_MOUNT) -> MirrorResult:
    """Gate, send and watch one move (targets in rad). GateRefused if the twin finds it unsafe.

    on_frame(elapsed_s, device_deg, predicted_deg) is called for every telemetry frame. hinges: each hinge's
    own plant for the twin (a per-hinge calibration's, Twin's); mount: how the device is held (the twin is
    held so: twin.device.mount).
    """
    targets = np.asarray(targets, float)
    state = link.get_state()
    if state.state == P.State.FAULT and state.faults == P.Fault.WATCHDOG:
        # the previous session ended and the watchdog stopped the motors, as it should: not a fault of the device
        link.log("clear_watchdog", reason="previous session's watchdog stop")
        link.clear_fault()
        state = link.get_state()
    if state.state in (P.State.ESTOP, P.State.FAULT):
        raise DeviceNotReady(f"device is in {P.enum_name(P.State, state.state)} (faults: {faults_text(state.faults)}); "
                             "clear it first (vrscroll status --clear-fault)")
    gains = device_gains(link, spec.n_hinges)
    twin = Twin(spec, gains, hinges=hinges, mount=mount)  # before the wait: a process's first takes 1.3-1.7 s
    state = wait_for_rest(link, spec)
    for _ in range(3):  # gate from the present state; again from the new one if the device left the start simulated
        start = angle_from_counts(spec, state.counts)
        report = check_move(spec, start, targets, gains, settle_limit=settle_limit, twin=twin,
                            integral=state.integral_duty)
        link.log("gate", **report.to_dict())
        now = link.get_state()
        moved = motion(state, now)
        if moved.kept_start(spec):
            break
        state = now
    else:
        raise DeviceNotReady(f"the device kept moving while the twin simulated the move ({moved.text(spec)}; at rest "
                             f"is at most {REST_COUNTS} counts per {REST_TIME} s and a drift within the settle band, "
                             f"{spec.settle_band} counts); nothing was sent")
    try:
        enforce(report, override)
    except GateRefused:
        link.log("gate_refused", reason=report.refusal())
        raise
    if report.overridden:
        link.log("gate_override", reason=report.refusal())

    trace = report.prediction  # None only when an override sent a target the twin could not simulate
    predicted = None if trace is None else trace.angle  # the encoder's angle, as the device reads it
    dt = spec.firmware_dt
    link.set_telemetry_rate(telemetry_hz)
    link.drain_telemetry()
    ack = link.set_targets(target_counts(spec, targets))
    times = FrameTimes(link, ack.time_us)
    watch_until = time.monotonic() + settle_limit + 1.0 + HOST_SLACK_S  # the host's own deadline
    tgt = target_counts(spec, targets)
    max_dev = np.zeros(spec.n_hinges)
    settle = SettleTracker(tgt, spec.settle_band, spec.settle_hold, 1.0 / telemetry_hz)
    slack = int(round(TIME_SLACK / dt))
    frames = 0
    elapsed = 0.0
    device = start
    deadline = settle_limit + 1.0

    twin_settle = report.settle_time

    rows = []  # each frame as a one-row Trace (telemetry_trace)

    def result(outcome, hinge, message, settled=math.nan):
        r = MirrorResult(report, outcome, hinge, np.degrees(max_dev), elapsed, settled, twin_settle, frames,
                         np.degrees(device), message, joined(rows) if rows else None)
        link.log("mirror_result", outcome=outcome, hinge=hinge, message=message, elapsed_s=elapsed,
                 settle_time_s=settled, twin_settle_time_s=twin_settle,
                 max_deviation_deg=np.degrees(max_dev).round(3).tolist(), frames=frames)
        return r

    while elapsed < deadline:
        item = link.telemetry(timeout=0.5)
        if item is None:
            _estop(link)
            return result("timeout", None, "no telemetry from the device for 0.5 s; e-stopped")
        if time.monotonic() > watch_until:  # the device's clock ran slow: the host's deadline holds
            _estop(link)
            return result("timeout", None, f"not settled {settle_limit + 1.0 + HOST_SLACK_S:.1f} s after the "
                          "move on the host's clock (the device's clock says less); e-stopped")
        _, fr = item
        since = times.since(fr)
        if since is None:  # a frame from before the targets took effect
            continue
        elapsed = since
        frames += 1
        rows.append(telemetry_trace(spec, [(since, fr)]))
        device = rows[-1].angle[0]
        expected, dev = deviation(device, predicted, int(round(elapsed / dt)), slack)
        max_dev = np.maximum(max_dev, dev)
        if on_frame:
            on_frame(elapsed, np.degrees(device), np.degrees(expected))
        if fr.state in (P.State.FAULT, P.State.ESTOP):
            hinge = None if fr.fault_hinge == 0xFF else fr.fault_hinge
            return result("device_fault", hinge, f"device stopped itself: {faults_text(fr.faults)}"
                          + (f" on hinge {hinge}" if hinge is not None else "") + f" at t={elapsed:.3f} s")
        parted = parted_text(dev, tolerance_deg, elapsed)
        if parted:
            _estop(link)
            return result("diverged", int(np.argmax(dev)), parted)
        settled = settle.feed(elapsed, fr.counts)  # the settle rule (twin.sim.settle), as the frames come
        if settled is not None:
            return result("settled", None, f"settled: settle time {settled:.3f} s (twin: {twin_settle:.3f} s), "
                          f"largest deviation {np.degrees(max_dev).max():.2f} deg", settled=settled)
    worst = int(np.argmax(np.abs(np.asarray(device) - targets)))
    return result("timeout", worst, f"not settled after {deadline:.1f} s (hinge {worst} at "
                  f"{math.degrees(device[worst]):.1f} deg, target {math.degrees(targets[worst]):.1f} deg)")


def parted_text(dev, tolerance_deg: float, t: float) -> str:
    """Why the device is e-stopped, naming the hinge and the time (t s), where a hinge's deviation (rad, from
    `deviation`) is more than tolerance_deg; "" where none is."""
    worst = int(np.argmax(dev))
    if math.degrees(dev[worst]) <= tolerance_deg:
        return ""
    return (f"hinge {worst} parted from the twin by {math.degrees(dev[worst]):.1f} deg (tolerance "
            f"{tolerance_deg:.1f} deg) at t={t:.3f} s: device e-stopped")


def _estop(link: Link) -> None:
    """ESTOP; then DeviceUntrusted if its answer showed the device cannot be trusted (a restart: the ACK's
    clock went back), so that the run's outcome says so rather than "timeout"."""
    link.estop()
    if link.untrusted is not None:
        raise link.untrusted


def deviation(device, predicted, row: int, slack: int):
    """(the prediction at `row`, each hinge's distance (rad) from the range the prediction spans within
    `slack` rows of it); no prediction: the device itself, and no deviation."""
    if predicted is None:
        return device, np.zeros_like(device)
    last = len(predicted) - 1
    window = predicted[min(max(row - slack, 0), last): min(row + slack, last) + 1]
    dev = np.maximum(0.0, np.maximum(window.min(axis=0) - device, device - window.max(axis=0)))
    return predicted[min(row, last)], dev


def telemetry_trace(spec: DeviceSpec, frames) -> Trace:
    """Telemetry frames, [(s since t = 0 (FrameTimes.since), P.Telemetry)], as a Trace in SI: the encoder's
    angle and the target from their counts (x rad per count), the duty from the wire's scale, the current from
    mA. The one conversion of a device's frames (mirror's watch and recording, run_hil's device.csv)."""
    n = spec.n_hinges
    column = (lambda field, dtype: np.array([getattr(fr, field) for _, fr in frames], dtype).reshape(-1, n))
    counts = column("counts", np.int64)
    return Trace(time=np.array([t for t, _ in frames], float), target=column("targets", np.int64) * spec.rad_per_count,
                 angle=counts * spec.rad_per_count, counts=counts, duty=column("duty", float) / P.DUTY_SCALE,
                 current=column("current_ma", float) / 1000.0)


def device_step(link: Link, spec: DeviceSpec, targets, settle_limit: float = 2.0, mount: str = DEFAULT_MOUNT,
                hinges=None, at_flat=None):
    """Bring the device to flat, call at_flat() once it rests there (e.g. push the gains the step is for, so the
    move to flat is made with the gains the device held), then step to targets (rad), both moves gated through
    `mirror` (mount, hinges: the twin's, as mirror's).

    Returns (t s, angle deg (frames, n), where the step started (twin.formats.run.RunStart: for
    twin.sim.replay.twin_at_start), the step's MirrorResult): the device's encoder angles from the moment
    the step took effect until it settled (or mirror gave up).
    """
    n = spec.n_hinges
    prior = wait_for_rest(link, spec)
    res = mirror(link, spec, np.zeros(n), settle_limit=settle_limit, mount=mount, hinges=hinges)
    if not res.ok:
        raise RuntimeError(f"device did not reach flat: {res.message}")
    if at_flat is not None:
        at_flat()
    start = run_start(start_meta(prior, wait_for_rest(link, spec)))
    ts, ys = [], []
    res = mirror(link, spec, targets, settle_limit=settle_limit, tolerance_deg=30.0, mount=mount, hinges=hinges,
                 on_frame=lambda t, dev, pred: (ts.append(t), ys.append(np.array(dev))))
    return np.array(ts), np.array(ys).reshape(-1, n), start, res
