"""An emulated VRScroll device: the firmware's logic on its own plant, with injected faults.

`Emulator` is one device, driven tick by tick: `receive(bytes)` as they arrive
from the host, `step()` once per firmware tick, `take_output()` for the bytes it
answers with. Each tick it reads the encoders, runs the firmware (watchdog, hinge
range, stall, PID), drives its plant (twin.link.plant) and streams telemetry; the
faults (twin.link.faults) act on its bytes and its plant. `twin.link.pty_device`
serves it on a pseudo-terminal in real time (`vrscroll emulate`). Every command
received is written to a JSON-lines log as it arrives.
"""

from __future__ import annotations

import dataclasses
import json
import math
import random

import numpy as np

from controllers.pid import PidGains, gains_table, pid_update
from twin.device.spec import DeviceSpec, load_spec
from twin.link import protocol as P
from twin.link.faults import FaultOptions, Faults
from twin.link.plant import Plant, PlantOptions

FIRMWARE_VERSION = (0, 1, 0)


@dataclasses.dataclass(frozen=True)
class EmulatorOptions:
    """The emulated device: its plant, its faults, its firmware's settings, the random seed."""

    plant: PlantOptions = PlantOptions()
    faults: FaultOptions = FaultOptions()
    watchdog_ms: int = 200  # host quiet this long while ACTIVE -> FAULT, motors off
    max_telemetry_hz: int = 500
    stall_duty: float = 0.5  # |duty| at or above this with no motion ...
    stall_ms: int = 300  # ... for this long -> FAULT STALL
    seed: int = 0


class Emulator:
    """The firmware, plant and injected faults of one device."""

    def __init__(self, spec: DeviceSpec | None = None, opt: EmulatorOptions | None = None,
                 log_path: str | None = None):
        self.spec = s = spec or load_spec()
        self.opt = opt or EmulatorOptions()
        self.rng = random.Random(self.opt.seed)
        self.plant = Plant(s, self.opt.plant, self.rng)
        self.faults = Faults(self.opt.faults, self.rng)
        self.n = n = s.n_hinges
        self.dt = s.firmware_dt
        self.tick = 0
        self.out = bytearray()  # bytes for the host, not yet taken
        self.log = open(log_path, "a", buffering=1) if log_path else None
        # firmware state; gains as the wire would carry them
        wire = P.Gains.from_pid(PidGains.from_spec(s))
        self.gains = [wire] * n
        self.gain_rows = gains_table(PidGains.from_spec(s), n, self.dt)
        self.limit_counts = int(math.floor(s.hinge_limit / s.rad_per_count))
        self.counts = self.plant.counts
        self.targets = self.counts.copy()
        self.prev = self.counts.copy()
        self.rate = np.zeros(n)
        self.integral = np.zeros(n)
        self.duty = np.zeros(n)
        # load the compiled PID now, not on the first tick that needs it (a stall of ~0.3 s)
        pid_update(self.targets, self.counts, self.prev.copy(), self.rate.copy(), self.integral.copy(),
                   self.gain_rows, self.dt, self.duty.copy())
        self.state = P.State.IDLE
        self.fault_flags = P.Fault.NONE
        self.fault_hinge = 0xFF
        self.last_rx_tick = 0
        self.telemetry_every = 0  # ticks; 0 = off
        self.telemetry_seq = 0
        self.telemetry_dropped = 0
        self.stall_ref = self.counts.copy()
        self.stall_since = np.zeros(n, np.int64)
        self.decoder = P.Decoder()
        p = self.plant.spec
        self._log("start", plant={k: getattr(p, k) for k in ("gear_friction", "gear_damping", "no_load_speed",
                                                             "rotor_inertia", "backlash")},
                  options=dataclasses.asdict(self.opt))

    @property
    def time(self) -> float:
        """Device time, s."""
        return self.tick * self.dt

    # ---- the device's edges -----------------------------------------------------------
    def receive(self, data: bytes) -> None:
        """Bytes from the host, arriving now."""
        self.faults.arrive(data, self.time)

    def take_output(self, max_bytes: int = 1 << 30) -> bytes:
        """Up to max_bytes of what the device has sent, oldest first."""
        out = bytes(self.out[:max_bytes])
        del self.out[:max_bytes]
        return out

    def step(self) -> None:
        """One firmware tick: commands due, encoders, safety checks, PID, the plant's physics, telemetry."""
        self._firmware_rx(self.faults.due(self.time))
        self.counts = counts = self.plant.sense()
        if self.state == P.State.ACTIVE:
            self._checks(counts)
        if self.state == P.State.ACTIVE:
            pid_update(self.targets, counts, self.prev, self.rate, self.integral, self.gain_rows, self.dt,
                       self.duty)
        else:
            self.duty[:] = 0.0
            self.prev[:] = counts
        self.plant.actuate(self.duty)
        jammed = self.faults.jam(self.plant, self.state == P.State.ACTIVE, self.time)
        if jammed is not None:
            self._log("jam", hinge=self.opt.faults.jam_hinge, angle_deg=math.degrees(jammed))
        if self.telemetry_every and self.tick % self.telemetry_every == 0:
            self._send(P.Telemetry((self.tick * 1000) & 0xFFFFFFFF, self.state, self.fault_flags, self.fault_hinge,
                                   tuple(int(c) for c in counts), tuple(int(c) for c in self.targets),
                                   tuple(int(round(x * P.DUTY_SCALE)) for x in self.duty),
                                   tuple(int(max(-32768, min(32767, round(i * 1000)))) for i in self.plant.current)),
                       self.telemetry_seq, telemetry=True)
            self.telemetry_seq = (self.telemetry_seq + 1) & 0xFFFF
        self.tick += 1

    def close(self, **stats) -> None:
        """Log the run's end (with the caller's stats) and close the log."""
        self._log("stop", ticks=self.tick, rx_bad_frames=self.decoder.bad_frames,
                  telemetry_dropped=self.telemetry_dropped, **stats)
        if self.log:
            self.log.close()
            self.log = None

    # ---- the firmware ------------------------------------------------------------------
    def _log(self, event: str, **fields) -> None:
        if self.log:
            self.log.write(json.dumps({"t": round(self.time, 6), "event": event, **fields}) + "\n")

    def _send(self, msg, seq: int, telemetry: bool = False) -> None:
        if telemetry and len(self.out) > 8192:  # the UART's buffer is full: drop, as firmware would
            self.telemetry_dropped += 1
            return
        self.out += self.faults.outgoing(P.encode(msg, seq), self.time)

    def _fault(self, flag: P.Fault, hinge: int = 0xFF) -> None:
        self.state = P.State.ESTOP if flag == P.Fault.ESTOP else P.State.FAULT
        self.fault_flags |= flag
        if self.fault_hinge == 0xFF:
            self.fault_hinge = hinge
        self.duty[:] = 0.0
        self._log("fault", fault=flag.name, hinge=None if hinge == 0xFF else hinge, state=self.state.name,
                  last_rx_t=round(self.last_rx_tick * self.dt, 6))

    def _firmware_rx(self, data: bytes) -> None:
        if not data:
            return
        bad = self.decoder.bad_frames
        for seq, msg in self.decoder.feed(data):
            self._log("rx", msg=msg.MSG.name, seq=seq, **_fields(msg))
            self._handle(seq, msg)
        if self.decoder.bad_frames != bad:
            self._log("bad_frames", count=self.decoder.bad_frames, last_error=self.decoder.last_error)

    def _handle(self, seq: int, msg) -> None:
        self.last_rx_tick = self.tick
        m = msg.MSG
        if m == P.MsgId.HEARTBEAT:
            return
        if m == P.MsgId.HELLO:
            self._send(P.HelloReply(FIRMWARE_VERSION, P.PROTOCOL_VERSION, self.n, int(self.spec.loop_rate),
                                    self.opt.watchdog_ms, self.opt.max_telemetry_hz), seq)
        elif m == P.MsgId.GET_STATE:
            self._send(P.StateMsg(FIRMWARE_VERSION, self.state, self.fault_flags, self.fault_hinge,
                                  (self.tick * 1000) & 0xFFFFFFFF, self.decoder.bad_frames & 0xFFFFFFFF,
                                  tuple(int(c) for c in self.counts), tuple(int(c) for c in self.targets)), seq)
        elif m == P.MsgId.GET_GAINS:
            if msg.hinge >= self.n:
                return self._nack(seq, m, P.Nack.BAD_VALUE, msg.hinge)
            self._send(P.GainsReply(msg.hinge, self.gains[msg.hinge]), seq)
        elif m == P.MsgId.SET_TARGETS:
            if len(msg.counts) != self.n:
                return self._nack(seq, m, P.Nack.BAD_LENGTH, len(msg.counts))
            if self.state in (P.State.ESTOP, P.State.FAULT):
                return self._nack(seq, m, P.Nack.BAD_STATE, self.state)
            for k, c in enumerate(msg.counts):
                if abs(c) > self.limit_counts:
                    return self._nack(seq, m, P.Nack.OUT_OF_RANGE, k)
            self.targets[:] = msg.counts
            if self.state == P.State.IDLE:
                self.prev[:] = self.counts
                self.rate[:] = 0.0
                self.integral[:] = 0.0
                self.stall_ref[:] = self.counts
                self.stall_since[:] = self.tick
                self.state = P.State.ACTIVE
            self._ack(seq, m)
        elif m == P.MsgId.SET_GAINS:
            if msg.hinge != P.BROADCAST and msg.hinge >= self.n:
                return self._nack(seq, m, P.Nack.BAD_VALUE, msg.hinge)
            g = msg.gains
            if g.cutoff <= 0 or min(g.kp, g.ki, g.kd, g.integral_limit, g.deadband) < 0:
                return self._nack(seq, m, P.Nack.BAD_VALUE, msg.hinge)
            for k in range(self.n) if msg.hinge == P.BROADCAST else (msg.hinge,):
                self.gains[k] = g
            self.gain_rows = gains_table([x.to_pid() for x in self.gains], self.n, self.dt)
            self._ack(seq, m)
        elif m == P.MsgId.ESTOP:
            if self.state != P.State.ESTOP:
                self._fault(P.Fault.ESTOP)
            self._ack(seq, m)
        elif m == P.MsgId.CLEAR_FAULT:
            self.state, self.fault_flags, self.fault_hinge = P.State.IDLE, P.Fault.NONE, 0xFF
            self.targets[:] = self.counts
            self._ack(seq, m)
        elif m == P.MsgId.SET_TELEMETRY_RATE:
            if msg.rate_hz > self.opt.max_telemetry_hz:
                return self._nack(seq, m, P.Nack.BAD_VALUE, 0)
            self.telemetry_every = 0 if msg.rate_hz == 0 else max(1, round(self.spec.loop_rate / msg.rate_hz))
            self._ack(seq, m)
        else:  # a device -> host message sent to the device
            self._nack(seq, m, P.Nack.UNKNOWN_MESSAGE, 0)

    def _ack(self, seq, m) -> None:
        self._send(P.Ack(m, (self.tick * 1000) & 0xFFFFFFFF), seq)

    def _nack(self, seq, m, reason: P.Nack, detail: int) -> None:
        self._log("nack", msg=P.MsgId(m).name, seq=seq, reason=reason.name, detail=int(detail))
        self._send(P.NackMsg(m, reason, int(detail) & 0xFF), seq)

    def _checks(self, counts) -> None:
        if (self.tick - self.last_rx_tick) * self.dt * 1000 > self.opt.watchdog_ms:
            return self._fault(P.Fault.WATCHDOG)
        for k in range(self.n):
            if abs(counts[k]) > self.limit_counts + 8:
                return self._fault(P.Fault.LIMIT, k)
        moved = np.abs(counts - self.stall_ref) > 2
        weak = np.abs(self.duty) < self.opt.stall_duty
        reset = moved | weak
        self.stall_ref[reset] = counts[reset]
        self.stall_since[reset] = self.tick
        stalled = np.flatnonzero((self.tick - self.stall_since) * self.dt * 1000 > self.opt.stall_ms)
        if stalled.size:
            self._fault(P.Fault.STALL, int(stalled[0]))


def _fields(msg) -> dict:
    out = {}
    for f in dataclasses.fields(msg):
        v = getattr(msg, f.name)
        out[f.name] = dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v
    return out
