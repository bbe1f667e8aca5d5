"""What a lock does to the hardware: gate the move on the twin, then morph the device (or the twin alone).

Both morphers run in a thread (they block) and report through `emit(event)`, called from
that thread with the control channel's event dicts (docs/live.md): "gate" (the gate's
report), "progress" (hinge angles as the device reports them, or as the twin predicts
them, at PROGRESS_HZ), and return a MorphOutcome that the service turns into "done",
"refused" or "stopped".

- `DeviceMorpher`: over the serial link, `twin.hil.mirror.mirror` (state, device gains,
  the gate's `check_move` from the device's present angles, send, watch, e-stop on
  divergence). The gate's report is the one mirror writes to the session log.
- `TwinMorpher`: no device: the gate simulates the move on the twin, and its predicted
  trace is played out in real time as the progress.

A client that leaves mid-morph does not stop it: the move was gated whole, so it is
finished and held (docs/live.md says why).
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time

import numpy as np

from controllers.encoder import angle_from_counts
from twin.device.mount import DEFAULT_MOUNT
from twin.device.spec import DeviceSpec
from twin.hil.device_gains import device_spec
from twin.hil.mirror import DeviceNotReady, faults_text, mirror
from twin.link import protocol as P
from twin.link.serial_link import Link, LinkError
from twin.live.messages import PROGRESS_HZ
from twin.sim.gate import GateRefused, check_move
from twin.sim.twin import Twin

SETTLE_LIMIT = 2.0  # s a morph may take (the gate's settle check and mirror's watch)


@dataclasses.dataclass
class MorphOutcome:
    status: str  # "done", "refused" (nothing moved) or "stopped" (the device stopped mid-way)
    final: np.ndarray | None  # rad, the hinge angles where the device ended (None when refused)
    message: str
    settle_time: float = math.nan  # s, the morph's settle time (twin.sim.response.settle_time); NaN: not settled


def _degrees(angles) -> list[float]:
    return [round(math.degrees(a), 3) for a in angles]


class _Throttle:
    """True at most `rate_hz` times per second of the given clock (and always for the first)."""

    def __init__(self, rate_hz: float):
        self.period, self.last = 1.0 / rate_hz, -math.inf

    def due(self, t: float) -> bool:
        if t - self.last >= self.period:
            self.last = t
            return True
        return False


class _ReportingLink(Link):
    """A Link whose session-log events also go to `listener(event, fields)`: the gate report mirror logs."""

    listener = None

    def log(self, event: str, **fields) -> None:
        super().log(event, **fields)
        listener = self.listener
        if listener is not None:
            listener(event, fields)


class DeviceMorpher:
    """The device on a serial port (or the emulator's pty); the link stays open, so the device holds.

    on_move(telemetry, prediction), where set, gets every move sent: the device's frames (a Trace) and
    the twin's predicted Trace (e.g. for a Rerun recording of the session)."""

    on_move = None

    def __init__(self, spec: DeviceSpec, port: str, log_path=None, tolerance_deg: float = 5.0, hinges=None,
                 mount: str = DEFAULT_MOUNT):
        self.spec = spec
        self.hinges = hinges  # each hinge's own plant for the gate's twin (a per-hinge calibration's)
        self.mount = mount  # how the device is held (twin.device.mount): the gate's twin is held so
        self.tolerance_deg = tolerance_deg
        self.link = _ReportingLink(port, log_path=log_path, log_telemetry=False, hinges=spec.n_hinges)
        self.name = f"device on {port}"

    def open(self) -> None:
        self.link.open()
        self.spec, notes = device_spec(self.spec, self.link.info)
        for note in notes:
            print(f"vrscroll serve: note: {note}", file=sys.stderr, flush=True)

    def morph(self, targets, emit) -> MorphOutcome:
        throttle = _Throttle(PROGRESS_HZ)

        def on_log(event, fields):
            if event == "gate":
                emit({"type": "gate", **fields})

        def on_frame(elapsed, device_deg, predicted_deg):
            if throttle.due(elapsed):
                emit({"type": "progress", "elapsed_s": round(elapsed, 4), "source": "device",
                      "angles_deg": np.round(device_deg, 3).tolist(),
                      "predicted_deg": np.round(predicted_deg, 3).tolist()})

        self.link.listener = on_log
        try:
            result = mirror(self.link, self.spec, targets, tolerance_deg=self.tolerance_deg,
                            settle_limit=SETTLE_LIMIT, on_frame=on_frame, hinges=self.hinges, mount=self.mount)
        except GateRefused as exc:
            return MorphOutcome("refused", None, str(exc))
        except DeviceNotReady as exc:
            return MorphOutcome("refused", None, str(exc))
        except LinkError as exc:
            return MorphOutcome("stopped", None, f"link: {exc}")
        finally:
            self.link.listener = None
            self._quiet()
        if self.on_move is not None:
            self.on_move(result.telemetry, result.report.prediction)
        return MorphOutcome("done" if result.ok else "stopped", np.radians(result.final_deg), result.message,
                            result.settle_time)

    def _quiet(self) -> None:
        """Telemetry off between morphs: the link queues every frame until it is read, and nothing reads it then."""
        try:
            self.link.set_telemetry_rate(0)
        except LinkError:
            pass  # the link is gone; the next lock says so
        self.link.drain_telemetry()

    def status(self) -> dict:
        try:
            state = self.link.get_state()
        except LinkError as exc:
            return {"device": self.name, "device_state": "UNREACHABLE", "faults": str(exc), "angles_deg": None}
        return {"device": self.name, "device_state": P.enum_name(P.State, state.state), "faults": faults_text(state.faults),
                "angles_deg": _degrees(angle_from_counts(self.spec, state.counts))}

    def close(self) -> None:
        """The service is ending (a stop signal, an error): a device it moved is e-stopped before the port
        closes, not left holding (or still driving toward) its last targets unwatched."""
        self.link.estop_if_moved("estop_on_stop")
        self.link.close()


class TwinMorpher:
    """No device: the twin is the device; it holds the angles its last morph reached. on_move(None, trace)
    as DeviceMorpher's."""

    on_move = None

    def __init__(self, spec: DeviceSpec, gains=None, hinges=None, mount: str = DEFAULT_MOUNT):
        self.spec = spec
        self.gains = gains
        self.hinges = hinges  # each hinge's own plant (a per-hinge calibration's)
        self.mount = mount  # how the device is held (twin.device.mount)
        self.twin = None
        self.angles = np.zeros(spec.n_hinges)
        self.integral = None  # the PID integral per hinge its last morph left (duty), as a device holds it
        self.name = "twin (no device attached)"

    def open(self) -> None:
        self.twin = Twin(self.spec, self.gains, hinges=self.hinges, mount=self.mount)

    def morph(self, targets, emit) -> MorphOutcome:
        report = check_move(self.spec, self.angles, targets, self.gains, settle_limit=SETTLE_LIMIT, twin=self.twin,
                            integral=self.integral)
        emit({"type": "gate", **report.to_dict()})
        if not report.passed:
            return MorphOutcome("refused", None, report.refusal())
        trace = report.prediction
        t0 = time.monotonic()
        step = 1.0 / PROGRESS_HZ
        for k in range(int(trace.duration / step) + 1):
            time.sleep(max(0.0, t0 + k * step - time.monotonic()))
            row = min(int(round(k * step / self.spec.firmware_dt)), len(trace.time) - 1)
            angles = _degrees(trace.true_angle[row])
            emit({"type": "progress", "elapsed_s": round(k * step, 4), "source": "twin",
                  "angles_deg": angles, "predicted_deg": angles})
        self.angles = trace.true_angle[-1].copy()
        self.integral = self.twin.pid.integral.copy()
        if self.on_move is not None:
            self.on_move(None, trace)
        return MorphOutcome("done", self.angles.copy(), f"the twin's settle time {report.settle_time:.3f} s",
                            report.settle_time)

    def status(self) -> dict:
        return {"device": self.name, "device_state": "TWIN", "faults": "none", "angles_deg": _degrees(self.angles)}

    def close(self) -> None:
        self.twin = None
