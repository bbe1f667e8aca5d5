"""The emulator under a flood of bytes (issue 40, item 5): does it keep answering, and at what cost?

For each kind of flood (and none, the baseline), --rate bytes/s (default 1 MB/s) written onto the emulator's pty for --seconds while
the same host asks GET_STATE every 20 ms: the answer times (median, p99, max, ms; timeouts), the emulator
process's CPU (share of one core, from /proc), its real-time overruns and the bad frames its core counted.
(That no flood feeds the watchdog is a test: tests/firmware/test_estop_always_runs.py.)

    .venv/bin/python benchmarks/bench_emulator_flood.py --seconds 10
"""

from __future__ import annotations

import argparse
import json
import os
import struct
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from twin.link import protocol as P  # noqa: E402
from twin.link.emulator_process import EmulatorProcess  # noqa: E402
from twin.link.serial_link import Link  # noqa: E402


def _other_version(n: int) -> bytes:
    """Intact frames of protocol version 2 (SET_TARGETS): each answered with a NACK, none feeding the watchdog."""
    payload = struct.pack("<BBH", P.PROTOCOL_VERSION - 1, P.MsgId.SET_TARGETS, 1) + bytes([6]) + b"\x01" * 24
    frame = P.cobs_encode(payload + struct.pack("<H", P.crc16(payload))) + b"\x00"
    return frame * (n // len(frame) + 1)


FLOODS = {
    "none": None,  # the baseline: the same questions, no flood
    "random": lambda rng, n: rng.integers(0, 256, n, dtype=np.uint8).tobytes(),  # a 0x00 every 256 bytes
    "no-delimiter": lambda rng, n: rng.integers(1, 256, n, dtype=np.uint8).tobytes(),  # one endless frame
    "other-version": lambda rng, n: _other_version(n),
}


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def flood(kind: str, rate: float, seconds: float, folder: Path) -> dict:
    emu = EmulatorProcess(folder / f"{kind}.jsonl", "--zeroed", "--ideal")
    try:
        with Link(emu.port, heartbeat=None, timeout=0.1, retries=0) as link:
            rng = np.random.default_rng(0)
            chunk = max(1, int(rate / 1000))
            data = FLOODS[kind](rng, chunk * 1000) if FLOODS[kind] else b""
            stop = threading.Event()
            sent = [0]

            def write():
                start, k = time.monotonic(), 0
                while not stop.is_set():
                    part = data[(k * chunk) % (len(data) - chunk):][:chunk]
                    link._write(b"\x00" + part)  # noqa: SLF001  a flood, as a raw line would carry it
                    sent[0] += len(part) + 1
                    k += 1
                    time.sleep(max(0.0, start + k / 1000 - time.monotonic()))

            cpu0, t0 = cpu_seconds(emu.proc.pid), time.monotonic()
            flooder = threading.Thread(target=write, daemon=True)
            if data:
                flooder.start()
            lat, timeouts = [], 0
            while time.monotonic() - t0 < seconds:
                t = time.perf_counter()
                try:
                    link.get_state()
                    lat.append(time.perf_counter() - t)
                except Exception:  # a LinkTimeout: counted
                    timeouts += 1
                time.sleep(0.02)
            stop.set()
            if data:
                flooder.join()
            wall = time.monotonic() - t0
            cpu = (cpu_seconds(emu.proc.pid) - cpu0) / wall
            time.sleep(0.5)  # the backlog drained
            bad = link.request(P.GetState(), timeout=1.0, retries=3).rx_bad_frames
    finally:
        emu.stop()
    ms = np.asarray(lat) * 1000 if lat else np.array([np.nan])
    stats = next((e for e in emu.events("stop")), {})
    return {"flood": kind, "sent_bytes_per_s": round(sent[0] / wall), "answers": len(lat), "timeouts": timeouts,
            "median_ms": round(float(np.median(ms)), 2), "p99_ms": round(float(np.percentile(ms, 99)), 2),
            "max_ms": round(float(ms.max()), 2), "emulator_cpu_share": round(cpu, 3),
            "overruns": stats.get("overruns"), "rx_bad_frames": bad}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=float, default=1e6, help="bytes/s of flood (default 1e6)")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--floods", default=",".join(FLOODS), help="which (default all)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        for kind in args.floods.split(","):
            print(json.dumps(flood(kind, args.rate, args.seconds, Path(d))), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
