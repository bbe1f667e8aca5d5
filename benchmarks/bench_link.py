"""Link benchmark against the device emulator on a real pty.

1. Command round trip: GET_STATE -> STATE, timed on the host (median, p99, max, ms),
   with telemetry off and again with telemetry streaming at 500 Hz. Goal: p99 < 5 ms.
2. Telemetry at 500 Hz for --seconds (default 60): frames received, frames lost
   (gaps in the device's telemetry sequence numbers), device-side drops and the
   emulator's real-time overruns.

    .venv/bin/python benchmarks/bench_link.py --seconds 60
    .venv/bin/python benchmarks/bench_link.py --serial /dev/ttyACM0   # a real device
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from twin.link.emulator_process import EmulatorProcess  # noqa: E402
from twin.link.serial_link import Link  # noqa: E402


def round_trips(link: Link, n: int) -> dict:
    lat = []
    for _ in range(n):
        t = time.perf_counter()
        link.get_state()
        lat.append(time.perf_counter() - t)
    ms = np.asarray(lat) * 1000
    return {"n": n, "median_ms": round(float(np.median(ms)), 3), "p99_ms": round(float(np.percentile(ms, 99)), 3),
            "max_ms": round(float(ms.max()), 3)}


def telemetry(link: Link, rate: int, seconds: float) -> dict:
    link.set_telemetry_rate(rate)
    link.drain_telemetry()
    lost0, recv0 = link.telemetry_lost, link.telemetry_received
    first = last = None
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        item = link.telemetry(timeout=1.0)
        if item is None:
            continue
        first = first or item[1]
        last = item[1]
    link.set_telemetry_rate(0)
    received = link.telemetry_received - recv0
    span = ((last.time_us - first.time_us) & 0xFFFFFFFF) / 1e6 if first else 0.0
    return {"rate_hz": rate, "seconds": seconds, "received": received, "lost": link.telemetry_lost - lost0,
            "expected_from_device_time": int(round(span * rate)) + 1,
            "achieved_hz": round(received / seconds, 1)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--serial", help="a device or pty to use instead of starting the emulator")
    p.add_argument("--seconds", type=float, default=60.0, help="telemetry run length, s (default %(default)s)")
    p.add_argument("--requests", type=int, default=2000, help="round trips per phase (default %(default)s)")
    p.add_argument("--rate", type=int, default=500, help="telemetry rate, Hz (default %(default)s)")
    p.add_argument("--log", help="session log (off by default: it measures the link, not the disk)")
    args = p.parse_args(argv)
    tmp = tempfile.TemporaryDirectory()
    emu = None if args.serial else EmulatorProcess(Path(tmp.name) / "emulator.jsonl", "--zeroed")
    port = args.serial or emu.port
    out = {"port": port}
    try:
        with Link(port, log_path=args.log) as link:
            link.set_telemetry_rate(0)
            out["round_trip_quiet"] = round_trips(link, args.requests)
            link.set_telemetry_rate(args.rate)
            out["round_trip_with_telemetry"] = round_trips(link, args.requests)
            out["telemetry"] = telemetry(link, args.rate, args.seconds)
            out["host_bad_frames"] = link.decoder.bad_frames
    finally:
        if emu:
            emu.stop()
            stop = emu.events("stop")
            if stop:
                out["emulator"] = {k: stop[-1][k] for k in ("ticks", "overruns", "rx_bad_frames", "telemetry_dropped")}
    print(json.dumps(out, indent=2))
    ok = out["round_trip_quiet"]["p99_ms"] < 5 and out["telemetry"]["lost"] == 0
    print("goal p99 < 5 ms and no telemetry lost:", "met" if ok else "NOT met")
    return 0


if __name__ == "__main__":
    sys.exit(main())
