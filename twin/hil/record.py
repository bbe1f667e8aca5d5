"""Recording a HIL run: one scenario on the device and on the twin, traces side by side.

`run_hil` moves the device to the scenario's start (gated, through twin.hil.mirror), then plays
the targets on the device over the link while a twin with the device's gains, started at the
device's measured start angles with the device's recent history (twin.sim.replay.twin_at_start:
so its firmware's integral matches), follows in device time: each target takes effect in the twin
at the device time the device's ACK reports. Both traces are written as they come (trace CSV,
one line per row), so an interrupted run keeps both up to that moment. The run folder's format:
twin.formats.run.

Through the whole run, as `mirror` does for one move, each telemetry frame is compared with the twin's
encoder angles within TIME_SLACK of its time, once the twin has played that far: when a hinge parts by
more than the tolerance the device is e-stopped, the hinge and the time named, and the run kept on
disk as far as it went, its status "stopped: <why>" (`Diverged`).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import time
from pathlib import Path

import numpy as np

from controllers.encoder import target_counts
from twin.device.mount import DEFAULT_MOUNT
from twin.device.spec import DeviceSpec
from twin.formats.gains import write_gains
from twin.formats.run import run_start, write_run_meta
from twin.formats.scenario import Scenario
from twin.formats.trace import TraceWriter
from twin.hil.device_gains import device_gains, push_gains, restore_gains
from twin.hil.mirror import (HOST_SLACK_S, TIME_SLACK, FrameTimes, deviation, faults_text, mirror, parted_text,
                             start_meta, telemetry_trace, wait_for_rest)
from twin.link import protocol as P
from twin.records.gains import Gains
from twin.records.profile import NO_PROFILE
from twin.sim.gate import GateRefused, check_scenario, enforce
from twin.sim.replay import replay_targets, twin_at_start


class Diverged(RuntimeError):
    """The device parted from the twin by more than the tolerance during the run: e-stopped, the run kept up to
    there (its status "stopped: ..."). hinge, t_s: which and when (s from the first target)."""

    def __init__(self, message: str, hinge: int, t_s: float):
        super().__init__(message)
        self.hinge, self.t_s = hinge, t_s


class GainsRestored(GateRefused):
    """The gate refused the scenario, or the move to its start, after the run's gains were sent: the
    device's previous gains were sent back, and no target was sent."""


def run_hil(link, spec: DeviceSpec, scenario: Scenario, out_dir, telemetry_hz: int = 500,
            scenario_path=None, on_progress=None, settle_limit: float = 2.0, gains=None,
            tolerance_deg: float = 5.0, profile: str = NO_PROFILE, hinges=None, mount: str = DEFAULT_MOUNT) -> dict:
    """Play a scenario on the device and the twin; write out_dir/{device,twin}.csv, gains.json, run.json.

    gains: optional per-hinge PidGains pushed to the device first (every hinge's checked before any
    is sent); if the gate then refuses the scenario or the move to its start, the device's previous
    gains are restored and GainsRestored is raised. tolerance_deg: the device is e-stopped if it parts from the twin by
    more, on its way to the scenario's start (twin.hil.mirror) and through the scenario (then Diverged is
    raised, the run kept and marked stopped). profile: the device profile's name, recorded in run.json; hinges:
    each hinge's own plant for the twin (a per-hinge calibration's, Twin's); mount: how the device is held (the
    twin, the gate and run.json say so too). Returns run.json's content. On KeyboardInterrupt the device is
    e-stopped and both traces stay readable up to that moment.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n, dt = spec.n_hinges, spec.firmware_dt
    previous = push_gains(link, gains, n) if gains is not None else None
    try:
        gains = device_gains(link, n)
        enforce(check_scenario(spec, scenario, gains, settle_limit=settle_limit, mount=mount))  # the whole run, as played
        # the same start on both sides: move the device there (gated), then start the twin where the device
        # is, with the device's history (twin_at_start)
        prior = wait_for_rest(link, spec)
        res = mirror(link, spec, scenario.start, settle_limit=settle_limit, tolerance_deg=tolerance_deg,
                     hinges=hinges, mount=mount)
    except GateRefused as exc:
        if previous is None:
            raise
        restore_gains(link, previous)
        raise GainsRestored(exc.report) from None
    if not res.ok:
        raise RuntimeError(f"could not bring the device to the scenario's start: {res.message}")
    if scenario_path:
        shutil.copy(scenario_path, out / ("scenario" + Path(scenario_path).suffix))
    write_gains(out / "gains.json", Gains(gains, {"source": f"read from the device at {link.url}"}))
    state = wait_for_rest(link, spec)
    meta = {"scenario": scenario.name, **start_meta(prior, state), "telemetry_hz": telemetry_hz,
            "firmware_dt_s": dt, "changes": [], "status": "running", "port": link.url,
            "device_profile": profile, "mount": mount, "tolerance_deg": tolerance_deg}
    twin = twin_at_start(spec, gains, run_start(meta), hinges=hinges, mount=mount)

    dev_w = TraceWriter(out / "device.csv", n)
    twin_w = TraceWriter(out / "twin.csv", n, extra=("true_angle_deg",))
    stride = max(1, int(round(spec.loop_rate / telemetry_hz)))
    changes: list[tuple[float, np.ndarray]] = []
    twin_ticks = 0
    end_tick = int(math.floor(scenario.duration / dt + 1e-9))
    predicted = np.zeros((end_tick + 1, n))  # the twin's encoder angles per tick, rad, as far as it has played
    slack = int(round(TIME_SLACK / dt))
    pending: list[tuple[float, np.ndarray]] = []  # device frames (t s, encoder angles rad) not yet compared

    def advance(to_time: float):
        """Play the twin up to device time to_time (s), writing every stride-th tick."""
        nonlocal twin_ticks
        for first, tr in replay_targets(twin, changes, twin_ticks, int(math.floor(to_time / dt + 1e-9))):
            predicted[first:first + len(tr.angle)] = tr.angle
            ticks = first + np.arange(len(tr.time))
            twin_w.write_rows(dataclasses.replace(tr, time=ticks * dt), ticks % stride == 0)
            twin_ticks = first + len(tr.time)

    def compare_frames(final: bool):
        """E-stop (Diverged) where a device frame parts from the twin by more than tolerance_deg: each pending
        frame once the twin has played TIME_SLACK past it (every one left when final)."""
        while pending and twin_ticks and (final or int(round(pending[0][0] / dt)) + slack < twin_ticks):
            since, device = pending.pop(0)
            _, dev = deviation(device, predicted[:twin_ticks], int(round(since / dt)), slack)
            parted = parted_text(dev, tolerance_deg, since)
            if parted:
                link.estop()
                raise Diverged(parted, int(np.argmax(dev)), since)

    try:
        link.set_telemetry_rate(telemetry_hz)
        link.drain_telemetry()
        ack = link.set_targets(target_counts(spec, scenario.targets[0]))
        t0 = ack.time_us
        times = FrameTimes(link, t0)  # frames before t0 skipped, but not for long
        host0 = time.monotonic()
        changes.append((0.0, scenario.targets[0]))
        meta["changes"].append({"t_s": 0.0, "angles_deg": np.degrees(scenario.targets[0]).round(4).tolist()})
        meta["device_t0_us"] = t0
        write_run_meta(out, meta)
        nxt = 1
        latest = 0.0
        while latest < scenario.duration:
            if nxt < len(scenario.times) and time.monotonic() - host0 >= scenario.times[nxt]:
                ack = link.set_targets(target_counts(spec, scenario.targets[nxt]))
                tc = P.elapsed_s(t0, ack.time_us)
                changes.append((tc, scenario.targets[nxt]))
                meta["changes"].append({"t_s": round(tc, 6),
                                        "angles_deg": np.degrees(scenario.targets[nxt]).round(4).tolist()})
                write_run_meta(out, meta)
                nxt += 1
            item = link.telemetry(timeout=0.5)
            if item is None:
                link.estop()
                raise RuntimeError("no telemetry from the device for 0.5 s; e-stopped")
            if time.monotonic() - host0 > scenario.duration + HOST_SLACK_S:  # the device's clock ran slow
                link.estop()
                raise RuntimeError(f"the device's clock says {latest:.2f} s of the run's {scenario.duration:.2f} s "
                                   f"have passed, the host's {time.monotonic() - host0:.2f} s; e-stopped")
            for _, fr in [item] + link.drain_telemetry():
                since = times.since(fr)
                if since is None:
                    continue  # from before the first target took effect
                if fr.state in (P.State.FAULT, P.State.ESTOP):
                    hinge = "" if fr.fault_hinge == 0xFF else f" on hinge {fr.fault_hinge}"
                    raise RuntimeError(f"device stopped itself at t={since:.3f} s: {faults_text(fr.faults)}{hinge}"
                                       " (vrscroll view RUN shows the run up to there)")
                row = telemetry_trace(spec, [(since, fr)])
                dev_w.write_rows(row)
                if since <= scenario.duration:
                    pending.append((since, row.angle[0]))
                latest = max(latest, since)
            advance(min(latest, scenario.duration))
            compare_frames(final=False)
            if on_progress:
                on_progress(latest)
        compare_frames(final=True)
        meta["status"] = "complete"
    except KeyboardInterrupt:  # the link e-stops the device as the interrupt leaves its session
        meta["status"] = "interrupted"
        raise
    except Diverged as exc:
        meta["status"] = f"stopped: {exc}"
        raise
    except Exception as exc:
        meta["status"] = f"failed: {exc}"
        raise
    finally:
        dev_w.close()
        twin_w.close()
        meta["device_rows"], meta["twin_rows"] = dev_w.rows, twin_w.rows
        write_run_meta(out, meta)
    return meta
