"""Why bring-up's drawn-plant tests time out now and then under load (issue 38): the emulator's cost per tick
idle and while a hinge is pulsed, and the host's GET_STATE round trip on a served emulator, as the tests run it
(the sketch in the loop on a drawn plant lying flat, on a thread of the host's own process, paced in real time).

- tick: `Emulator.step` alone, 500 ticks idle, then 250 ticks after each PULSE at the strongest bring-up pulse
  (0.4, 150 ms) each way on every hinge: median, p99, max per tick, us;
- round trip: for SECONDS, GET_STATE every 20 ms (8 a round), with or without a PULSE (0.3, 100 ms; hinges 0, 1,
  4, 5 each way) starting each round: p50, p99, max ms, how many over 100 ms, whether the Link timed out (4 tries
  of 100 ms: what failed the tests), and the device time the emulator lost behind the wall clock.

    python benchmarks/bench_bringup_link.py [--seconds 15] [--seed 72]

One run; the round trip depends on the machine's load (print `uptime` beside it).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from twin.commands import emulate  # noqa: E402
from twin.device.spec import load_spec  # noqa: E402
from twin.link import protocol as P  # noqa: E402
from twin.link.drawn_plant import emulator_args  # noqa: E402
from twin.link.emulator import Emulator  # noqa: E402
from twin.link.pty_device import served  # noqa: E402
from twin.link.serial_link import Link, LinkTimeout  # noqa: E402


def drawn(spec, seed: int) -> Emulator:
    """The sketch in the loop on a plant drawn from seed, lying flat (as the tests' drawn_emulator)."""
    p = argparse.ArgumentParser()
    emulate.add_arguments(p)
    args = p.parse_args([*emulator_args(seed), "--sketch", "--latency-ms", "0", "--lying-flat"])
    return Emulator(spec, emulate.options_from_args(args, spec))


def tick_costs(spec, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """us per Emulator.step: idle, and after pulses."""
    emu = drawn(spec, seed)

    def run(n):
        out = []
        for _ in range(n):
            t0 = time.perf_counter()
            emu.step()
            emu.take_output()
            out.append(time.perf_counter() - t0)
        return np.array(out) * 1e6
    idle, pulsed, seq = run(500), [], 1
    for k in range(spec.n_hinges):
        for duty in (P.PULSE_MAX_DUTY, -P.PULSE_MAX_DUTY):
            emu.receive(P.encode(P.Pulse(k, int(duty * P.DUTY_SCALE), 150), seq))
            emu.receive(P.encode(P.Heartbeat(), seq + 1))
            seq += 2
            pulsed.append(run(250))
    return idle, np.concatenate(pulsed)


def round_trips(spec, seed: int, seconds: float, pulses: bool) -> tuple[np.ndarray, bool, float]:
    """GET_STATE round trips (ms), whether one timed out, and device time lost behind the wall clock (ms)."""
    emu = drawn(spec, seed)
    rtts, timed_out = [], False
    with served(emu) as port, Link(port, hinges=spec.n_hinges) as link:
        t_start, tick0, i = time.monotonic(), emu.tick, 0
        try:
            while time.monotonic() < t_start + seconds:
                if pulses:
                    link.pulse([0, 1, 4, 5][(i // 2) % 4], 0.3 * (1 if i % 2 == 0 else -1), 0.1)
                for _ in range(8):
                    t0 = time.monotonic()
                    link.get_state()
                    rtts.append((time.monotonic() - t0) * 1000)
                    time.sleep(0.02)
                i += 1
        except LinkTimeout:
            timed_out = True
        lost = (time.monotonic() - t_start - (emu.tick - tick0) * emu.dt) * 1000
    return np.array(rtts), timed_out, lost


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--seed", type=int, default=72)
    a = ap.parse_args()
    spec = load_spec()
    idle, pulsed = tick_costs(spec, a.seed)
    for name, t in (("idle", idle), ("pulsed", pulsed)):
        print(f"tick {name:6}: median {np.median(t):.0f} us, p99 {np.percentile(t, 99):.0f}, max {t.max():.0f}")
    for pulses in (False, True):
        r, timed_out, lost = round_trips(spec, a.seed, a.seconds, pulses)
        print(f"GET_STATE {'with pulses' if pulses else 'no pulses  '}: n={len(r)} p50 {np.percentile(r, 50):.1f} ms, "
              f"p99 {np.percentile(r, 99):.1f}, max {r.max():.1f}, over 100 ms {(r > 100).sum()}, "
              f"timed out {timed_out}; the emulator {lost:.0f} ms behind the wall clock")
    print("load average", " ".join(f"{x:.1f}" for x in os.getloadavg()))


if __name__ == "__main__":
    main()
