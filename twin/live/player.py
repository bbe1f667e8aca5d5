"""The session player: synthetic VR sessions over the evaluation shapes, played against the live service.

Per shape, as a user of the paper's system would (docs/live.md, "Session player"):

1. target: the shape by name;
2. approach: the tracked device pose moves along its own normal from APPROACH_DISTANCE
   away to a start pose, on a minimum-jerk profile over APPROACH_S, with a hand tremor of
   TREMOR (two sines across the device, 5 and 7 Hz), streamed at POSE_HZ; then held still for
   HOLD_S. The first start is the shape's own (models/shapes/shapes.toml), the next ones the
   evaluation's seeded approach starts (twin/evaluation/starts.py);
3. lock the newest approximation, and follow gate, progress, then done / refused / stopped;
   when refused or stopped, approach again from the next start (up to `attempts`);
4. after done: a pen stroke touching the device where it ended, from one end of the row of
   flaps to the other (5 mm in from each end) on a wave across the depth (±35 % of the usable
   depth), the pen held along the surface normal, STROKE_S long at PEN_HZ, with the held
   device pose still streamed at POSE_HZ; every pen sample's reply is collected.

Nothing here is random but the seeded starts: the same seed plays the same sessions.
"""

from __future__ import annotations

import asyncio
import math
import time

import numpy as np

from twin.device.kinematics import flap_frames, matrix_quat
from twin.device.spec import DeviceSpec
from twin.evaluation.starts import approach_starts
from twin.formats.target import message_approximation
from twin.live.client import LiveClient, LiveError, latency
from twin.morphpatch.approximation import pose_from_mm_deg
from twin.morphpatch.redirection import flap_boundaries, rotation_between, surface_points
from twin.morphpatch.shapes import load_shape, shape_table

POSE_HZ = 90.0
PEN_HZ = 360.0
APPROACH_S = 1.0
APPROACH_DISTANCE = 0.12  # m
TREMOR = 0.001  # m, amplitude of each tremor sine
HOLD_S = 0.2
STROKE_S = 0.5
STROKE_INSET = 0.005  # m from each end of the row
STROKE_WAVE = 0.35  # of the usable depth
MORPH_TIMEOUT = 15.0  # s from lock to done / refused / stopped
REPLY_WAIT = 1.0  # s to wait for the last replies


def approach(start: np.ndarray, duration: float = APPROACH_S, rate_hz: float = POSE_HZ) -> np.ndarray:
    """Device poses (N, 4, 4) coming in along the start's own z to the start, minimum jerk, with tremor."""
    t = np.arange(int(round(duration * rate_hz)) + 1) / rate_hz
    u = t / duration
    s = 10 * u ** 3 - 15 * u ** 4 + 6 * u ** 5
    rot = start[:3, :3]
    offset = (1 - s)[:, None] * APPROACH_DISTANCE * rot[:, 2]
    offset += TREMOR * (np.sin(2 * math.pi * 5 * t)[:, None] * rot[:, 0] + np.sin(2 * math.pi * 7 * t)[:, None] * rot[:, 1])
    poses = np.tile(start, (len(t), 1, 1))
    poses[:, :3, 3] += offset
    return poses


def stroke(spec: DeviceSpec, root_pose, angles, widths, duration: float = STROKE_S,
           rate_hz: float = PEN_HZ) -> tuple[np.ndarray, np.ndarray]:
    """Pen tip positions (N, 3) m on the touch surface and orientations (N, 4) w,x,y,z along its normal."""
    frames = flap_frames(spec, angles, root_pose, widths)
    edges = flap_boundaries(spec, widths)
    n = int(round(duration * rate_hz))
    s = np.linspace(edges[0] + STROKE_INSET, edges[-1] - STROKE_INSET, n)
    y = STROKE_WAVE * spec.usable_depth * np.sin(2 * math.pi * (s - s[0]) / (s[-1] - s[0]))
    points, normals = surface_points(frames, edges, s, y)
    return points, rotation_between(np.tile([0.0, 0.0, 1.0], (n, 1)), normals)


async def _paced(count: int, rate_hz: float):
    """Yield 0..count-1 at rate_hz on the wall clock (late ticks are not made up twice)."""
    t0 = time.perf_counter()
    for k in range(count):
        await asyncio.sleep(max(0.0, t0 + k / rate_hz - time.perf_counter()))
        yield k


def _ms(values, q) -> float | None:
    return round(float(np.percentile(values, q)) * 1e3, 3) if len(values) else None


async def play_shape(client: LiveClient, spec: DeviceSpec, name: str, attempts: int = 4, seed: int = 0) -> dict:
    """One shape's session; a record of every attempt, the morph and the pen stroke."""
    await client.set_target(shape=name)
    starts = [pose_from_mm_deg(shape_table()[name]["start"])]
    if attempts > 1:
        starts += list(approach_starts(load_shape(name), attempts - 1, seed))
    record = {"shape": name, "attempts": [], "morphed": False}
    approx_latency = []
    for start in starts:
        poses = approach(start)
        held = poses[-1]
        quat = matrix_quat(held[:3, :3])
        last = None
        async for k in _paced(len(poses) + int(HOLD_S * POSE_HZ), POSE_HZ):
            pose = poses[min(k, len(poses) - 1)]
            last = client.send_pose(pose[:3, 3] * 1e3, matrix_quat(pose[:3, :3]))
        got = client.drain("approximation")
        while not got or got[-1]["seq"] != last:
            try:
                got.append(await client.datagram("approximation", timeout=REPLY_WAIT))
            except LiveError:
                break
        approx_latency += [latency(a) for a in got]
        t_lock = time.perf_counter()
        locked = await client.lock()
        outcome = await client.expect("done", "refused", "stopped", timeout=MORPH_TIMEOUT)
        attempt = {"start_pose_seq": last, "locked_seq": locked["seq"], "outcome": outcome["type"],
                   "message": outcome["message"], "settle_time_s": outcome.get("settle_time_s"),
                   "lock_to_done_wall_s": round(time.perf_counter() - t_lock, 3)}
        record["attempts"].append(attempt)
        if outcome["type"] != "done":
            continue
        record["morphed"] = True
        record["redirection"] = outcome["redirection"]
        approx = message_approximation(locked, spec, "the service's locked approximation")
        points, orientations = stroke(spec, approx.root_pose, np.radians(outcome["angles_deg"]), approx.widths)
        sent = []
        async for k in _paced(len(points), PEN_HZ):
            sent.append(client.send_pen(points[k] * 1e3, orientations[k]))
            if k % round(PEN_HZ / POSE_HZ) == 0:
                client.send_pose(held[:3, 3] * 1e3, quat)
        replies = client.drain("pen_redirected")
        deadline = time.monotonic() + REPLY_WAIT
        while len(replies) < len(sent) and time.monotonic() < deadline:
            try:
                replies.append(await client.datagram("pen_redirected", timeout=REPLY_WAIT))
            except LiveError:
                break
        answered = {r["seq"] for r in replies}
        pen_latency = [latency(r) for r in replies]
        record["pen"] = {"sent": len(sent), "redirected": len(answered & set(sent)),
                         "within_share": round(float(np.mean([r["within_thresholds"] for r in replies])), 4)
                         if replies else None,
                         "largest_offset_mm": max((r["offset_mm"] for r in replies), default=None),
                         "latency_p50_ms": _ms(pen_latency, 50), "latency_p99_ms": _ms(pen_latency, 99)}
        break
    client.drain("approximation")
    record["approximation_latency_p50_ms"] = _ms(approx_latency, 50)
    record["approximation_latency_p99_ms"] = _ms(approx_latency, 99)
    return record


async def play(url: str, spec: DeviceSpec, shapes, token: str | None = None, attempts: int = 4, seed: int = 0,
               on_record=None) -> list[dict]:
    """Every shape's session against the service at `url`; on_record(record) as each finishes."""
    records = []
    async with LiveClient(url, "control", token) as client:
        for name in shapes:
            record = await play_shape(client, spec, name, attempts, seed)
            records.append(record)
            if on_record:
                on_record(record)
    return records


def session_line(record: dict) -> str:
    """One shape's session (play_shape's record) on a line: its attempts' outcomes, then the settle time, the pen
    samples redirected, their latency and share within the thresholds, or why it did not morph."""
    r = record
    tries = ", ".join(a["outcome"] for a in r["attempts"])
    if not r["morphed"]:
        return f"{r['shape']:<14} not morphed ({tries}): {r['attempts'][-1]['message'] if r['attempts'] else ''}"
    pen, red = r["pen"], r["redirection"]
    settle = r["attempts"][-1]["settle_time_s"]
    settle = "not settled" if settle is None else f"{settle:5.3f} s"
    return (f"{r['shape']:<14} {tries:<28} settle time {settle}  pen {pen['redirected']}/"
            f"{pen['sent']} redirected, p99 {pen['latency_p99_ms']} ms, {pen['within_share']:.0%} within; surface "
            f"{red['share_within']:.0%} within; approximation p99 {r['approximation_latency_p99_ms']} ms")


def all_played(records: list[dict]) -> bool:
    """The sessions' verdict: every shape morphed and every pen sample it sent redirected."""
    return all(r["morphed"] and r["pen"]["redirected"] == r["pen"]["sent"] for r in records)
