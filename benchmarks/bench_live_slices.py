"""The live service's short scheduler slices (twin/live/scheduling.py) on and off, alternating on one service.

    .venv/bin/python benchmarks/bench_live_slices.py [--phases 6] [--seconds 5.5] [--worker] [--client] [--keep-pens]
        [--spin-us US]

One emulator, one `vrscroll serve --serial` on it, one client (benchmarks/bench_live.py's): a lock, then phases of
pens at 360 Hz with poses at 90 Hz beside, the pen process on the kernel's default slice in the even phases and on
its shortest (it asks for it as it starts; this sets it back and forth from outside) in the odd ones; --worker: the
worker too (it keeps the default: the cost shows in the pose), --client: this client too; --keep-pens: the pen
process keeps its short slice throughout (with --client: the client's slice alone alternates); --spin-us: in the odd
phases this client also polls its socket for each pen's reply for at most that long (LiveClient.spin) before it
waits in its event loop. Alternating phases of one service under the same load are the fairest
comparison this shared machine allows: before-and-after runs of two services differ by the load between them more
than by the change. Per phase: the pen's and the pose's round trips (p50 / p99 ms), the pen process's own path,
and each process's wait for a core per wake-up (schedstat).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_live import breakdown, hover, load, p50_p99, processes, schedstat, waits  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402
from twin.device.spec import load_spec  # noqa: E402
from twin.formats.target import message_approximation  # noqa: E402
from twin.link.emulator_process import EmulatorProcess  # noqa: E402
from twin.live.client import LiveClient, latency  # noqa: E402
from twin.live.collection import collect_if_due, hold_collection, release_collection  # noqa: E402
from twin.live.player import PEN_HZ, POSE_HZ, stroke  # noqa: E402
from twin.live.process import ServiceProcess  # noqa: E402
from twin.live.scheduling import SLICE_S, ask_short_slice, slice_s  # noqa: E402
from twin.morphpatch.approximation import pose_from_mm_deg  # noqa: E402
from twin.morphpatch.shapes import shape_table  # noqa: E402


async def alternate(url: str, find_pids, phases: int, seconds: float, shaped: list[str], spin_s: float = 0.0) -> None:
    """Lock, then `phases` phases of pens and poses, the processes named in `shaped` (of find_pids()'s, found once
    the service has its target: its children named) on short slices in the odd ones, and the client polling for
    each pen's reply for at most spin_s s in the odd ones."""
    spec = load_spec()
    start = pose_from_mm_deg(shape_table()["cylinder"]["start"])
    quat = Rotation.from_matrix(start[:3, :3]).as_quat(scalar_first=True)
    async with LiveClient(url) as client:
        await client.set_target(shape="cylinder")
        pids = find_pids()
        if "pens" not in pids:
            raise SystemExit("this service has no pen process")
        default_s = slice_s(pids["emulator"])  # a process that asked for nothing: the kernel's default
        for k in range(45):
            client.send_pose(*hover(start, quat, k / POSE_HZ))
            await asyncio.sleep(1 / POSE_HZ)
        locked = await client.lock()
        done = await client.expect("done", "refused", "stopped", timeout=15)
        if done["type"] != "done":
            raise SystemExit(f"the lock ended {done['type']}: {done['message']}")
        approx = message_approximation(locked, spec, "locked")
        points, quats = stroke(spec, approx.root_pose, np.radians(done["angles_deg"]), approx.widths)
        for phase in range(phases):
            short = phase % 2 == 1
            for name in shaped:
                if not ask_short_slice(SLICE_S if short else default_s, pids[name]):
                    raise SystemExit(f"{name}: the kernel took no slice request (Linux 6.12 or later needed)")
            for kind in ("pen_redirected", "approximation", "estimates"):
                client.drain(kind)
            hold_collection()
            ran = {name: schedstat(pid) for name, pid in pids.items()}
            loaded, pens, t0 = os.getloadavg()[0], 0, time.perf_counter()
            while (t := time.perf_counter() - t0) < seconds:
                collect_if_due()
                client.send_pen(points[pens % len(points)] * 1e3, quats[pens % len(points)])
                pens += 1
                if pens % round(PEN_HZ / POSE_HZ) == 0:
                    client.send_pose(*hover(start, quat, t))
                if short and spin_s:
                    client.spin("pen_redirected", spin_s)
                await asyncio.sleep(max(0.0, t0 + pens / PEN_HZ - time.perf_counter()))
            await asyncio.sleep(0.2)
            release_collection()
            line, _ = waits(ran, {name: schedstat(pid) for name, pid in pids.items()}, seconds, pens)
            status = await client.status()
            replies = client.drain("pen_redirected")
            pen = [latency(r) for r in replies]
            wake = [r["received_s"] - r["arrived_s"] for r in replies]
            pose = [latency(r) for r in client.drain("approximation")]
            print(f"phase {phase + 1}, {'short slices' if short else 'default slices'} ({', '.join(shaped) or 'none'}"
                  f"{f', spin {spin_s * 1e6:.0f} us' if short and spin_s else ''}), load "
                  f"{loaded:.2f}: pen {p50_p99(pen)} ms ({len(pen)} of {pens}), of which the client's wake-up "
                  f"{p50_p99(wake)} ms, pose {p50_p99(pose)} ms; "
                  + breakdown("the pen process's path", status["pen_path_ms"]), flush=True)
            print(f"  waiting for a core: {line}", flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--phases", type=int, default=6, help="phases, default then short slices in turn (default 6)")
    p.add_argument("--seconds", type=float, default=5.5, help="length of each phase (default 5.5)")
    p.add_argument("--worker", action="store_true", help="the worker on short slices too in the odd phases")
    p.add_argument("--client", action="store_true", help="this client on short slices too in the odd phases")
    p.add_argument("--keep-pens", action="store_true", help="the pen process on its short slice in every phase")
    p.add_argument("--spin-us", type=float, default=0.0, metavar="US",
                   help="in the odd phases the client polls for each pen's reply for at most this long (default 0)")
    args = p.parse_args()
    if args.phases < 2 or args.seconds <= 0:
        p.error("--phases must be at least 2 and --seconds positive")
    print(load())
    with tempfile.TemporaryDirectory() as tmp, EmulatorProcess(Path(tmp) / "emulator.jsonl", "--zeroed") as emu, \
            ServiceProcess("--serial", emu.port, "--log", str(Path(tmp) / "session.jsonl"),
                           stderr_path=Path(tmp) / "serve.err") as service:
        shaped = ([] if args.keep_pens else ["pens"]) + (["worker"] if args.worker else []) + \
            (["client"] if args.client else [])
        asyncio.run(alternate(service.url, lambda: processes(service, emu.proc.pid), args.phases, args.seconds, shaped,
                              args.spin_us * 1e-6))
    print(load())


if __name__ == "__main__":
    main()
