"""The live service's latencies on loopback, with the emulator as the device, and where the time goes.

    .venv/bin/python benchmarks/bench_live.py [--seconds 10] [--shape cylinder] [--variant full]
    .venv/bin/python benchmarks/bench_live.py --against OLD_TREE [--rounds 3] [--seconds 5]

Starts an emulator and `vrscroll serve --serial` on it (each its own process), then, as one
client (twin/live/client.py):

1. poses at 90 Hz for --seconds, the device hovering over the shape's start (±10 mm at 0.5 Hz,
   the player's tremor): pose -> approximation round trip, p50 and p99 (goal p99 <= 3 ms);
2. lock, morph on the emulator;
3. pen samples at 360 Hz (the player's stroke, back and forth over the device) with the poses
   still at 90 Hz, so approximations run meanwhile: pen -> redirected pen round trip, p50 and
   p99 (goal p99 <= 0.5 ms), and the approximations' round trip again.

The last lines before the closing load say both goals at once ("GOALS ...": each p99, met or NOT met, the
scheduler and the load; with --against one line per side, pooled over the rounds; the C# client's worst round).

Round trips are measured by the client (its clock in t_s, echoed by the service). Counted:
samples that got no reply (dropped by the network or superseded by a newer pose: the newest
wins), and the service's own counts of stale, superseded and missing samples. Where the time
went: the service's per-stage breakdown (its `status`: pose_path_ms, pen_path_ms) and the
client's own send and receive. The machine's load (uptime) is printed before and after: the
figures depend on it. This client collects its garbage before each send (twin/live/collection.py),
so its own collector's pauses (a millisecond or two each, in this process of many objects) do not
land inside the round trips it times.

--against OLD_TREE: the same measurement, alternating this code's service with the service of
another checkout (a folder holding its `twin` package, e.g. `git worktree add /tmp/old HEAD~3`)
round by round (order swapped every round), each on a fresh emulator, with the same client (saying
each side's protocol version): the before and after under the same load. Pooled p50 and p99 per
side, and per round.

CPU: per phase, each process's CPU time (schedstat) per sample sent; the worker's per pose (poses alone) and the
pen process's per pen sample (an older service's own: pens at 360 Hz, poses at 90 Hz beside) are pooled per side
(the median of the rounds) with --against.

--fifo PRIORITY: the processes on the samples' way (this client, the service, its worker and pen process; the C#
client with `chrt`) run under SCHED_FIFO at that priority (the worker one below) while they are measured (Linux;
needs CAP_SYS_NICE): a wake-up then takes a core from any ordinary process at once, which on a shared machine is
what a core of their own would give. Each of them sleeps between samples (no busy wait), so together they take what they
took before, ~10-30 % of a core.

Where a pen's round trip went (the `pen split` line): to the reply's arrival in the client's socket (the kernel's
stamp: the client's send, the pen process's wake-up and path, the reply's way back), then the client's wake-up, and
the round trips of the pens that had a pose sent right after them. --spin-us and --client-slice change this code's
side's client only (the other side's waits as main's bench did): it polls its socket for each reply for at most that
long (LiveClient.spin) / its thread asks for the kernel's shortest slice (LiveClient(short_slice=True)); docs/live.md,
"The clients' waits", says what each did.

--csharp: after the Python client, the C# client (clients/unity, compiled here with Mono's mcs;
with --against, each side's own, as each speaks its own protocol version) plays a session on the
same service and streams pens at ~360 Hz with poses for --seconds, measuring the round trips on its
own clock (clients/unity/tests/ScriptedSession.cs).
"""

from __future__ import annotations

import argparse
import asyncio
import math
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from twin.device.spec import load_spec  # noqa: E402
from twin.link.emulator_process import EmulatorProcess  # noqa: E402
from twin.live.client import LiveClient, latency  # noqa: E402
from twin.live.collection import collect_if_due, hold_collection, release_collection  # noqa: E402
from twin.live.messages import PROTOCOL_VERSION  # noqa: E402
from twin.live.player import POSE_HZ, PEN_HZ, TREMOR, stroke  # noqa: E402
from twin.live.process import ServiceProcess  # noqa: E402
from twin.live.scheduling import ask_thread_slice, slice_s  # noqa: E402
from twin.formats.target import message_approximation  # noqa: E402
from twin.morphpatch.approximation import pose_from_mm_deg  # noqa: E402
from twin.morphpatch.shapes import shape_table  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

HOVER = 0.01  # m, amplitude of the hover
HOVER_HZ = 0.5
POSE_GOAL_MS = 3.0  # issue 40: pose -> approximation p99, end to end on loopback
PEN_GOAL_MS = 0.5  # pen -> redirected pen p99


def load() -> str:
    return "load average " + ", ".join(f"{v:.2f}" for v in os.getloadavg()) + f" ({os.cpu_count()} cores)"


def schedstat(pid: int) -> np.ndarray:
    """(on a core, waiting for one, s; times put on a core) summed over the process's threads: Linux's
    /proc/PID/task/TID/schedstat (zeros for a process that has gone)."""
    total = np.zeros(3)
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            total += np.array((task / "schedstat").read_text().split(), float)
        except (OSError, ValueError):
            pass
    return total * [1e-9, 1e-9, 1]


def processes(service: ServiceProcess, emulator_pid: int) -> dict:
    """{name: pid} of the processes on a sample's way: this client, the service, its worker, its pen process (a
    service that has one), the emulator. The service's children are told apart by their names (twin/live/child.py);
    an older service's one unnamed child is its worker."""
    found = {}
    for pid in Path(f"/proc/{service.pid}/task/{service.pid}/children").read_text().split():
        name = {"vrscroll-worker": "worker", "vrscroll-pens": "pens"}.get(Path(f"/proc/{pid}/comm").read_text().strip())
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
        if name is None and b"spawn_main" in cmdline and b"resource_tracker" not in cmdline:
            name = "worker"
        if name:
            found.setdefault(name, int(pid))
    return {"client": os.getpid(), "service": service.pid, **found, "emulator": emulator_pid}


def prioritise(pids, priority: int) -> None:
    """Every thread of each process under SCHED_FIFO at `priority` (0: the ordinary scheduler again)."""
    policy = os.SCHED_FIFO if priority else os.SCHED_OTHER
    for pid in pids:
        for task in Path(f"/proc/{pid}/task").glob("*"):
            try:
                os.sched_setscheduler(int(task.name), policy, os.sched_param(priority))
            except ProcessLookupError:  # a thread that has ended
                pass


def waits(before: dict, after: dict, seconds: float, samples: int) -> tuple[str, dict]:
    """Per process, between two {name: schedstat} snapshots: its share of a core, its CPU per sample sent (us), and
    the time it spent runnable but waiting for a core (ms per second of wall clock, and per time it was put on one,
    us); and {name: CPU per sample sent, us}."""
    parts, cpu = [], {}
    for name in after:
        run, wait, slices = after[name] - before[name]
        cpu[name] = run / max(samples, 1) * 1e6
        parts.append(f"{name} ran {run / seconds:.0%} of a core ({cpu[name]:.0f} us CPU per sample), waited "
                     f"{wait / seconds * 1e3:.1f} ms/s ({wait / max(slices, 1) * 1e6:.0f} us per wake-up)")
    return "; ".join(parts), cpu


def hover(start: np.ndarray, quat: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Position mm and quaternion of the device hovering over `start` (4x4; quat: its rotation's, w first, made once:
    scipy's conversion is ~60 us on a warm core, which this client spent after every fourth pen it timed) at time t
    s."""
    rot = start[:3, :3]
    p = start[:3, 3] + HOVER * math.sin(2 * math.pi * HOVER_HZ * t) * rot[:, 0] \
        + TREMOR * (math.sin(2 * math.pi * 5 * t) * rot[:, 1] + math.sin(2 * math.pi * 7 * t) * rot[:, 2])
    return p * 1e3, quat


def stats(name: str, values, sent: int, goal_ms: float | None = None) -> str:
    v = np.asarray(values) * 1e3
    if not len(v):
        return f"{name}: no replies of {sent}"
    text = (f"{name}: p50 {np.percentile(v, 50):.3f} ms, p99 {np.percentile(v, 99):.3f} ms, max {v.max():.3f} ms "
            f"over {len(v)} replies; {sent - len(v)} of {sent} samples got none")
    return text + (f" (goal p99 <= {goal_ms} ms: {'met' if np.percentile(v, 99) <= goal_ms else 'NOT met'})"
                   if goal_ms else "")


def breakdown(name: str, stages: dict | None) -> str:
    """One line of a status's per-stage p50/p99 (ms)."""
    if not stages:
        return f"{name}: not reported by this service"
    return f"{name} (p50/p99 ms): " + ", ".join(f"{k} {v['p50']:.3f}/{v['p99']:.3f}" for k, v in stages.items() if v)


async def measure(url: str, shape: str, seconds: float, protocol: int = PROTOCOL_VERSION,
                  pids=lambda: {}, fifo: int = 0, spin_s: float = 0.0, short_slice: bool = False) -> dict:
    """One session (saying `protocol` in hello: an older service's): {"pose", "estimates", "worker", "pen",
    "pose_with_pens", "client_send", "client_receive": [s], "sent": {phase: samples sent}, "status": the
    service's status at the end (None if the lock failed), "waits": {phase: `waits` of the processes pids()},
    "cpu_us": {"worker per pose": its CPU per pose, poses alone; "pens per pen": the CPU per pen sample of the
    process that serves the pens (the pen process; an older service itself), pens
    and poses}}.
    fifo: the SCHED_FIFO priority of those processes while measured (0: none); spin_s: after each sample sent, the
    client polls its socket for the reply for at most this long (LiveClient.spin; 0: it waits in its event loop);
    short_slice: this client's thread on the kernel's shortest slice while measured (LiveClient's short_slice).
    "pen_to_socket", "pen_wake": per pen reply, s from its t_s to the reply's arrival in the client's socket (the
    client's send, the pen process's wake-up and work, the reply's way back) and from there to the client taking it
    (the client's wake-up)."""
    out = {"sent": {}, "status": None, "waits": {}, "cpu_us": {}}
    default_slice = slice_s()
    try:
        return await _measure(url, shape, seconds, protocol, pids, fifo, spin_s, short_slice, out)
    finally:
        if short_slice and default_slice:
            ask_thread_slice(default_slice)  # the other side's session on the kernel's default again


async def _measure(url, shape, seconds, protocol, pids, fifo, spin_s, short_slice, out) -> dict:
    start = pose_from_mm_deg(shape_table()[shape]["start"])
    quat = Rotation.from_matrix(start[:3, :3]).as_quat(scalar_first=True)
    async with LiveClient(url, protocol=protocol, short_slice=short_slice) as client:
        await client.set_target(shape=shape)
        processes = pids()
        # under SCHED_FIFO from the settling on: the service's per-stage figures (its last 2,000 samples) are all so
        # the worker one step below the rest: a pen wakes its process and preempts an approximation (at one priority
        # SCHED_FIFO never preempts, and the worker's 1-2 ms held a core from the pens: docs/live.md, "Measured")
        prioritise([pid for name, pid in processes.items() if name not in ("emulator", "worker")], fifo)
        prioritise([processes["worker"]], max(fifo - 1, 1) if fifo else 0)
        for k in range(45):  # settle: half a second of poses, not measured
            client.send_pose(*hover(start, quat, k / POSE_HZ))
            await asyncio.sleep(1 / POSE_HZ)
        await asyncio.sleep(0.1)
        client.drain("approximation")
        client.drain("estimates")

        hold_collection()  # this client's garbage collected before each send, not amid a round trip it times
        ran = {name: schedstat(pid) for name, pid in processes.items()}
        sent, t0 = 0, time.perf_counter()
        while (t := time.perf_counter() - t0) < seconds:
            collect_if_due()
            client.send_pose(*hover(start, quat, t))
            sent += 1
            await asyncio.sleep(max(0.0, t0 + sent / POSE_HZ - time.perf_counter()))
        await asyncio.sleep(0.2)
        replies = client.drain("approximation")
        out["pose"] = [latency(a) for a in replies]
        out["worker"] = [a["time_ms"] / 1e3 for a in replies]
        out["estimates"] = [latency(e) for e in client.drain("estimates")]  # none from a protocol-1 service
        out["sent"]["pose"] = sent
        out["waits"]["poses"], cpu = waits(ran, {name: schedstat(pid) for name, pid in processes.items()},
                                           time.perf_counter() - t0, sent)
        out["cpu_us"]["worker per pose"] = cpu.get("worker")

        release_collection()
        locked = await client.lock()
        done = await client.expect("done", "refused", "stopped", timeout=15)
        out["lock"] = f"{done['type']} ({done['message']})"
        if done["type"] != "done":
            return out
        hold_collection()
        ran = {name: schedstat(pid) for name, pid in processes.items()}
        approx = message_approximation(locked, load_spec(), "locked")
        points, quats = stroke(load_spec(), approx.root_pose, np.radians(done["angles_deg"]), approx.widths)
        order = np.r_[np.arange(len(points)), np.arange(len(points))[::-1]]
        pens = poses = 0
        t0 = time.perf_counter()
        while (t := time.perf_counter() - t0) < seconds:
            k = order[pens % len(order)]
            collect_if_due()
            client.send_pen(points[k] * 1e3, quats[k])
            pens += 1
            if pens % round(PEN_HZ / POSE_HZ) == 0:
                client.send_pose(*hover(start, quat, t))
                poses += 1
            if spin_s:
                client.spin("pen_redirected", spin_s)
            await asyncio.sleep(max(0.0, t0 + pens / PEN_HZ - time.perf_counter()))
        await asyncio.sleep(0.2)
        release_collection()
        out["waits"]["pens and poses"], cpu = waits(ran, {name: schedstat(pid) for name, pid in processes.items()},
                                                    time.perf_counter() - t0, pens)
        out["cpu_us"]["pens per pen"] = cpu.get("pens", cpu.get("service"))
        pen_replies = client.drain("pen_redirected")
        out["pen"] = [latency(r) for r in pen_replies]
        out["pen_to_socket"] = [r["arrived_s"] - r["t_s"] for r in pen_replies]
        out["pen_wake"] = [r["received_s"] - r["arrived_s"] for r in pen_replies]
        per_pose = round(PEN_HZ / POSE_HZ)  # the pens with seq per_pose - 1, 2 per_pose - 1, ... have a pose after them
        out["pen_before_pose"] = [latency(r) for r in pen_replies if r["seq"] % per_pose == per_pose - 1]
        out["pose_with_pens"] = [latency(a) for a in client.drain("approximation")]
        out["sent"].update(pen=pens, pose_with_pens=poses)
        out["client_send"], out["client_receive"] = list(client.send_s), list(client.receive_s)
        out["status"] = await client.status()
    return out


def report(m: dict) -> None:
    print(stats("pose -> approximation at 90 Hz", m["pose"], m["sent"]["pose"], POSE_GOAL_MS))
    print(stats("  of which the approximation itself (worker)", m["worker"], len(m["worker"])))
    print(stats("pose -> its frame estimates (the datagram after the approximation's)", m["estimates"],
                m["sent"]["pose"]))
    print(f"lock: {m['lock']}")
    if m["status"] is None:
        return
    print(stats("pen -> redirected pen at 360 Hz, approximations running", m["pen"], m["sent"]["pen"], PEN_GOAL_MS))
    print(stats("pose -> approximation at 90 Hz meanwhile", m["pose_with_pens"], m["sent"]["pose_with_pens"],
                POSE_GOAL_MS))
    status = m["status"]
    counts = status["counts"]
    print("service counts: " + ", ".join(f"{k} {counts.get(k, 0)}" for k in
                                         ("pose", "approximations", "superseded", "stale", "missing", "pen",
                                          "pen_redirected")))
    print(f"service side (arrival -> reply sent): approximation {status['approximation_latency_ms']}, "
          f"pen {status['pen_latency_ms']} ms")
    print(breakdown("where a pose's time went in the service", status.get("pose_path_ms")))
    print(breakdown("a pose's CPU in the worker", status.get("pose_cpu_ms")))
    print(f"then, off the pose's path: frame estimates {status.get('estimates_ms')} ms after their "
          f"approximation's datagram, {counts.get('estimates', 'one per approximation')} of them, CPU "
          f"{status.get('estimates_cpu_ms')} ms each")
    print(breakdown("where a pen sample's time went in the service", status.get("pen_path_ms")))
    print(pen_split(m))
    print(stats("client: encoding and sending a sample", m["client_send"], len(m["client_send"])))
    print(stats("client: parsing and queueing a reply", m["client_receive"], len(m["client_receive"])))
    for phase, line in m["waits"].items():
        print(f"waiting for a core, {phase}: {line}")
    print("CPU: " + ", ".join(f"{k} {v:.0f} us" for k, v in m["cpu_us"].items() if v is not None))
    if "csharp" in m:
        print(csharp_line(m))


def pen_split(m: dict) -> str:
    """Where a pen's round trip went, p50 / p99 ms: to the reply's arrival in the client's socket, then the client's
    wake-up, beside the client's own send and the pen's way through the pen process (its status)."""
    path = (m["status"] or {}).get("pen_path_ms") or {}
    inside = path.get("total")
    return (f"pen split (p50 / p99 ms): t_s -> reply in the client's socket {p50_p99(m.get('pen_to_socket', []))} "
            f"[of which the client's send {p50_p99(m.get('client_send', []))}, the pen process's wake-up "
            f"{p50_p99_ms(path.get('socket'))}, its path {p50_p99_ms(inside)}]; the client's wake-up "
            f"{p50_p99(m.get('pen_wake', []))}; the pens with a pose sent right after them "
            f"{p50_p99(m.get('pen_before_pose', []))}")


def p50_p99_ms(stage: dict | None) -> str:
    return f"{stage['p50']:.3f} / {stage['p99']:.3f}" if stage else "-"


def protocol_of(code: Path | None) -> int:
    """The live protocol version the service in checkout `code` (None: this one) speaks."""
    if code is None:
        return PROTOCOL_VERSION
    return int(re.search(r"^PROTOCOL_VERSION = (\d+)", (code / "twin/live/messages.py").read_text(), re.M).group(1))


def session(args, code=None) -> dict:
    """One emulator and one service (this code's, or the checkout `code`'s: each version with its own device, whose
    protocol it speaks), one measured session; with
    args.csharp ({checkout or None: its compiled C# session}), then the C# client's too: m["csharp"]
    {"pose_ms", "pen_ms": [p50, p99, replies]}."""
    with tempfile.TemporaryDirectory() as tmp, \
            EmulatorProcess(Path(tmp) / "emulator.jsonl", "--zeroed", code=code) as emu, \
            ServiceProcess("--serial", emu.port, "--variant", args.variant, "--log", str(Path(tmp) / "session.jsonl"),
                           stderr_path=Path(tmp) / "serve.err", code=code) as service:
        m = asyncio.run(measure(service.url, args.shape, args.seconds, protocol_of(code),
                                lambda: processes(service, emu.proc.pid), args.fifo,
                                args.spin_us * 1e-6 if code is None else 0.0, code is None and args.client_slice))
        prioritise([os.getpid()], 0)  # this client back to the ordinary scheduler before it starts anything
        if args.csharp:
            fifo = ["chrt", "-f", str(args.fifo)] if args.fifo else []
            run = subprocess.run([*fifo, "mono", str(args.csharp[code]), service.url, args.shape, str(args.seconds)],
                                 capture_output=True, text=True, timeout=120 + 2 * args.seconds)
            seen = json.loads(run.stdout.strip().splitlines()[-1]) if run.returncode == 0 else {}
            m["csharp"] = {"pose_ms": seen.get("measure_pose_ms"), "pen_ms": seen.get("measure_pen_ms"),
                           "error": None if seen else error_text(run)}
        return m


def error_text(run: subprocess.CompletedProcess) -> str:
    """A failed C# run in a few lines: its exit status, the start and the end of what it said."""
    said = (run.stderr.strip() or run.stdout.strip())
    return f"exit {run.returncode}: " + (said if len(said) <= 700 else f"{said[:400]} ... {said[-300:]}")


def csharp_line(m: dict) -> str:
    c = m.get("csharp")
    if c is None:
        return ""
    if c["error"]:
        return f"C# client: failed: {c['error']}"
    (pose50, pose99, n_pose), (pen50, pen99, n_pen) = c["pose_ms"], c["pen_ms"]
    return (f"C# client: pose -> approximation p50 {pose50:.3f} / p99 {pose99:.3f} ms ({n_pose} replies), "
            f"pen -> redirected p50 {pen50:.3f} / p99 {pen99:.3f} ms ({n_pen} replies)")


def build_csharp(folder: Path, code: Path | None = None) -> Path:
    """The C# scripted session of checkout `code` (None: this one) compiled with Mono's mcs into folder; SystemExit
    naming what is missing."""
    root = (code or Path(__file__).resolve().parents[1]) / "clients" / "unity"
    folder.mkdir()
    exe = folder / "ScriptedSession.exe"
    sources = [*(root / "VRScrollLive").glob("*.cs"), root / "tests" / "ScriptedSession.cs"]
    sources = [s for s in sources if s.name != "VRScrollLiveDriver.cs"]  # the MonoBehaviour needs Unity
    try:
        build = subprocess.run(["mcs", "-warnaserror", f"-out:{exe}", *map(str, sources)], capture_output=True,
                               text=True)
    except FileNotFoundError:
        raise SystemExit("--csharp needs Mono: apt-get install mono-mcs mono-runtime") from None
    if build.returncode != 0:
        raise SystemExit(f"--csharp: mcs failed: {build.stdout}{build.stderr}")
    return exe


def goals_line(label: str, m: dict, fifo: int, load_text: str) -> str:
    """Both goals in one line: the pooled p99s of m's "pose", "pose_with_pens", "pen" (s) and the C# client's per
    session ([p50, p99, replies] ms lists under "csharp_pose_ms", "csharp_pen_ms"; the worst p99 of them), each
    met or NOT met."""
    def verdict(values_ms, goal) -> str:
        if not len(values_ms):
            return "none"
        worst = max(values_ms)
        return f"{worst:.2f} ms ({'met' if worst <= goal else 'NOT met'})"

    def p99(key):
        return [np.percentile(np.asarray(m[key]) * 1e3, 99)] if m.get(key) else []

    text = (f"GOALS {label} ({'--fifo ' + str(fifo) if fifo else 'ordinary scheduler'}, {load_text}): "
            f"pose -> approximation p99 {verdict(p99('pose'), POSE_GOAL_MS)} [goal {POSE_GOAL_MS} ms; "
            f"with pens running {verdict(p99('pose_with_pens'), POSE_GOAL_MS)}]; pen -> redirected p99 "
            f"{verdict(p99('pen'), PEN_GOAL_MS)} [goal {PEN_GOAL_MS} ms]")
    if m.get("csharp_pose_ms") is not None:
        text += (f"; C# client (worst round) pose p99 {verdict([c[1] for c in m['csharp_pose_ms']], POSE_GOAL_MS)}, "
                 f"pen p99 {verdict([c[1] for c in m['csharp_pen_ms']], PEN_GOAL_MS)}")
    return text


def csharp_rounds(ms: list[dict]) -> dict:
    """The C# client's [p50, p99, replies] per session of those that ran it, for goals_line."""
    ran = [m["csharp"] for m in ms if m.get("csharp") and not m["csharp"]["error"]]
    if not any(m.get("csharp") for m in ms):
        return {}
    return {"csharp_pose_ms": [c["pose_ms"] for c in ran], "csharp_pen_ms": [c["pen_ms"] for c in ran]}


def p50_p99(values) -> str:
    v = np.asarray(values) * 1e3
    return f"{np.percentile(v, 50):.3f} / {np.percentile(v, 99):.3f}" if len(v) else "-"


def compare(args) -> None:
    """Alternate this code's service and the one in args.against, round by round; pooled and per-round figures."""
    sides = {"before": args.against, "after": None}
    pooled = {side: {"pose": [], "pose_with_pens": [], "pen": [], "worker": [], "cpu": [], "sessions": []}
              for side in sides}
    rows = []
    first_load = os.getloadavg()[0]
    for r in range(args.rounds):
        for side in (("before", "after") if r % 2 == 0 else ("after", "before")):
            before = os.getloadavg()[0]
            m = session(args, sides[side])
            load_1min = f"{before:.2f} -> {os.getloadavg()[0]:.2f}"
            for key in ("pose", "pose_with_pens", "pen", "worker"):
                pooled[side][key] += m.get(key, [])
            pooled[side]["cpu"].append(m["cpu_us"])
            pooled[side]["sessions"].append(m)
            rows.append((r + 1, side, load_1min, m))
            print(f"round {r + 1} {side}: load {load_1min}; pose {p50_p99(m['pose'])} ms, "
                  f"pen {p50_p99(m.get('pen', []))} ms, lock {m['lock']}; CPU "
                  + ", ".join(f"{k} {v:.0f} us" for k, v in m["cpu_us"].items() if v is not None), flush=True)
            if "csharp" in m:
                print("  " + csharp_line(m), flush=True)
            for phase, line in m["waits"].items():
                print(f"  waiting for a core, {phase}: {line}", flush=True)
            if m["status"]:
                print("  " + breakdown("pose path", m["status"]["pose_path_ms"]))
                print("  " + breakdown("pose CPU", m["status"].get("pose_cpu_ms")))
                print("  " + breakdown("pen path", m["status"]["pen_path_ms"]))
            if m["status"]:
                print("  " + pen_split(m))
            if side == "after" and m["status"]:
                print("  " + stats("client send", m["client_send"], len(m["client_send"])))
                print("  " + stats("client receive", m["client_receive"], len(m["client_receive"])))
    print("\n| side | pose -> approximation p50 / p99 ms | with pens running | of which the worker | "
          "pen -> redirected p50 / p99 ms | worker CPU per pose, us | pens' CPU per pen, us |")
    print("|---|---|---|---|---|---|---|")
    for side, v in pooled.items():
        cpu = {key: [c[key] for c in v["cpu"] if c.get(key) is not None] for key in ("worker per pose", "pens per pen")}
        print(f"| {side} | {p50_p99(v['pose'])} | {p50_p99(v['pose_with_pens'])} | {p50_p99(v['worker'])} | "
              f"{p50_p99(v['pen'])} | " + " | ".join(f"{np.median(c):.0f}" if c else "-" for c in cpu.values()) + " |")
    load_text = f"load {first_load:.2f} -> {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores, {args.rounds} rounds"
    for side, v in pooled.items():
        print(goals_line(side, {**v, **csharp_rounds(v["sessions"])}, args.fifo, load_text))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=10.0, help="length of each measured phase (default 10)")
    p.add_argument("--shape", default="cylinder", choices=list(shape_table()))
    p.add_argument("--variant", default="full")
    p.add_argument("--against", type=Path, help="a checkout of another version (the folder holding its twin "
                                                "package): alternate its service with this one's")
    p.add_argument("--rounds", type=int, default=3, help="with --against: rounds of before and after (default 3)")
    p.add_argument("--csharp", action="store_true", help="measure with the C# client too (needs Mono's mcs, mono)")
    p.add_argument("--fifo", type=int, default=0, metavar="PRIORITY",
                   help="run the measured processes under SCHED_FIFO at this priority, 1-99 (default 0: not)")
    p.add_argument("--spin-us", type=float, default=0.0, metavar="US",
                   help="this code's side: after each sample the client polls its socket for the reply for at most "
                        "this long, us, before it waits in its event loop (default 0: it does not poll)")
    p.add_argument("--client-slice", action="store_true",
                   help="this code's side: the client's thread on the kernel's shortest scheduler slice "
                        "(LiveClient(short_slice=True); Linux 6.12 or later)")
    args = p.parse_args()
    if args.against is not None and not (args.against / "twin" / "live" / "service.py").is_file():
        p.error(f"--against {args.against}: no twin/live/service.py there")
    if args.rounds < 1:
        p.error("--rounds must be at least 1")
    if not 0 <= args.fifo <= 99:
        p.error("--fifo must be a priority from 1 to 99, or 0")
    with tempfile.TemporaryDirectory() as build:
        if args.csharp:
            args.csharp = {None: build_csharp(Path(build) / "after")}
            if args.against is not None:
                args.csharp[args.against] = build_csharp(Path(build) / "before", args.against)
        print(load())
        if args.against is not None:
            compare(args)
        else:
            first_load = os.getloadavg()[0]
            m = session(args)
            report(m)
            print(goals_line("this code", {**m, **csharp_rounds([m])}, args.fifo,
                             f"load {first_load:.2f} -> {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores"))
        print(load())


if __name__ == "__main__":
    main()
