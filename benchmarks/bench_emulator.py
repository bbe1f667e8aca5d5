"""The emulator's control tick in real time: period and jitter at the firmware rate, under load.

The emulated device (twin/link/emulator.py, served on a real pty by
twin/link/pty_device.py) runs in its own process; this process is its host: a
Link with its heartbeat, telemetry streaming at 500 Hz and a new target for all
six hinges every 0.5 s. The device's process stamps the start of every tick
(the wall clock as `serve` asks whether to stop); the period is the difference
between stamps, the jitter its difference from 1 / loop rate.

    python benchmarks/bench_emulator.py [--seconds 20] [--sketch]

--sketch: the emulator runs the whole ESP32-S3 sketch on its peripherals' stand-ins (controllers.sketch)
instead of the C core alone.

Prints p50 and p99 of |jitter| (goal: p99 within 0.5 ms) and the emulator's overruns.
Measured, not asserted: shared machines are noisy (the load average is printed beside).
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from controllers.encoder import target_counts  # noqa: E402
from twin.device.spec import load_spec  # noqa: E402
from twin.link import protocol as P  # noqa: E402
from twin.link.emulator import Emulator, EmulatorOptions  # noqa: E402
from twin.link.pty_device import open_pty, serve  # noqa: E402
from twin.link.serial_link import Link  # noqa: E402

MOVES_DEG = ([30.0, -20.0, 45.0, 10.0, -60.0, 80.0], [-30.0, 20.0, -45.0, -10.0, 60.0, -80.0])


def device(ticks: int, sketch: bool, conn) -> None:
    """The emulated device for `ticks` ticks; sends its pty path, then its tick stamps (s) and overruns."""
    master, slave, path = open_pty()
    emu = Emulator(load_spec(), EmulatorOptions(zeroed=True, sketch=sketch))
    stamps = np.zeros(ticks)
    done = [0]

    def should_stop() -> bool:
        if done[0] < ticks:
            stamps[done[0]] = time.perf_counter()
        done[0] += 1
        return done[0] > ticks

    conn.send(path)
    overruns = serve(emu, master, should_stop)
    conn.send((stamps, overruns))
    os.close(master)
    os.close(slave)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--sketch", action="store_true", help="the whole sketch, not the C core alone")
    args = ap.parse_args()
    spec = load_spec()
    ticks = int(args.seconds * spec.loop_rate)
    ctx = multiprocessing.get_context("spawn")
    ours, theirs = ctx.Pipe()
    proc = ctx.Process(target=device, args=(ticks, args.sketch, theirs))
    proc.start()
    port = ours.recv()
    end = time.monotonic() + args.seconds - 1.0  # the host stops before the device does
    with Link(port) as link:
        link.set_telemetry_rate(500)
        k, faults = 0, []
        while time.monotonic() < end:
            state = link.get_state()
            if state.state == P.State.FAULT:  # e.g. a heartbeat late on a loaded machine: noted, cleared
                faults.append(P.Fault(state.faults).name)
                link.clear_fault()
            link.set_targets(target_counts(spec, np.radians(MOVES_DEG[k % 2])))
            time.sleep(0.5)
            link.drain_telemetry()
            k += 1
        stamps, overruns = ours.recv()
    proc.join()
    jitter = np.abs(np.diff(stamps) - spec.firmware_dt) * 1e3
    firmware = "the whole sketch (--sketch)" if args.sketch else "the C core alone"
    print(f"emulator ({firmware}) control tick at {spec.loop_rate:.0f} Hz, {args.seconds:.0f} s with a host streaming telemetry "
          f"at 500 Hz and moving all hinges every 0.5 s (load average {os.getloadavg()[0]:.2f}):")
    print(f"  period p50 {np.median(np.diff(stamps)) * 1e3:.3f} ms; |jitter| p50 {np.percentile(jitter, 50):.3f} ms, "
          f"p99 {np.percentile(jitter, 99):.3f} ms, max {jitter.max():.3f} ms (goal p99 <= 0.5 ms); "
          f"overruns {overruns}; device faults seen {faults or 'none'}")


if __name__ == "__main__":
    main()
