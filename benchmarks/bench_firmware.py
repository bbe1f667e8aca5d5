"""The firmware core's control step (controllers/firmware) for six hinges, ns per tick.

1. C alone: a driver built with the core (-O2) runs vrs_tick on a moving plant in batches of
   ticks; the median and p99 of the batches' ns per tick, telemetry off and at 500 Hz.
2. Called from numba's nopython code by address, as the twin's loop calls it.

    .venv/bin/python benchmarks/bench_firmware.py
"""

from __future__ import annotations

import argparse
import platform
import subprocess
import sys
import time
from pathlib import Path

import numba
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from controllers import core  # noqa: E402
from controllers.pid import PidGains  # noqa: E402
from twin.device.spec import load_spec  # noqa: E402

DRIVER = Path(__file__).resolve().parent / "firmware_tick.c"


def c_alone(batches: int, per: int, telemetry_hz: int) -> dict:
    exe = core.build((*core.WARNINGS, "-O2"), [DRIVER], name="firmware_tick", suffix="")
    out = subprocess.run([str(exe), str(batches), str(per), str(telemetry_hz)], capture_output=True, text=True,
                         check=True).stdout
    ns = np.array([float(x) for x in out.split()])
    return {"median_ns": round(float(np.median(ns)), 1), "p99_ns": round(float(np.percentile(ns, 99)), 1)}


@numba.njit
def _run_c(tick, address, counts, duty, decay, n_ticks, start_us):
    pos = counts.astype(np.float64)
    for k in range(n_ticks):
        tick(address, start_us + k * 1000, counts.ctypes.data, 0, duty.ctypes.data, decay.ctypes.data)
        for i in range(6):
            pos[i] += duty[i] * 5.0
            counts[i] = int(pos[i])


def from_numba(n_ticks: int, repeats: int) -> dict:
    spec = load_spec()
    lib = core.library()
    cfg = core.config_from_spec(spec)
    cfg.watchdog_ms = 0
    c = core.Core(cfg, [PidGains.from_spec(spec)] * 6, [0] * 6)
    c.set_targets([300, 200, 100, 0, -100, -200], 0)
    counts, duty, decay = np.zeros(8, np.int32), np.zeros(8, np.float32), np.zeros(8, np.uint8)
    _run_c(lib.vrs_tick, c.address, counts, duty, decay, 10, 0)
    times = []
    for r in range(repeats):
        t = time.perf_counter()
        _run_c(lib.vrs_tick, c.address, counts, duty, decay, n_ticks, (r + 1) * n_ticks * 1000)
        times.append((time.perf_counter() - t) / n_ticks * 1e9)
    return {"c_step_from_numba_ns": round(float(np.median(times)), 1)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batches", type=int, default=400, help="batches of ticks for the C driver (default 400)")
    p.add_argument("--per-batch", type=int, default=1000, help="ticks per batch (default 1000)")
    p.add_argument("--repeats", type=int, default=20, help="repeats of the run from numba (default 20)")
    args = p.parse_args(argv)
    print("command:", " ".join([Path(sys.executable).name, *sys.argv]))
    print("machine:", platform.machine(), platform.processor() or "", "| compiler:", core.compiler())
    for hz in (0, 500):
        print(f"C vrs_tick, 6 hinges, telemetry {hz} Hz:", c_alone(args.batches, args.per_batch, hz))
    print("from numba, 6 hinges, telemetry off:", from_numba(100_000, args.repeats))
    return 0


if __name__ == "__main__":
    sys.exit(main())
