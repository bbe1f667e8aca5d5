"""Faults injected into the emulated device: command latency, a dropped link, corrupted bytes, a jammed hinge,
wiring mistakes between the board and its motors and encoders (those of a first board: swapped wires, a dead
encoder or one dead channel, motors on each other's bridges, a bridge input left open).

Each acts at the device's edge, never inside its firmware: latency and a dead
link on the bytes in, a dead link and corruption on the bytes out, a jam on the
plant. Times are the device's, in seconds.
"""

from __future__ import annotations

import collections
import dataclasses
import random

import numpy as np

from twin.sim.plant import Plant

FRAME_END = b"\x00"  # every frame on the wire ends with this byte (COBS)


@dataclasses.dataclass(frozen=True)
class FaultOptions:
    """Which faults to inject, and when."""

    latency_ms: float = 1.0  # from a command's arrival to its effect (and its ACK)
    jam_hinge: int | None = None  # this hinge locks ...
    jam_after: float = 0.0  # ... this many seconds after it first moves under a target
    drop_after: float | None = None  # s of device time after which the link goes dead (no bytes in or out)
    corrupt: float = 0.0  # probability per outgoing frame of a flipped byte, and of garbage inserted
    wiring: tuple[str, ...] = ()  # wiring mistakes (WIRING_FAULTS): "motor-reversed:2", "crossed:1,3", ...


WIRING_FAULTS = {
    "motor-reversed": "hinge K's motor leads swapped: positive drive turns it the negative way",
    "encoder-reversed": "hinge K's encoder A and B swapped: it counts the other way",
    "encoder-dead": "hinge K's encoder unpowered: its count never changes",
    "channel-dead": "hinge K's encoder channel B open: the decoder sees A's edges alone, back and forth by one count",
    "crossed": "hinges J and K's encoder cables swapped: each motor turns the other's encoder",
    "bridges-crossed": "hinges J and K's motors on each other's bridges: each bridge turns the other hinge",
    "input-open": "bridge K's input N (1 or 2) open: the board's pull-up holds it high, so the way it drives (IN2 "
                  "forward, IN1 reverse) brakes instead",
}
TWO = {"crossed": "two different hinges", "bridges-crossed": "two different hinges", "input-open": "a hinge and 1 or 2"}


@dataclasses.dataclass(frozen=True)
class Miswiring:
    """How the board's inputs and outputs reach the plant: board encoder input k reads plant motor source[k]'s
    shaft (times sign[k]; dead ones stay at their first reading; one_channel ones decode channel A alone),
    plant motor m is driven by board bridge bridge[m] times motor_sign[m], and a bridge k with an open input
    drives one way only (open[k]: +1 forward braked, -1 reverse braked, 0 none)."""

    source: tuple[int, ...]
    sign: tuple[int, ...]
    dead: tuple[bool, ...]
    motor_sign: tuple[int, ...]
    one_channel: tuple[bool, ...] = ()
    bridge: tuple[int, ...] = ()
    open: tuple[int, ...] = ()

    @classmethod
    def parse(cls, faults, n: int) -> "Miswiring":
        """From FaultOptions.wiring; ValueError naming a fault or hinge that is not there."""
        source, sign, dead, motor = list(range(n)), [1] * n, [False] * n, [1] * n
        one_channel, bridge, open_ = [False] * n, list(range(n)), [0] * n
        for text in faults:
            kind, _, where = str(text).partition(":")
            if kind not in WIRING_FAULTS:
                raise ValueError(f"wiring fault {text!r}: one of {', '.join(WIRING_FAULTS)} with its hinge(s), "
                                 "e.g. motor-reversed:2 or crossed:1,3")
            try:
                hinges = [int(x) for x in where.split(",")]
            except ValueError:
                raise ValueError(f"wiring fault {text!r}: expected hinge numbers after the colon") from None
            ok = len(hinges) == (2 if kind in TWO else 1) and 0 <= hinges[0] < n and (
                kind not in TWO or (hinges[1] in (1, 2) if kind == "input-open" else
                                    0 <= hinges[1] < n and hinges[1] != hinges[0]))
            if not ok:
                raise ValueError(f"wiring fault {text!r}: {TWO.get(kind, 'one hinge')} of 0..{n - 1}")
            k = hinges[0]
            if kind == "motor-reversed":
                motor[k] = -motor[k]
            elif kind == "encoder-reversed":
                sign[k] = -sign[k]
            elif kind == "encoder-dead":
                dead[k] = True
            elif kind == "channel-dead":
                one_channel[k] = True
            elif kind == "input-open":
                open_[k] = 1 if hinges[1] == 2 else -1
            elif kind == "crossed":
                j = hinges[1]
                source[k], source[j] = source[j], source[k]
            else:
                j = hinges[1]
                bridge[k], bridge[j] = bridge[j], bridge[k]
        return cls(tuple(source), tuple(sign), tuple(dead), tuple(motor), tuple(one_channel), tuple(bridge),
                   tuple(open_))

    def encoder_inputs(self, shaft_counts, first) -> np.ndarray:
        """What the board's encoder inputs count, from the plant's shaft counts (first: the counts at power-on)."""
        c, c0 = np.asarray(shaft_counts), np.asarray(first)
        out = np.array([s * c[src] for src, s in zip(self.source, self.sign)], c.dtype)
        for k in np.flatnonzero(self.one_channel):
            out[k] = one_channel_count(out[k], self.sign[k] * c0[self.source[k]])
        dead = np.array(self.dead)
        out[dead] = c0[dead]
        return out

    def plant_drive(self, pwm, decay) -> tuple[np.ndarray, np.ndarray]:
        """The plant's motors' PWM and decay from the board's bridges': a bridge with an open input brakes the way
        that input drives; each motor takes its bridge's PWM, times its sign, and its decay (a coasting bridge
        leaves its motor's windings open)."""
        p = np.asarray(pwm, np.float32).copy()
        blocked = np.asarray(self.open or [0] * len(p))
        p[(blocked != 0) & (np.sign(p) == blocked)] = 0.0
        bridge = list(self.bridge or range(len(p)))
        return p[bridge] * np.asarray(self.motor_sign, np.float32), np.asarray(decay, np.uint8)[bridge]


    def bridge_current(self, motor_current) -> np.ndarray:
        """What each board bridge senses from the plant's motors' currents: the current of the motor it drives."""
        c = np.asarray(motor_current)
        out = c.copy()
        out[list(self.bridge or range(len(c)))] = c
        return out


def one_channel_count(count: int, first: int) -> int:
    """What an x4 decoder counts with channel B stuck where it was at `first` counts and A still following the
    shaft at `count` (A leads B counting up: AB = 00, 10, 11, 01): A's edges step +1 and -1 about `first`."""
    def a(c):
        return int(c % 4 in (1, 2))
    b = int(first % 4 in (2, 3))
    return first + (a(count) - a(first)) * (1 if b == 0 else -1)


class Faults:
    """The injected faults' state for one device."""

    def __init__(self, opt: FaultOptions, rng: random.Random):
        self.opt = opt
        self.rng = rng
        self.incoming = collections.deque()  # (due time s, bytes)
        self.jam_armed_at = None  # s
        self.jam_angle = None  # rad

    def link_dead(self, t: float) -> bool:
        return self.opt.drop_after is not None and t >= self.opt.drop_after

    def arrive(self, data: bytes, t: float) -> None:
        """Bytes from the host at time t: they reach the firmware after the latency (never, on a dead link)."""
        if not self.link_dead(t):
            self.incoming.append((t + self.opt.latency_ms / 1000, data))

    def due(self, t: float) -> bytes:
        """The bytes whose latency has passed by time t."""
        out = bytearray()
        while self.incoming and self.incoming[0][0] <= t + 1e-9:
            out += self.incoming.popleft()[1]
        return bytes(out)

    def outgoing(self, data: bytes, t: float) -> bytes:
        """The firmware's bytes as the host receives them: per frame, maybe a flipped byte and garbage before it."""
        if self.link_dead(t):
            return b""
        if self.opt.corrupt <= 0 or not data:
            return data
        out = bytearray()
        for frame in data.split(FRAME_END)[:-1]:
            frame = bytearray(frame + FRAME_END)
            if self.rng.random() < self.opt.corrupt:
                frame[self.rng.randrange(len(frame) - 1)] ^= self.rng.randrange(1, 256)
            if self.rng.random() < self.opt.corrupt:
                out += bytes(self.rng.randrange(256) for _ in range(self.rng.randrange(1, 40)))
            out += frame
        return bytes(out)

    def jam(self, plant: Plant, active: bool, t: float) -> float | None:
        """Hold the jammed hinge once it is due (armed when the device first runs under a target).

        Returns the jam angle (rad) on the tick the hinge jams, else None.
        """
        k = self.opt.jam_hinge
        if k is None:
            return None
        if self.jam_armed_at is None and active:
            self.jam_armed_at = t
        if self.jam_armed_at is None:
            return None
        jammed_now = None
        if self.jam_angle is None and t - self.jam_armed_at >= self.opt.jam_after:
            self.jam_angle = jammed_now = float(plant.data.qpos[plant.hinges.qadr[k]])
        if self.jam_angle is not None:
            plant.hold_hinge(k, self.jam_angle)
        return jammed_now

