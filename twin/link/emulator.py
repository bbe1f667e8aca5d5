"""An emulated VRScroll device, software in the loop: the device's firmware on a MuJoCo plant.

The firmware is the C core alone (controllers.core), or with `sketch=True` the whole ESP32-S3
sketch on stand-ins for its peripherals (controllers.sketch): its encoders decoded from quadrature
edges, its PWM through the H-bridges' truth table, its serial port's buffers. Both give the same
`run_tick(now_us, counts, current_ma, battery_mv) -> (pwm, decay)`.

`Emulator` is one device, driven tick by tick: `receive(bytes)` as they arrive
from the host, `step()` once per firmware tick, `take_output()` for the bytes it
answers with. The firmware is the device's own C core (controllers.core): the
host's bytes go into its parser (`vrs_rx`), every reply and telemetry frame
comes from it (`vrs_tx`), every duty the plant gets comes from its control tick
(`vrs_tick`: supervisor, watchdog, PID). Python keeps only the plant
(twin.sim.plant), the injected faults (twin.link.faults) and the command log;
`twin.link.pty_device` serves it on a pseudo-terminal in real time
(`vrscroll emulate`). The log is JSON lines, written as things happen: every
command the firmware receives, its refusals and faults, read back from its
bytes and state, never decided here.
"""

from __future__ import annotations

import dataclasses
import json
import math
import random

import numpy as np

from controllers import core
from controllers.core import tick_us
from controllers.pid import PidGains
from controllers.sketch import Sketch
from twin.device.spec import DeviceSpec, load_spec
from twin.link import protocol as P
from twin.link.faults import FaultOptions, Faults, Miswiring
from twin.sim.plant import Plant, PlantOptions, PlantRanges, draw_plant

BACKLOG = 4096  # bytes out of the firmware but not yet taken by the host: it is not asked for more beyond this
# Frames of the firmware's answer the log reads per tick for its "nack" lines; beyond, they are counted
# ("tx_unlogged", once a second). The log's reader is Python: a 1 MB/s flood of frames of another protocol
# version, each answered with a NACK, gave it 30 a tick to decode, 1.3 ms of work per 1 ms tick (the emulator
# overran its real time 99 times in 6 s, and answered GET_STATE 44 ms late; benchmarks/bench_emulator_flood.py)
LOG_FRAMES_PER_TICK = 8


@dataclasses.dataclass(frozen=True)
class EmulatorOptions:
    """The emulated device: its plant, its faults, its watchdog (None: the spec's), the random seed, and
    whether the firmware is the whole ESP32-S3 sketch on its peripherals' stand-ins (controllers.sketch)
    or the C core alone."""

    plant: PlantOptions = PlantOptions()
    faults: FaultOptions = FaultOptions()
    watchdog_ms: int | None = None
    host_away_hold_ms: int | None = None  # None: the spec's (the C core alone; the sketch has the spec's)
    seed: int = 0
    sketch: bool = False
    zeroed: bool = False  # the bench user confirmed the flat pose at power-on, before anything sagged


def drawn_options(ranges: PlantRanges, faults: FaultOptions, seed: int, watchdog_ms: int | None = None,
                  encoder_miss: float = 0.0, pack_voltage: float | None = None, sketch: bool = False,
                  zeroed: bool = False, n_hinges: int | None = None) -> EmulatorOptions:
    """An emulated device whose plant and latency are drawn within `ranges` from `seed` (the faults' latency
    replaced by the drawn one); n_hinges: the device's (default the spec's)."""
    n_hinges = load_spec().n_hinges if n_hinges is None else n_hinges
    plant, latency = draw_plant(ranges, random.Random(seed), encoder_miss, pack_voltage, n_hinges)
    return EmulatorOptions(plant=plant, faults=dataclasses.replace(faults, latency_ms=latency),
                           watchdog_ms=watchdog_ms, seed=seed, sketch=sketch, zeroed=zeroed)


class Emulator:
    """The firmware core, plant and injected faults of one device."""

    def __init__(self, spec: DeviceSpec | None = None, opt: EmulatorOptions | None = None,
                 log_path: str | None = None):
        self.spec = s = spec or load_spec()
        self.opt = opt or EmulatorOptions()
        self.rng = random.Random(self.opt.seed)
        self.plant = Plant(s, self.opt.plant, self.rng)
        self.faults = Faults(self.opt.faults, self.rng)
        self.wiring = Miswiring.parse(self.opt.faults.wiring, s.n_hinges)
        self._first_counts = self.plant.counts.copy()
        self.hand: tuple[int, float] | None = None  # (hinge, rad): a hand holding that flap there, for bring-up
        self.dt = s.firmware_dt
        self.tick = 0
        if self.opt.sketch:
            if self.opt.watchdog_ms is not None or self.opt.host_away_hold_ms is not None:
                raise ValueError("the sketch's watchdog and hold are the spec's (its header's): "
                                 "--watchdog-ms and --host-away-hold-ms are for the C core alone")
            self.firmware = Sketch(self.wiring.encoder_inputs(self.plant.counts, self._first_counts),
                                   P.ResetReason.POWERON)
        else:
            config = core.config_from_spec(s)
            if self.opt.watchdog_ms is not None:
                config.watchdog_ms = self.opt.watchdog_ms
            if self.opt.host_away_hold_ms is not None:
                config.host_away_hold_ms = self.opt.host_away_hold_ms
            self.firmware = core.Core(config, [PidGains.from_spec(s)] * s.n_hinges,
                                      self.wiring.encoder_inputs(self.plant.counts, self._first_counts))
            self.firmware.set_reset_reason(P.ResetReason.POWERON)
        if self.opt.zeroed:
            self.firmware.confirm_zero()
        self.out = bytearray()  # bytes for the host, not yet taken
        self._heard = P.Decoder()  # reads what the firmware is given and what it answers, for the log
        self._said = P.Decoder()
        self._unlogged = 0  # frames the firmware answered that the log has not read since its last count
        self._unlogged_tick = 0
        self._last_rx_tick = 0
        self._faults = 0
        self._state = P.State.IDLE
        self.log = open(log_path, "a", buffering=1) if log_path else None
        p = self.plant.spec
        self._log("start", plant={k: getattr(p, k) for k in ("gear_friction", "gear_stiction", "gear_damping",
                                                             "no_load_speed", "rotor_inertia", "backlash",
                                                             "backdrive_efficiency", "supply_voltage")},
                  hinges=[{k: getattr(h, k) for k in ("gear_friction", "gear_stiction", "gear_damping", "no_load_speed",
                                                      "rotor_inertia")} for h in self.plant.hinge_specs],
                  options=dataclasses.asdict(self.opt))

    @property
    def time(self) -> float:
        """Device time, s."""
        return self.tick * self.dt

    @property
    def counts(self) -> np.ndarray:
        """Encoder counts the firmware read at the last tick."""
        return self.plant.counts

    # ---- the device's edges -----------------------------------------------------------
    def receive(self, data: bytes) -> None:
        """Bytes from the host, arriving now."""
        self.faults.arrive(data, self.time)

    def take_output(self, max_bytes: int = BACKLOG) -> bytes:
        """Up to max_bytes of what the device has sent, oldest first."""
        out = bytes(self.out[:max_bytes])
        del self.out[:max_bytes]
        return out

    def step(self) -> None:
        """One firmware tick: the bytes due into the core, encoders, the core's tick, the plant's physics, its bytes out."""
        now_us = (self.tick * tick_us(self.spec)) & 0xFFFFFFFF
        data = self.faults.due(self.time)
        if data:
            self._log_rx(data)
            self.firmware.rx(data, now_us)
        # mA, the last tick's winding current, as each bridge senses its motor's
        sensed = np.clip(np.rint(self.wiring.bridge_current(self.plant.current) * 1000), -32768, 32767)
        # the battery the ADC reads is the last tick's bus voltage
        inputs = self.wiring.encoder_inputs(self.plant.sense(), self._first_counts)
        pwm, decay = self.firmware.run_tick(now_us, inputs, sensed, round(self.plant.bus * 1000))
        self._log_faults()
        self.plant.actuate(*self.wiring.plant_drive(pwm, decay))
        if self.hand is not None:
            self.plant.hold_hinge(*self.hand)
        driving = self.firmware.state == P.State.ACTIVE or bool(np.any(pwm))  # under targets, or a program
        jammed = self.faults.jam(self.plant, driving, self.time)
        if jammed is not None:
            self._log("jam", hinge=self.opt.faults.jam_hinge, angle_deg=math.degrees(jammed))
        if len(self.out) < BACKLOG:
            said = self.firmware.tx()
            self._log_nacks(said)
            self.out += self.faults.outgoing(said, self.time)
        self.tick += 1

    def close(self, **stats) -> None:
        """Log the run's end (with the caller's stats) and close the log."""
        self._log_unlogged()
        self._log("stop", ticks=self.tick, rx_bad_frames=self.firmware.rx_bad_frames,
                  telemetry_dropped=self.firmware.telemetry_dropped, **stats)
        if self.log:
            self.log.close()
            self.log = None

    # ---- the log: what the firmware heard, refused and did --------------------------------
    def _log(self, event: str, **fields) -> None:
        if self.log:
            self.log.write(json.dumps({"t": round(self.time, 6), "event": event, **fields}) + "\n")

    def _log_rx(self, data: bytes) -> None:
        bad = self._heard.bad_frames
        for seq, msg in self._heard.feed(data):
            self._last_rx_tick = self.tick
            self._log("rx", msg=msg.MSG.name, seq=seq, **_fields(msg))
        if self._heard.bad_frames != bad:
            self._log("bad_frames", count=self._heard.bad_frames, last_error=self._heard.last_error)

    def _log_nacks(self, data: bytes) -> None:
        if not self.log or not data:
            return
        if self.tick - self._unlogged_tick >= round(1 / self.dt):
            self._log_unlogged()
        frames = data.count(0)
        if frames > LOG_FRAMES_PER_TICK:  # a flood's answers: counted, not read; the reader resyncs after them
            self._unlogged += frames
            self._said = P.Decoder()
            self._said.feed(data[data.rindex(0) + 1:])
            return
        for seq, msg in self._said.feed(data):
            if isinstance(msg, P.NackMsg):
                self._log("nack", msg=_name(P.MsgId, msg.acked), seq=seq, reason=_name(P.Nack, msg.reason),
                          detail=msg.detail)

    def _log_unlogged(self) -> None:
        """The count of the firmware's frames the log did not read since the last count, if any."""
        if self._unlogged:
            self._log("tx_unlogged", frames=self._unlogged)
        self._unlogged, self._unlogged_tick = 0, self.tick

    def _log_faults(self) -> None:
        state = self.firmware.state
        if state == P.State.HOLDING and self._state != P.State.HOLDING:
            self._log("host_away", last_rx_t=round(self._last_rx_tick * self.dt, 6))
        self._state = state
        faults = self.firmware.faults
        new = faults & ~self._faults
        self._faults = faults
        if not new:
            return
        for flag in P.Fault:
            if flag & new:
                hinge = self.firmware.fault_hinge
                self._log("fault", fault=flag.name, hinge=None if hinge == 0xFF else hinge,
                          state=P.enum_name(P.State, self.firmware.state), last_rx_t=round(self._last_rx_tick * self.dt, 6))


def _name(kind, value: int) -> str:
    """The enum member's name, or the number in hex for one the table does not have (a host's unknown id)."""
    return kind(value).name if value in kind._value2member_map_ else f"0x{value:02X}"


def _fields(msg) -> dict:
    out = {}
    for f in dataclasses.fields(msg):
        v = getattr(msg, f.name)
        out[f.name] = dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v
    return out
