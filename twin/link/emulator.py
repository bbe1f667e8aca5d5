"""A VRScroll device emulator on a real pseudo-terminal: the firmware's logic on its own plant.

`vrscroll emulate` (or `python -m twin.emulator`) opens a pty, prints the path of its
slave end (connect to it like to /dev/ttyACM0) and runs until SIGINT/SIGTERM. Each
firmware tick (1 kHz, paced to real time) it reads the encoders, runs the firmware
PID (controllers.pid, the same kernel as the twin), checks the watchdog, hinge
range and stall, drives its MuJoCo plant and streams telemetry.

The plant is the twin's model built from a *different* spec (more friction, a
weaker motor constant) plus what MuJoCo does not model here: backlash (as encoder
hysteresis), encoder noise and command latency; options add faults (a jammed
hinge, a link that stops answering, corrupted bytes). Every command received is
written to a JSON-lines log as it arrives.
"""

from __future__ import annotations

import argparse
import collections
import subprocess
import dataclasses
import errno
import json
import math
from pathlib import Path
import os
import random
import select
import signal
import sys
import time
import tty

import mujoco
import numpy as np

from controllers.pid import gains_table, pid_update
from twin.link import protocol as P
from twin.device.spec import DeviceSpec, load_spec

FIRMWARE_VERSION = (0, 1, 0)


@dataclasses.dataclass
class EmulatorOptions:
    """How the emulated device differs from the twin, and which faults to inject."""

    friction_scale: float = 1.25  # gear_friction x
    damping_scale: float = 1.2  # gear_damping x
    speed_scale: float = 0.95  # no_load_speed x (so motor constant / 0.95)
    armature_scale: float = 1.0  # rotor_inertia x
    backlash_deg: float = 0.5  # dead zone between hinge and encoder, deg (full width)
    encoder_noise: float = 0.01  # probability per read that a count is off by one
    latency_ms: float = 1.0  # from a command's arrival to its effect (and its ACK)
    watchdog_ms: int = 200  # host quiet this long while ACTIVE -> FAULT, motors off
    max_telemetry_hz: int = 500
    stall_duty: float = 0.5  # |duty| at or above this with no motion ...
    stall_ms: int = 300  # ... for this long -> FAULT STALL
    jam_hinge: int | None = None  # this hinge locks ...
    jam_after: float = 0.0  # ... this many seconds after it first moves under a target
    drop_after: float | None = None  # s of device time after which the link goes dead (no bytes in or out)
    corrupt: float = 0.0  # probability per outgoing frame of a flipped byte, and of garbage inserted
    seed: int = 0


def plant_spec(spec: DeviceSpec, opt: EmulatorOptions) -> DeviceSpec:
    """The emulated device's physical spec: the twin's, perturbed."""
    return spec.replace(gear_friction=spec.gear_friction * opt.friction_scale,
                        gear_damping=spec.gear_damping * opt.damping_scale,
                        no_load_speed=spec.no_load_speed * opt.speed_scale,
                        rotor_inertia=spec.rotor_inertia * opt.armature_scale,
                        backlash=math.radians(opt.backlash_deg))


class Emulator:
    """The firmware and plant of one device, talking over a file descriptor (the pty master)."""

    def __init__(self, fd: int, spec: DeviceSpec | None = None, opt: EmulatorOptions | None = None,
                 log_path: str | None = None):
        from controllers.pid import PidGains
        from twin.device.mjcf import load_model

        self.fd = fd
        self.spec = spec or load_spec()
        self.opt = opt or EmulatorOptions()
        self.plant = plant_spec(self.spec, self.opt)
        self.model = load_model(self.plant)
        self.data = mujoco.MjData(self.model)
        mujoco.mj_resetDataKeyframe(self.model, self.data, self.model.key("flat").id)
        mujoco.mj_forward(self.model, self.data)
        s, n = self.spec, self.spec.n_hinges
        self.n = n
        self.dt = s.firmware_dt
        self.qadr = np.array([self.model.joint(f"hinge{k}").qposadr[0] for k in range(n)])
        self.dadr = np.array([self.model.joint(f"hinge{k}").dofadr[0] for k in range(n)])
        self.rng = random.Random(self.opt.seed)
        # firmware state; gains as the wire would carry them
        wire = P.Gains.from_pid(PidGains.from_spec(s))
        self.gains = [wire] * n
        self.gain_rows = gains_table([g.to_pid() for g in self.gains], n, self.dt)
        self.limit_counts = int(math.floor(s.hinge_limit / s.rad_per_count))
        self.measured = self.data.qpos[self.qadr].copy()  # hinge angle as the encoder sees it (backlash)
        self.counts = self._read_counts()
        self.targets = self.counts.copy()
        self.prev = self.counts.copy()
        self.rate = np.zeros(n)
        self.integral = np.zeros(n)
        self.duty = np.zeros(n)
        self.current = np.zeros(n)
        # load the compiled PID now, not on the first tick that needs it (a stall of ~0.3 s)
        pid_update(self.targets, self.counts, self.prev.copy(), self.rate.copy(), self.integral.copy(),
                   self.gain_rows, self.dt, self.duty.copy())
        self.state = P.State.IDLE
        self.faults = P.Fault.NONE
        self.fault_hinge = 0xFF
        self.tick = 0
        self.last_rx_tick = 0
        self.telemetry_every = 0  # ticks; 0 = off
        self.telemetry_seq = 0
        self.telemetry_dropped = 0
        self.stall_ref = self.counts.copy()
        self.stall_since = np.zeros(n, np.int64)
        self.jam_angle = None
        self.jam_armed_at = None
        self.decoder = P.Decoder()
        self.pending = collections.deque()  # (apply tick, seq, message)
        self.out = bytearray()
        self.overruns = 0
        self.log = open(log_path, "a", buffering=1) if log_path else None
        self._log("start", plant={k: getattr(self.plant, k) for k in ("gear_friction", "gear_damping",
                                                                       "no_load_speed", "rotor_inertia", "backlash")},
                  options=dataclasses.asdict(self.opt))

    # ---- helpers --------------------------------------------------------------------
    @property
    def time(self) -> float:
        """Device time, s."""
        return self.tick * self.dt

    def _log(self, event: str, **fields) -> None:
        if self.log:
            self.log.write(json.dumps({"t": round(self.time, 6), "event": event, **fields}) + "\n")

    def _dead(self) -> bool:
        return self.opt.drop_after is not None and self.time >= self.opt.drop_after

    def _read_counts(self) -> np.ndarray:
        """Encoder counts: the hinge angle through the backlash dead zone, quantized, with noise."""
        s = self.spec
        angle = self.data.qpos[self.qadr]
        half = self.plant.backlash / 2
        self.measured = np.clip(self.measured, angle - half, angle + half)
        counts = np.floor(self.measured * s.gear_ratio * s.counts_per_motor_rev / (2 * math.pi)).astype(np.int64)
        if self.opt.encoder_noise > 0:
            for k in range(self.n):
                if self.rng.random() < self.opt.encoder_noise:
                    counts[k] += self.rng.choice((-1, 1))
        return counts

    def _send(self, msg, seq: int, telemetry: bool = False) -> None:
        if self._dead():
            return
        frame = P.encode(msg, seq)
        if telemetry and len(self.out) > 8192:  # the UART's buffer is full: drop, as firmware would
            self.telemetry_dropped += 1
            return
        if self.opt.corrupt > 0:
            if self.rng.random() < self.opt.corrupt:
                b = bytearray(frame)
                i = self.rng.randrange(len(b) - 1)
                b[i] ^= self.rng.randrange(1, 256)
                frame = bytes(b)
            if self.rng.random() < self.opt.corrupt:
                frame = bytes(self.rng.randrange(256) for _ in range(self.rng.randrange(1, 40))) + frame
        self.out += frame

    def _fault(self, flag: P.Fault, hinge: int = 0xFF) -> None:
        self.state = P.State.ESTOP if flag == P.Fault.ESTOP else P.State.FAULT
        self.faults |= flag
        if self.fault_hinge == 0xFF:
            self.fault_hinge = hinge
        self.duty[:] = 0.0
        self._log("fault", fault=flag.name, hinge=None if hinge == 0xFF else hinge, state=self.state.name,
                  last_rx_t=round(self.last_rx_tick * self.dt, 6))

    # ---- commands -------------------------------------------------------------------
    def receive(self, data: bytes) -> None:
        """Bytes from the host: decode and queue each command for after the latency."""
        if self._dead():
            return
        bad = self.decoder.bad_frames
        due = self.tick + int(round(self.opt.latency_ms / 1000 / self.dt))
        for seq, msg in self.decoder.feed(data):
            self.pending.append((due, seq, msg))
            self._log("rx", msg=msg.MSG.name, seq=seq, **_fields(msg))
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
            self._send(P.StateMsg(FIRMWARE_VERSION, self.state, self.faults, self.fault_hinge,
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
            if self.opt.jam_hinge is not None and self.jam_armed_at is None:
                self.jam_armed_at = self.tick
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
            self.state, self.faults, self.fault_hinge = P.State.IDLE, P.Fault.NONE, 0xFF
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

    # ---- one firmware tick ------------------------------------------------------------
    def step(self) -> None:
        """One firmware tick: commands due, encoders, safety checks, PID, one plant step, telemetry."""
        s, d = self.spec, self.data
        while self.pending and self.pending[0][0] <= self.tick:
            _, seq, msg = self.pending.popleft()
            self._handle(seq, msg)
        mujoco.mj_step1(self.model, d)
        self.counts = counts = self._read_counts()
        if self.state == P.State.ACTIVE:
            self._checks(counts)
        if self.state == P.State.ACTIVE:
            pid_update(self.targets, counts, self.prev, self.rate, self.integral, self.gain_rows, self.dt,
                       self.duty)
        else:
            self.duty[:] = 0.0
            self.prev[:] = counts
        volts = self.duty * s.drive_cap
        d.ctrl[:] = volts
        speed = d.qvel[self.dadr]
        self.current = (volts - s.motor_constant * s.gear_ratio * speed) / s.resistance
        mujoco.mj_step2(self.model, d)
        self._jam()
        if self.telemetry_every and self.tick % self.telemetry_every == 0:
            self._send(P.Telemetry((self.tick * 1000) & 0xFFFFFFFF, self.state, self.faults, self.fault_hinge,
                                   tuple(int(c) for c in counts), tuple(int(c) for c in self.targets),
                                   tuple(int(round(x * P.DUTY_SCALE)) for x in self.duty),
                                   tuple(int(max(-32768, min(32767, round(i * 1000)))) for i in self.current)),
                       self.telemetry_seq, telemetry=True)
            self.telemetry_seq = (self.telemetry_seq + 1) & 0xFFFF
        self.tick += 1

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

    def _jam(self) -> None:
        k = self.opt.jam_hinge
        if k is None or self.jam_armed_at is None:
            return
        if self.jam_angle is None and (self.tick - self.jam_armed_at) * self.dt >= self.opt.jam_after:
            self.jam_angle = float(self.data.qpos[self.qadr[k]])
            self._log("jam", hinge=k, angle_deg=math.degrees(self.jam_angle))
        if self.jam_angle is not None:
            self.data.qpos[self.qadr[k]] = self.jam_angle
            self.data.qvel[self.dadr[k]] = 0.0

    # ---- real time ------------------------------------------------------------------
    def _read_input(self) -> None:
        try:
            data = os.read(self.fd, 65536)
        except BlockingIOError:
            return
        except OSError as exc:
            if exc.errno in (errno.EIO, errno.EAGAIN):
                return
            raise
        if data:
            self.receive(data)

    def _flush(self) -> None:
        if self._dead():
            self.out.clear()
        while self.out:
            try:
                sent = os.write(self.fd, self.out)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                if exc.errno in (errno.EIO, errno.EAGAIN):
                    self.out.clear()
                    return
                raise
            del self.out[:sent]
            if len(self.out) > 65536:  # nobody reads: keep the newest
                del self.out[:-65536]

    def run(self, should_stop) -> None:
        """Tick at the firmware rate in real time until should_stop() is true."""
        os.set_blocking(self.fd, False)
        start = time.monotonic()
        first = self.tick
        while not should_stop():
            self._read_input()
            self.step()
            self._flush()
            next_at = start + (self.tick - first) * self.dt
            wait = next_at - time.monotonic()
            if wait > 0:
                r, _, _ = select.select([self.fd], [], [], wait)
                if r:
                    self._read_input()
                    wait = next_at - time.monotonic()
                    if wait > 0:
                        time.sleep(wait)
            elif wait < -0.05:  # fell behind by more than 50 ticks: do not try to catch up
                self.overruns += 1
                start, first = time.monotonic(), self.tick
        self._log("stop", ticks=self.tick, overruns=self.overruns, rx_bad_frames=self.decoder.bad_frames,
                  telemetry_dropped=self.telemetry_dropped)
        if self.log:
            self.log.close()


def _fields(msg) -> dict:
    out = {}
    for f in dataclasses.fields(msg):
        v = getattr(msg, f.name)
        out[f.name] = dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v
    return out


# ---- as a separate process ----------------------------------------------------------------

_ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


class EmulatorProcess:
    """`python -m twin.emulator` in a subprocess; `port` is its pty, `log` its JSON-lines command log."""

    def __init__(self, log, *args: str):
        self.log = Path(log)
        self._stderr = open(self.log.with_suffix(".stderr"), "w")
        self.proc = subprocess.Popen([sys.executable, "-m", "twin.link.emulator", "--log", str(self.log), *args],
                                     stdout=subprocess.PIPE, stderr=self._stderr, text=True, cwd=_ROOT)
        line = self.proc.stdout.readline().strip()  # the pty path, printed once the device is running
        if not line.startswith("/dev/"):
            self.stop()
            raise RuntimeError(f"emulator did not start: {line!r} {self.log.with_suffix('.stderr').read_text()}")
        self.port = line

    def events(self, kind: str | None = None) -> list[dict]:
        """The emulator's log so far (every line must be valid JSON)."""
        if not self.log.exists():
            return []
        rows = [json.loads(x) for x in self.log.read_text().splitlines() if x.strip()]
        return [r for r in rows if kind is None or r["event"] == kind]

    def kill(self) -> None:
        """Pull the plug: SIGKILL, the pty vanishes."""
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(5)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self.proc.stdout.close()
        self._stderr.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


# ---- command line ---------------------------------------------------------------------

def add_arguments(p: argparse.ArgumentParser) -> None:
    o = EmulatorOptions()
    p.add_argument("--log", help="JSON-lines log of every command received (appended)")
    p.add_argument("--port-file", help="also write the pty path to this file")
    p.add_argument("--friction-scale", type=float, default=o.friction_scale, help="gear friction x (default %(default)s)")
    p.add_argument("--damping-scale", type=float, default=o.damping_scale, help="gear damping x (default %(default)s)")
    p.add_argument("--speed-scale", type=float, default=o.speed_scale,
                   help="no-load speed x, i.e. motor constant / x (default %(default)s)")
    p.add_argument("--armature-scale", type=float, default=o.armature_scale,
                   help="rotor inertia (armature) x (default %(default)s)")
    p.add_argument("--backlash-deg", type=float, default=o.backlash_deg, help="backlash, deg (default %(default)s)")
    p.add_argument("--encoder-noise", type=float, default=o.encoder_noise,
                   help="probability per read of a count off by one (default %(default)s)")
    p.add_argument("--latency-ms", type=float, default=o.latency_ms, help="command latency, ms (default %(default)s)")
    p.add_argument("--watchdog-ms", type=int, default=o.watchdog_ms, help="watchdog timeout, ms (default %(default)s)")
    p.add_argument("--jam-hinge", type=int, help="this hinge jams ...")
    p.add_argument("--jam-after", type=float, default=0.0, help="... this many s after the first target (default 0)")
    p.add_argument("--drop-after", type=float, help="the link goes dead after this many s of device time")
    p.add_argument("--corrupt", type=float, default=0.0,
                   help="probability per frame sent of a flipped byte and of inserted garbage (default 0)")
    p.add_argument("--seed", type=int, default=0, help="random seed for noise and corruption")
    p.add_argument("--ideal", action="store_true",
                   help="plant identical to the twin: no perturbation, backlash, noise or latency")


def options_from_args(args) -> EmulatorOptions:
    if args.ideal:
        base = dict(friction_scale=1.0, damping_scale=1.0, speed_scale=1.0, armature_scale=1.0, backlash_deg=0.0,
                    encoder_noise=0.0, latency_ms=0.0)
    else:
        base = dict(friction_scale=args.friction_scale, damping_scale=args.damping_scale,
                    speed_scale=args.speed_scale, armature_scale=args.armature_scale, backlash_deg=args.backlash_deg,
                    encoder_noise=args.encoder_noise, latency_ms=args.latency_ms)
    if args.jam_hinge is not None and not 0 <= args.jam_hinge < load_spec().n_hinges:
        raise ValueError(f"--jam-hinge {args.jam_hinge}: no such hinge")
    return EmulatorOptions(**base, watchdog_ms=args.watchdog_ms, jam_hinge=args.jam_hinge, jam_after=args.jam_after,
                           drop_after=args.drop_after, corrupt=args.corrupt, seed=args.seed)


def run(args) -> int:
    """Open a pty, print its path, emulate the device until SIGINT/SIGTERM."""
    opt = options_from_args(args)
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    emu = Emulator(master, opt=opt, log_path=args.log)
    stop = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.append(True))
    if args.port_file:
        with open(args.port_file + ".part", "w") as f:
            f.write(path + "\n")
        os.replace(args.port_file + ".part", args.port_file)
    print(path, flush=True)
    try:
        emu.run(lambda: bool(stop))
    finally:
        os.close(master)
        os.close(slave)
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m twin.emulator", description=__doc__.splitlines()[0])
    add_arguments(p)
    return run(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
