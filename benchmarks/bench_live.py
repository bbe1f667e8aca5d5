"""The live service's latencies on loopback, with the emulator as the device.

    .venv/bin/python benchmarks/bench_live.py [--seconds 10] [--shape cylinder] [--variant full]

Starts an emulator and `vrscroll serve --serial` on it (each its own process), then, as one
client (twin/live/client.py):

1. poses at 90 Hz for --seconds, the device hovering over the shape's start (±10 mm at 0.5 Hz,
   the player's tremor): pose -> approximation round trip, p50 and p99 (goal p99 <= 11.1 ms,
   one VR frame);
2. lock, morph on the emulator;
3. pen samples at 360 Hz (the player's stroke, back and forth over the device) with the poses
   still at 90 Hz, so approximations run meanwhile: pen -> redirected pen round trip, p50 and
   p99 (goal p99 <= 2.78 ms, one 360 Hz sample), and the approximations' round trip again.

Round trips are measured by the client (its clock in t_s, echoed by the service). Counted:
samples that got no reply (dropped by the network or superseded by a newer pose: the newest
wins), and the service's own counts of stale, superseded and missing samples. The machine's
load (uptime) is printed before and after: the figures depend on it.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from twin.device.spec import load_spec  # noqa: E402
from twin.link.emulator_process import EmulatorProcess  # noqa: E402
from twin.live.client import LiveClient, latency  # noqa: E402
from twin.live.player import POSE_HZ, PEN_HZ, TREMOR, stroke  # noqa: E402
from twin.live.process import ServiceProcess  # noqa: E402
from twin.morphpatch.approximation import Approximation, pose_from_mm_deg  # noqa: E402
from twin.morphpatch.shapes import shape_table  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

HOVER = 0.01  # m, amplitude of the hover
HOVER_HZ = 0.5


def load() -> str:
    return "load average " + ", ".join(f"{v:.2f}" for v in os.getloadavg()) + f" ({os.cpu_count()} cores)"


def hover(start: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Position mm and quaternion of the hovering device at time t s."""
    rot = start[:3, :3]
    p = start[:3, 3] + HOVER * math.sin(2 * math.pi * HOVER_HZ * t) * rot[:, 0] \
        + TREMOR * (math.sin(2 * math.pi * 5 * t) * rot[:, 1] + math.sin(2 * math.pi * 7 * t) * rot[:, 2])
    return p * 1e3, Rotation.from_matrix(rot).as_quat(scalar_first=True)


def stats(name: str, values, sent: int, goal_ms: float | None = None) -> str:
    v = np.asarray(values) * 1e3
    if not len(v):
        return f"{name}: no replies of {sent}"
    text = (f"{name}: p50 {np.percentile(v, 50):.3f} ms, p99 {np.percentile(v, 99):.3f} ms, max {v.max():.3f} ms "
            f"over {len(v)} replies; {sent - len(v)} of {sent} samples got none")
    return text + (f" (goal p99 <= {goal_ms} ms: {'met' if np.percentile(v, 99) <= goal_ms else 'NOT met'})"
                   if goal_ms else "")


async def bench(url: str, shape: str, seconds: float) -> None:
    spec = load_spec()
    start = pose_from_mm_deg(shape_table()[shape]["start"])
    async with LiveClient(url) as client:
        await client.set_target(shape=shape)
        for k in range(45):  # settle: half a second of poses, not measured
            client.send_pose(*hover(start, k / POSE_HZ))
            await asyncio.sleep(1 / POSE_HZ)
        await asyncio.sleep(0.1)
        client.drain("approximation")

        sent, t0 = 0, time.perf_counter()
        while (t := time.perf_counter() - t0) < seconds:
            client.send_pose(*hover(start, t))
            sent += 1
            await asyncio.sleep(max(0.0, t0 + sent / POSE_HZ - time.perf_counter()))
        await asyncio.sleep(0.2)
        replies = client.drain("approximation")
        print(stats("pose -> approximation at 90 Hz", [latency(a) for a in replies], sent, 11.1))
        print(stats("  of which the approximation itself (worker)", [a["time_ms"] / 1e3 for a in replies], len(replies)))

        locked = await client.lock()
        done = await client.expect("done", "refused", "stopped", timeout=15)
        print(f"lock: {done['type']} ({done['message']})")
        if done["type"] != "done":
            return
        approx = Approximation.from_json(locked)
        points, quats = stroke(spec, approx.root_pose, np.radians(done["angles_deg"]), approx.widths)
        order = np.r_[np.arange(len(points)), np.arange(len(points))[::-1]]
        pens = poses = 0
        t0 = time.perf_counter()
        while (t := time.perf_counter() - t0) < seconds:
            k = order[pens % len(order)]
            client.send_pen(points[k] * 1e3, quats[k])
            pens += 1
            if pens % round(PEN_HZ / POSE_HZ) == 0:
                client.send_pose(*hover(start, t))
                poses += 1
            await asyncio.sleep(max(0.0, t0 + pens / PEN_HZ - time.perf_counter()))
        await asyncio.sleep(0.2)
        print(stats("pen -> redirected pen at 360 Hz, approximations running",
                    [latency(r) for r in client.drain("pen_redirected")], pens, 2.78))
        print(stats("pose -> approximation at 90 Hz meanwhile", [latency(a) for a in client.drain("approximation")],
                    poses))
        status = await client.status()
        counts = status["counts"]
        print("service counts: " + ", ".join(f"{k} {counts.get(k, 0)}" for k in
                                             ("pose", "approximations", "superseded", "stale", "missing", "pen",
                                              "pen_redirected")))
        print(f"service side (arrival -> reply sent): approximation {status['approximation_latency_ms']}, "
              f"pen {status['pen_latency_ms']} ms")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=10.0, help="length of each measured phase (default 10)")
    p.add_argument("--shape", default="cylinder", choices=list(shape_table()))
    p.add_argument("--variant", default="full")
    args = p.parse_args()
    print(load())
    with tempfile.TemporaryDirectory() as tmp, EmulatorProcess(Path(tmp) / "emulator.jsonl", "--zeroed") as emu, \
            ServiceProcess("--serial", emu.port, "--variant", args.variant, "--log", str(Path(tmp) / "session.jsonl"),
                           stderr_path=Path(tmp) / "serve.err") as service:
        print(service.banner.strip())
        asyncio.run(bench(service.url, args.shape, args.seconds))
    print(load())


if __name__ == "__main__":
    main()
