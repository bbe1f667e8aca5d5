"""The live service (twin/live), run as `vrscroll serve` in its own process and talked to over
loopback by the Python client (twin/live/client.py), with the emulator as the device where one
is needed. The C# client's test is tests/live/test_live_unity.py.
"""

import asyncio
import collections
import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import trimesh

from websockets.asyncio.client import connect

from twin.cli import main as vrscroll
from twin.paths import cli_env
from twin.live.client import LiveClient, LiveError
from twin.live.morph import TwinMorpher
from twin.live.messages import (ERROR_INTERVAL, ESTIMATES_RATE_HZ, MAX_CONTROL_BYTES, MAX_DATAGRAM_BYTES,
                                PROTOCOL_VERSION, ProtocolError, encode_sample, parse_control, parse_sample)
from twin.live.player import stroke
from twin.live.process import ServiceProcess
from twin.live.scheduling import SLICE_S, ask_thread_slice, slice_s
from twin.live.stages import PEN_STAGES, POSE_CPU_STAGES, POSE_STAGES
from twin.device.spec import load_spec
from twin.formats.target import message_approximation
from twin.morphpatch.approximation import approximate, pose_from_mm_deg
from twin.morphpatch.fields import build_fields
from twin.morphpatch.frame_metrics import frame_estimates
from twin.morphpatch.redirection import build_field, threshold_summary
from twin.morphpatch.shapes import load_shape
from twin.morphpatch.surface_metrics import msd_hd, point_distances
from twin.perception.thresholds import load_thresholds
from twin.sim.response import move_report
from twin.sim.twin import Twin

CYLINDER_START = ([10.0, 0.0, 190.0], [1.0, 0.0, 0.0, 0.0])  # mm, above the cylinder's top, level


@pytest.fixture(scope="module")
def twin_service(tmp_path_factory):
    """A service without a device (locks morph the twin), the cylinder as its first target."""
    with ServiceProcess("--shape", "cylinder", stderr_path=tmp_path_factory.mktemp("live") / "serve.err") as s:
        yield s


def run(coroutine):
    return asyncio.run(asyncio.wait_for(coroutine, 120))


async def first_approximation(client, timeout=5.0):
    """Stream the cylinder start at 90 Hz until an approximation comes back."""
    for _ in range(int(timeout * 90)):
        client.send_pose(*CYLINDER_START)
        try:
            return await client.datagram("approximation", timeout=1 / 90)
        except LiveError:
            pass
    raise AssertionError("no approximation")


async def expect_error(client, code, source="control"):
    event = await client.expect("error", timeout=5)
    assert (event["code"], event["source"]) == (code, source), event
    return event


# ---- the wire format -----------------------------------------------------------------------

@pytest.mark.parametrize("message, code", [
    (b"\x00\x01", "malformed"), ("{", "malformed"), ("[1, 2]", "malformed"), ('{"type": "fly"}', "unknown_type"),
    ('{"type": "hello", "protocol": 1, "role": "control"}', "malformed"),  # version 1's approximation had estimates
    ('{"type": "hello", "protocol": 2, "role": "control"}', "malformed"),  # version 2 sent its poses to udp_port
    ('{"type": "hello", "protocol": 3, "role": "control"}', "malformed"),  # version 3 sent JSON samples
    ('{"type": "hello", "protocol": 4, "role": "king"}', "malformed"),
    ('{"type": "target"}', "malformed"), ('{"type": "target", "shape": "cube", "mesh": {}}', "malformed"),
    ("x" * (MAX_CONTROL_BYTES + 1), "oversized")])
def test_bad_control_messages_are_named(message, code):
    with pytest.raises(ProtocolError) as exc:
        parse_control(message)
    assert exc.value.code == code


S = "ab" * 16  # a session


@pytest.mark.parametrize("data, code, words", [
    (b"x" * (MAX_DATAGRAM_BYTES + 1), "oversized", "limit"), (b"\xff\xfe", "malformed", "152 bytes"),
    (b'{"type": "pose", "session": "s"}', "malformed", "binary"),  # protocol 3's JSON
    (b"VX" + encode_sample("pose", S, 1, [0, 0, 0], [1, 0, 0, 0])[2:], "malformed", "VS"),
    (encode_sample("pose", S, 1, [0, 0, 0], [1, 0, 0, 0])[:2] + b"\x03" + encode_sample(
        "pose", S, 1, [0, 0, 0], [1, 0, 0, 0])[3:], "malformed", "version"),
    (encode_sample("pose", S, 1, [0, 0, 0], [1, 0, 0, 0])[:3] + b"\x07" + encode_sample(
        "pose", S, 1, [0, 0, 0], [1, 0, 0, 0])[4:], "unknown_type", "kind"),
    (encode_sample("pose", S, 1, [0, 0, 0], [1, 0, 0, 0], device_position_mm=[0, 0, 0],
                   device_quat_wxyz=[1, 0, 0, 0]), "malformed", "pens only"),
    (encode_sample("pose", S, 1, [0, 0, 0], [1, 0, 0, 0])[:7] + b"\x01" + encode_sample(
        "pose", S, 1, [0, 0, 0], [1, 0, 0, 0])[8:], "malformed", "reserved"),
    (encode_sample("pose", S, 1, [0, 0, float("nan")], [1, 0, 0, 0]), "malformed", "position_mm"),
    (encode_sample("pen", S, 1, [0, 0, 0], [0, 0, 0, 0]), "malformed", "zero quaternion"),
    (encode_sample("pose", S, 2 ** 53, [0, 0, 0], [1, 0, 0, 0]), "malformed", "seq"),
    (encode_sample("pose", S, 1, [0, 0, 0], [1, 0, 0, 0], t_s=float("inf")), "malformed", "t_s"),
    # huge but finite: refused before any compiled code sees them (a segmentation fault of the worker once)
    (encode_sample("pose", S, 1, [1e300, 1e300, 1e300], [1, 0, 0, 0]), "malformed", "position_mm"),
    (encode_sample("pose", S, 1, [0, 0, 0], [1e300, 1e300, 0, 0]), "malformed", "quat_wxyz"),
    (encode_sample("pen", S, 1, [0, 0, 0], [1, 0, 0, 0], device_position_mm=[0, 0, 2e5],
                   device_quat_wxyz=[1, 0, 0, 0]), "malformed", "device_position_mm"),
    (encode_sample("pen", S, 1, [0, 0, 0], [1, 0, 0, 0], device_position_mm=[0, 0, 0],
                   device_quat_wxyz=[0, 0, 0, 0]), "malformed", "device_quat_wxyz")])
def test_bad_datagrams_are_named(data, code, words):
    with pytest.raises(ProtocolError) as exc:
        parse_sample(data)
    assert exc.value.code == code and words in str(exc.value)


def test_a_datagram_round_trips_in_si():
    sample = parse_sample(encode_sample("pen", S, 7, [10, 20, 30], [2, 0, 0, 0], t_s=1.5,
                                        device_position_mm=[1, 2, 3], device_quat_wxyz=[0, 0, 0, 1]))
    assert sample.kind == "pen" and sample.session == S and sample.seq == 7 and sample.t_s == 1.5
    assert np.allclose(sample.position, [0.01, 0.02, 0.03]) and np.allclose(sample.quat, [1, 0, 0, 0])
    assert np.allclose(sample.device_pose[:3, 3], [0.001, 0.002, 0.003])
    assert np.allclose(sample.device_pose[:3, :3], np.diag([-1, -1, 1]))
    pose = parse_sample(encode_sample("pose", S, 2 ** 53 - 1, [0, 0, 1e5], [0, 0, -3, 0]), "pose")
    assert (pose.kind, pose.seq, pose.t_s, pose.device_pose) == ("pose", 2 ** 53 - 1, None, None)
    assert np.allclose(pose.position, [0, 0, 100.0]) and np.allclose(pose.quat, [0, 0, -1, 0])


def test_frame_estimates_agree_with_the_exact_metrics(spec):
    thresholds = load_thresholds()
    for shape, start in [("cylinder", [10, 0, 190, 5, 5, 10]), ("stairs", [10, 0, 130, 0, -20, 5])]:
        mesh = load_shape(shape)
        fields = build_fields(mesh)
        a = approximate(fields, pose_from_mm_deg(start), spec)
        msd, share = frame_estimates(spec, fields, thresholds, a.root_pose, a.angles, a.widths)
        exact_msd, _ = msd_hd(spec, mesh, a.root_pose, a.angles, a.widths)
        exact_share = threshold_summary(build_field(spec, a.root_pose, a.angles, a.widths, mesh, fields))["share_within"]
        assert abs(msd - exact_msd) < 0.3e-3 + 0.1 * exact_msd, (shape, msd, exact_msd)
        assert abs(share - exact_share) < 0.1, (shape, share, exact_share)
    # flat and 60 mm above the cylinder's top: beyond the 50 mm positional threshold everywhere
    lifted = a.root_pose.copy()
    lifted[:3, 3] = [0.0, 0.0, 0.21]
    lifted[:3, :3] = np.eye(3)
    msd, share = frame_estimates(spec, build_fields(load_shape("cylinder")), thresholds, lifted, np.zeros(6),
                                 np.full(7, spec.flap_pitch))
    assert msd > 0.05 and share == 0.0


def test_the_twin_without_a_device_is_one_device_across_morphs(spec):
    """The service's twin, with no device attached, keeps what its last morph left the PID holding (the
    integral, frozen at rest as a device's): a morph from there is predicted as a twin that made both moves
    in one run. Started empty, each morph's prediction came 4-12 ms sooner."""
    first, second = np.radians([-20, -30, -40, -40, -30, -20]), np.radians([20, 30, 40, 40, 30, 20])
    one = Twin(spec)
    one.move_to(first, max_time=2.0)
    one.hold(spec.settle_hold)
    both = move_report(spec, one.move_to(second, max_time=2.0)).settle_time
    morpher, moves = TwinMorpher(spec), []
    morpher.open()
    morpher.on_move = lambda _, trace: moves.append(trace)
    for targets in (first, second):
        assert morpher.morph(targets, lambda message: None).status == "done"
    assert move_report(spec, moves[-1]).settle_time == pytest.approx(both, abs=0.002)


def test_bad_command_lines_are_one_line_errors(capsys):
    assert vrscroll(["play", "--shapes", "teapot"]) == 2
    assert vrscroll(["play", "--url", "nonsense", "--shapes", "cube"]) == 2
    assert vrscroll(["serve", "--host", "10.1.2.3"]) == 2  # refused before anything is bound
    err = capsys.readouterr().err
    assert "'teapot' is not one of" in err and "nonsense" in err and "--allow-remote" in err


# ---- the service -----------------------------------------------------------------------------

def test_bad_messages_get_errors_and_the_connection_stays_open(twin_service):
    async def session():
        async with LiveClient(twin_service.url, "observer") as observer:
            await observer.send({"type": "lock"})
            await expect_error(observer, "forbidden")
        client = LiveClient(twin_service.url)
        await client.connect()
        for bad, code in [("not json", "malformed"), (b"\x01\x02", "malformed"), ('{"type": "fly"}', "unknown_type"),
                          ("[" + " " * (MAX_CONTROL_BYTES + 10) + "]", "oversized"),
                          ('{"type": "target", "shape": "teapot"}', "bad_target"),
                          ('{"type": "target", "mesh": {"vertices_mm": [[0, 0, 0]], "faces": [[0, 1, 2]]}}',
                           "malformed"),
                          (json.dumps({"type": "hello", "protocol": PROTOCOL_VERSION, "role": "control"}), "out_of_order")]:
            await client.send(bad)
            await expect_error(client, code)
        await client.send({"type": "lock"})  # nothing approximated yet on this session
        await expect_error(client, "out_of_order")
        first = await first_approximation(client)
        # datagrams: pen before any lock, malformed, oversized, an old sequence number
        client.send_pen([0, 0, 150], [1, 0, 0, 0])
        await expect_error(client, "out_of_order", "datagram")
        client.send_raw_datagram(b"{nope")
        await expect_error(client, "malformed", "datagram")
        client.send_raw_datagram(b" " * (MAX_DATAGRAM_BYTES + 100))
        await expect_error(client, "oversized", "datagram")
        client.send_raw_datagram(encode_sample("pose", client.session, first["seq"], *CYLINDER_START), to="pose")
        await expect_error(client, "stale", "datagram")
        # the worker's pose port takes poses only, the service's port pens only; a pose there is malformed too
        client.send_raw_datagram(encode_sample("pen", client.session, 10**6, *CYLINDER_START), to="pose")
        assert "pose_port" in (await expect_error(client, "unknown_type", "datagram"))["message"]
        client.send_raw_datagram(encode_sample("pose", client.session, 10**6, *CYLINDER_START))
        await asyncio.sleep(ERROR_INTERVAL)  # the same code's reports are a tenth of a second apart
        client.send_raw_datagram(encode_sample("pose", client.session, 10**6 + 1, *CYLINDER_START))
        assert "pose_port" in (await expect_error(client, "unknown_type", "datagram"))["message"]
        client.send_raw_datagram(b"{nope", to="pose")
        await expect_error(client, "malformed", "datagram")
        # still served: a status, and a new pose still gets its approximation
        status = await client.status()
        assert status["counts"]["stale"] >= 1 and status["counts"]["malformed"] >= 4
        assert (await first_approximation(client))["seq"] > first["seq"]
        await client.close()

    run(session())


def test_nothing_but_hello_is_taken_before_hello(twin_service):
    async def session():
        async with connect(twin_service.url) as ws:
            await ws.send(json.dumps({"type": "lock"}))
            event = json.loads(await ws.recv())
            assert event["code"] == "out_of_order" and "hello" in event["message"]
            await ws.send(json.dumps({"type": "status"}))
            assert json.loads(await ws.recv())["code"] == "out_of_order"

    run(session())


def test_a_second_controller_is_refused_and_observers_watch(twin_service):
    async def session():
        async with LiveClient(twin_service.url) as first, LiveClient(twin_service.url, "observer") as observer:
            second = LiveClient(twin_service.url)
            with pytest.raises(LiveError, match="controller_taken"):
                await second.connect()
            await second.send({"type": "hello", "protocol": PROTOCOL_VERSION, "role": "observer"})  # same connection, now watching
            assert (await second.expect("welcome"))["role"] == "observer"
            await second.send({"type": "target", "shape": "cube"})
            await expect_error(second, "forbidden")
            await first.set_target(shape="arch")
            for watcher in (observer, second):
                assert (await watcher.expect("target_ready"))["target"]["name"] == "arch"
            await second.close()
            await first.set_target(shape="cylinder")

    run(session())


def test_a_mesh_sent_as_the_target_is_approximated_and_an_open_one_refused(twin_service):
    box = trimesh.creation.box([0.3, 0.3, 0.1])  # its top larger than the device
    box.apply_translation([0, 0, 0.05])  # on the ground, top face at z = 100 mm
    open_box = box.copy()
    open_box.update_faces(np.arange(len(open_box.faces)) > 1)  # one side's two triangles gone

    def mesh(m):
        return {"vertices_mm": (m.vertices * 1e3).tolist(), "faces": m.faces.tolist()}

    async def session():
        async with LiveClient(twin_service.url) as client:
            await client.send({"type": "target", "mesh": mesh(open_box)})
            refused = await expect_error(client, "bad_target")
            ready = await client.set_target(mesh=mesh(box))
            client.send_pose([0, 0, 140], [1, 0, 0, 0])
            approx = await client.datagram("approximation", timeout=5)
            estimates = await client.datagram("estimates", timeout=5)
            await client.set_target(shape="cylinder")
            return refused, ready, approx, estimates

    refused, ready, approx, estimates = run(session())
    assert "mesh" in refused["message"]
    assert ready["target"]["name"] == "mesh" and np.allclose(ready["target"]["bounds_mm"], [[-150, -150, 0], [150, 150, 100]])
    # flat on the box's top: the anchor at 100 mm, hinges flat, the surface on the face
    assert abs(approx["root_position_mm"][2] - 100) < 1 and max(map(abs, approx["angles_deg"])) < 1
    assert estimates["seq"] == approx["seq"]
    assert estimates["msd_estimate_mm"] < 0.5 and estimates["share_within_estimate"] == 1.0


def test_each_approximation_comes_first_and_frame_estimates_follow_for_the_newest(twin_service, spec):
    """Poses at 90 Hz sliding over the cylinder: every approximation comes back in order; frame estimates follow in
    datagrams of their own (off the pose's path), each for an approximation already sent (the newest when the worker
    had no pose waiting), in order, at most ESTIMATES_RATE_HZ (so not for every approximation at 90 Hz), with the
    values the estimates give for that approximation as it was sent."""
    async def session():
        async with LiveClient(twin_service.url) as client:
            await client.set_target(shape="cylinder")
            for k in range(60):
                client.send_pose([10 + 20 * np.sin(k / 9), 0, 190], [1, 0, 0, 0])
                await asyncio.sleep(1 / 90)
            await asyncio.sleep(0.5)
            return client.welcome, client.drain("approximation"), client.drain("estimates")

    welcome, approximations, estimates = run(session())
    assert welcome["estimates_rate_hz"] == ESTIMATES_RATE_HZ
    seqs = [a["seq"] for a in approximations]
    assert len(seqs) >= 30 and seqs == sorted(set(seqs))
    estimated = [e["seq"] for e in estimates]
    assert estimated == sorted(set(estimated)) and set(estimated) <= set(seqs)
    assert 5 <= len(estimates) < len(approximations)
    fields, thresholds = build_fields(load_shape("cylinder")), load_thresholds()
    slid = [a["root_position_mm"][0] for a in approximations]
    assert max(slid) - min(slid) > 10  # they answer different poses
    by_seq = {a["seq"]: a for a in approximations}
    for e in estimates:
        a = by_seq[e["seq"]]
        assert e["received_s"] >= a["received_s"] and e["t_s"] == a["t_s"]
        approx = message_approximation(a, spec, "approximation")
        msd, share = frame_estimates(spec, fields, thresholds, approx.root_pose, approx.angles, approx.widths)
        assert e["msd_estimate_mm"] == pytest.approx(msd * 1e3, abs=0.01)
        assert e["share_within_estimate"] == pytest.approx(share, abs=0.01)


def test_off_loopback_needs_the_flag_and_every_client_the_token(tmp_path):
    assert vrscroll(["serve", "--host", "127.0.0.2"]) == 2  # not the loopback address, no --allow-remote
    with ServiceProcess("--host", "127.0.0.2", "--allow-remote", "--token", "s3cret",
                        stderr_path=tmp_path / "serve.err") as service:
        assert service.url.startswith("ws://127.0.0.2:")

        async def session():
            for token in (None, "wrong"):
                client = LiveClient(service.url, token=token)
                with pytest.raises(LiveError, match="unauthorized"):
                    await client.connect()
                closed = await client.expect("closed")
                assert closed["code"] == 1008
            async with LiveClient(service.url, "observer", token="s3cret") as good:
                assert good.welcome["role"] == "observer"

        run(session())


def test_memory_stays_bounded_under_a_flood_of_datagrams(twin_service):
    """200 000 datagrams as fast as a loop can send them: valid, stale, malformed, pens out of turn."""
    async def session():
        async with LiveClient(twin_service.url) as client:
            await first_approximation(client)
            first = client.send_pose(*CYLINDER_START)
            await asyncio.sleep(0.5)
            begin = (await client.status())["counts"]  # (the service is the module's: earlier tests' poses too)

            async def flood(n):
                for k in range(n):
                    kind = k % 4
                    if kind == 0:
                        client.send_pose(*CYLINDER_START)
                    elif kind == 1:
                        client.send_raw_datagram(encode_sample("pose", client.session, 0, *CYLINDER_START), "pose")
                    elif kind == 2:
                        client.send_raw_datagram(b'{"type": "pose", "seq": "x"}', "pose")
                    else:
                        client.send_pen([0, 0, 150], [1, 0, 0, 0])
                    if k % 200 == 0:
                        await asyncio.sleep(0.001)  # bursts the service can mostly keep up with

            await flood(40_000)
            await asyncio.sleep(0.5)
            before = twin_service.rss_bytes()
            await flood(160_000)
            await asyncio.sleep(0.5)
            last = client.send_pose(*CYLINDER_START)  # carries the kernel's count of the flood's pose datagrams dropped
            await asyncio.sleep(0.5)
            after = twin_service.rss_bytes()
            for _ in range(20):  # until the worker has taken what waited on its socket (it may still, at a high load)
                status = await client.status()
                if taken(status["counts"]) - taken(begin) >= 100_000 + last - first:
                    break
                await asyncio.sleep(0.5)
            errors = [e for e in client.history if e["type"] == "error"]
            return before, after, status, errors, begin, first, last

    def taken(counts):  # pose datagrams the worker read, or the kernel dropped
        return counts["pose_datagrams"] + counts.get("pose_dropped", 0)

    before, after, status, errors, begin, first, last = run(session())
    # 160 000 datagrams kept would be well over 100 MB of Python objects
    assert after - before < 8e6, (before, after)
    counts = status["counts"]
    # the service's port: the 50,000 pens (a fifth of them taken at least, as before of the 200,000 on one port)
    assert counts["datagrams"] > 10_000 and counts["pen_not_locked"] > 10_000
    # the worker's port: every pose datagram taken, or dropped by the kernel while the worker approximated (counted)
    poses_sent = 200_000 // 2 + last - first  # the raw ones (stale, malformed), and every send_pose after `first`
    assert taken(counts) - taken(begin) == poses_sent
    assert counts["stale"] > 0 and counts["malformed"] > 0
    assert 0 < counts["approximations"] < counts["pose"]  # the newest pose wins; the rest were superseded
    # errors reported with counts, not one per datagram: at most one per kind every 0.1 s
    assert sum(e["count"] for e in errors) > 10 * len(errors)


def test_lock_on_the_twin_morphs_and_redirects_touching_pens_onto_the_target(twin_service):
    mesh = load_shape("cylinder")

    async def session():
        async with LiveClient(twin_service.url) as client, LiveClient(twin_service.url, "observer") as observer:
            first = await first_approximation(client)
            locked = await client.lock()
            # locked the moment the worker's datagram arrived: the newest it had sent, that one or a later one, as
            # the client received it
            assert locked["seq"] >= first["seq"]
            await asyncio.sleep(0.1)
            received = {a["seq"]: a for a in [first, *client.drain("approximation")]}
            assert locked["seq"] in received
            # the same approximation: the datagram's doubles, the event's rounded to 0.001 deg
            assert received[locked["seq"]]["angles_deg"] == pytest.approx(locked["angles_deg"], abs=0.0005 + 1e-9)
            gate = await client.expect("gate")
            progress = await client.expect("progress")
            done = await client.expect("done", timeout=10)
            assert (await observer.expect("done", timeout=10))["seq"] == locked["seq"]
            approx = message_approximation(locked, load_spec(), "locked")
            points, quats = stroke(load_spec(), approx.root_pose, np.radians(done["angles_deg"]), approx.widths,
                                   duration=0.1)
            for p, q in zip(points, quats):
                client.send_pen(p * 1e3, q)
            replies = [await client.datagram("pen_redirected") for _ in points]
            # the same pens again, each reply taken by polling the socket (LiveClient.spin), not by the event loop
            spun = []
            for p, q in zip(points, quats):
                seq = client.send_pen(p * 1e3, q)
                assert client.spin("pen_redirected", 1.0)
                spun += client.drain("pen_redirected")
                assert spun[-1]["seq"] == seq
            return gate, progress, done, points, replies, spun, await client.status()

    gate, progress, done, points, replies, spun, status = run(session())
    # a reply polled for is the one the event loop took, stamped in the kernel before this process took it
    assert [r["position_mm"] for r in spun] == [r["position_mm"] for r in replies]
    assert all(r["t_s"] <= r["arrived_s"] <= r["received_s"] for r in replies + spun)
    # where the time went, per stage of each path (twin/live/stages.py), each stage within its path's total
    for path, stages in (("pose_path_ms", POSE_STAGES), ("pen_path_ms", PEN_STAGES)):
        assert tuple(status[path]) == stages
        total = status[path]["total"]
        assert all(0 <= t["p50"] <= t["p99"] and t["p50"] <= total["p99"] for t in status[path].values()), status[path]
    assert status["pen_path_ms"]["total"] == status["pen_latency_ms"]
    # a pose's CPU in the worker, per stage of its answer: the approximation's no more than its wall time, pose by
    # pose, and so in each percentile (the two stamped a few us apart)
    assert tuple(status["pose_cpu_ms"]) == POSE_CPU_STAGES
    assert all(0 <= t["p50"] <= t["p99"] for t in status["pose_cpu_ms"].values())
    for p in ("p50", "p99"):
        assert status["pose_cpu_ms"]["approximate"][p] <= status["pose_path_ms"]["approximate"][p] + 0.005
    assert gate["passed"] and progress["source"] == "twin"
    # the morph's settle time, as the gate predicted it (one definition: docs/device.md)
    assert done["settle_time_s"] == pytest.approx(next(c["value"] for c in gate["checks"] if c["name"] == "settle"),
                                                  abs=1e-4)
    assert done["redirection"]["share_within"] > 0.9
    virtual = np.array([r["position_mm"] for r in replies]) / 1e3
    on_device = np.abs(point_distances(mesh, points))
    on_target = np.abs(point_distances(mesh, virtual))
    # the device is within a few mm of the cylinder; the redirected pen lands on it (the blur leaves < 1 mm)
    assert on_device.max() > 1e-3 and on_target.max() < 1e-3, (on_device.max(), on_target.max())


def test_a_client_asking_for_a_short_slice_gets_it_on_its_own_thread_alone(twin_service):
    """LiveClient(short_slice=True): the thread that connects (its event loop takes the replies) on Linux's shortest
    scheduler slice wherever this kernel grants a thread one; the process's other threads as they were."""
    seen = {}

    def client_thread():
        async def session():
            async with LiveClient(twin_service.url, short_slice=True) as client:
                seen["welcome"] = client.welcome
        asyncio.run(session())
        seen["slice"] = slice_s(threading.get_native_id())

    def probe():  # what the kernel grants a thread here, asked in a thread of its own
        seen["granted"] = ask_thread_slice()

    before = slice_s(threading.get_native_id())
    for target in (client_thread, probe):
        thread = threading.Thread(target=target)
        thread.start()
        thread.join()
    assert seen["welcome"]["role"] == "control"
    assert slice_s(threading.get_native_id()) == before
    if seen["granted"]:
        assert seen["slice"] == SLICE_S != before


def test_serve_records_every_morph_for_rerun(tmp_path):
    from rerun_read import read_rrd

    rrd = tmp_path / "live.rrd"
    with ServiceProcess("--shape", "cylinder", "--rerun", str(rrd), stderr_path=tmp_path / "serve.err") as service:
        async def session():
            async with LiveClient(service.url) as client:
                await first_approximation(client)
                await client.lock()
                return await client.expect("done", timeout=10)

        done = run(session())
    columns = read_rrd(rrd)
    final = [columns[(f"/hinge{k}/true_angle_deg/twin", "Scalars:scalars")][-1][0] for k in range(6)]
    assert final == pytest.approx(done["angles_deg"], abs=1e-3)  # the flaps' true angles, where the morph ended
    encoder = [columns[(f"/hinge{k}/angle_deg/twin", "Scalars:scalars")][-1][0] for k in range(6)]
    assert encoder == pytest.approx(final, abs=1.0) and encoder != final  # the encoder's, as a device's reads
    assert ("/world/twin/flap0_visual", "Transform3D:translation") in columns


def test_a_pose_never_moves_the_device_and_a_controller_leaving_mid_morph_leaves_it_holding(emulator, tmp_path):
    emu = emulator()
    with ServiceProcess("--shape", "cylinder", "--serial", emu.port, "--log", str(tmp_path / "session.jsonl"),
                        stderr_path=tmp_path / "serve.err") as service:
        async def session():
            async with LiveClient(service.url, "observer") as observer:
                client = LiveClient(service.url)
                await client.connect()
                for _ in range(45):  # half a second of poses
                    client.send_pose(*CYLINDER_START)
                    await asyncio.sleep(1 / 90)
                await first_approximation(client)
                await asyncio.sleep(0.1)
                moved_by_poses = [e for e in emu.events("rx") if e["msg"] == "SET_TARGETS"]
                locked = await client.lock()
                await client.expect("progress", timeout=10)  # moving
                await client.close()  # the VR application goes away mid-morph
                done = await observer.expect("done", "stopped", timeout=10)
                seen = [e["type"] for e in observer.history]
                left = observer.history[seen.index("controller_left")]
                assert left["state"] == "morphing" and seen.index("controller_left") < seen.index(done["type"])
                await asyncio.sleep(0.6)  # three watchdog periods
                async with LiveClient(service.url) as again:
                    status = await again.status()
                return moved_by_poses, locked, done, status

        moved_by_poses, locked, done, status = run(session())
        estops_while_serving = [e for e in emu.events("rx") if e["msg"] == "ESTOP"]
    assert moved_by_poses == []
    assert done["type"] == "done", done
    assert status["device_state"] == "ACTIVE" and status["faults"] == "none"
    assert np.allclose(status["angles_deg"], locked["angles_deg"], atol=1.0)
    assert not estops_while_serving  # held while the service runs; e-stopped as it stops (tests/hil/test_interrupts.py)
    assert [e for e in emu.events("rx") if e["msg"] == "ESTOP"]
    # telemetry is switched off after the morph (the link would queue 500 frames a second for nobody)
    rates = [e["rate_hz"] for e in emu.events("rx") if e["msg"] == "SET_TELEMETRY_RATE"]
    assert rates[-1] == 0 and 500 in rates


def test_a_device_that_goes_away_is_reported_and_the_service_stays(emulator, tmp_path):
    emu = emulator()
    with ServiceProcess("--shape", "cylinder", "--serial", emu.port, "--log", str(tmp_path / "session.jsonl"),
                        stderr_path=tmp_path / "serve.err") as service:
        async def session():
            async with LiveClient(service.url) as client:
                assert (await client.status())["device_state"] == "IDLE"
                emu.kill()  # the cable is pulled
                await asyncio.sleep(0.3)
                gone = await client.status()
                await first_approximation(client)  # approximations go on without a device
                await client.lock()
                outcome = await client.expect("done", "refused", "stopped", timeout=10)
                return gone, outcome, await client.status()

        gone, outcome, after = run(session())
    assert gone["device_state"] == "UNREACHABLE" and "went away" in gone["faults"]
    assert outcome["type"] == "stopped" and "link" in outcome["message"]
    assert after["state"] == "idle"


@pytest.mark.parametrize("shapes", ["cylinder,stairs",
                                    pytest.param(None, marks=pytest.mark.slow)])
def test_session_player_against_the_emulator_locks_morphs_and_redirects_every_pen_sample(shapes, tmp_path, capsys):
    out = tmp_path / "play.json"
    args = ["play", "--json", str(out)] + (["--shapes", shapes] if shapes else [])
    assert vrscroll(args) == 0, capsys.readouterr()
    records = json.loads(out.read_text())
    assert [r["shape"] for r in records] == (shapes.split(",") if shapes else
                                             ["cube", "torus", "arch", "cone", "cylinder", "ellipsoid", "stairs",
                                              "curved_stairs"])
    for r in records:
        assert r["morphed"] and r["attempts"][-1]["outcome"] == "done"
        assert r["pen"]["sent"] == r["pen"]["redirected"] > 100
        assert r["redirection"]["share_within"] > 0.5
    assert "every pen sample redirected" in capsys.readouterr().out


def test_serve_uses_the_device_profile_and_names_it(tmp_path, capsys):
    """`serve --device NAME`: the profile's twin, named in the welcome; with none selected, the spec's (that a
    selected profile is remembered: tests/hil/test_profile.py)."""
    assert vrscroll(["device", "create", "bench"]) == 0
    capsys.readouterr()

    async def welcome(url):
        async with LiveClient(url, "observer") as observer:
            return observer.welcome

    with ServiceProcess("--device", "bench", "--shape", "cylinder", stderr_path=tmp_path / "serve.err") as s:
        assert run(welcome(s.url))["device_profile"] == "bench"
    assert vrscroll(["device", "select", "none"]) == 0
    with ServiceProcess("--shape", "cylinder", stderr_path=tmp_path / "serve3.err") as s:
        assert run(welcome(s.url))["device_profile"] == "spec defaults"


def _children(pid: int) -> dict[str, list[int]]:
    """The service pid's children by name (/proc/PID/comm: `vrscroll-worker`, `vrscroll-pens`; multiprocessing's
    resource tracker, when one runs, is a plain `python`)."""
    out = collections.defaultdict(list)
    for proc in Path("/proc").glob("[0-9]*"):
        try:
            parent = int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
            name = (proc / "comm").read_text().strip()
        except (OSError, IndexError, ValueError):
            continue
        if parent == pid:
            out[name].append(int(proc.name))
    return out


def test_a_worker_that_dies_is_restarted_and_the_client_served(tmp_path):
    """The approximation worker killed (as a crash of compiled code would): the pose that was in flight gets an
    error, the next ones their approximations, with the target the service had."""
    with ServiceProcess("--shape", "cylinder", stderr_path=tmp_path / "serve.err") as service:
        async def session():
            async with LiveClient(service.url) as client:
                await first_approximation(client)
                workers = _children(service.pid)["vrscroll-worker"]
                assert len(workers) == 1
                os.kill(workers[0], signal.SIGKILL)
                await asyncio.sleep(0.5)
                client.drain("estimates")
                client.drain("approximation")  # any the killed worker sent before it died: the next is the new one's
                await first_approximation(client, timeout=60)
                again = await client.datagram("estimates")
                assert again["msd_estimate_mm"] < 5.0  # on the cylinder again: the restarted worker has its target
                failed = [e for e in client.history if e["type"] == "error" and e["code"] == "approximation_failed"]
                assert failed and failed[0]["source"] == "datagram" and "died" in failed[0]["message"]

        run(session())
        assert "approximation worker died" in (tmp_path / "serve.err").read_text()


def test_pens_are_served_by_a_process_of_their_own_that_is_restarted_with_its_field(tmp_path):
    """The pens' own process (nothing else in it, on a short scheduler slice: twin/live/pens.py) redirects the pens
    after a lock; killed, it is
    started again with the controller's session and the lock's field, and the next pens are redirected as before,
    in order, to the same virtual points; a new lock stops the redirection until its own morph is done."""
    with ServiceProcess("--shape", "cylinder", stderr_path=tmp_path / "serve.err") as service:
        async def session():
            async with LiveClient(service.url) as client:
                await first_approximation(client)
                children = _children(service.pid)
                assert len(children["vrscroll-pens"]) == 1 and len(children["vrscroll-worker"]) == 1
                slices = [slice_s(children[name][0]) for name in ("vrscroll-pens", "vrscroll-worker")]
                locked = await client.lock()
                done = await client.expect("done", timeout=10)
                approx = message_approximation(locked, load_spec(), "locked")
                points, quats = stroke(load_spec(), approx.root_pose, np.radians(done["angles_deg"]), approx.widths,
                                       duration=0.05)

                async def pens():
                    seqs = [client.send_pen(p * 1e3, q) for p, q in zip(points, quats)]
                    replies = [await client.datagram("pen_redirected", timeout=5) for _ in points]
                    assert [r["seq"] for r in replies] == seqs
                    return [r["position_mm"] for r in replies]

                before = await pens()
                os.kill(children["vrscroll-pens"][0], signal.SIGKILL)
                for _ in range(100):  # until the new one runs (it imports numpy and the compiled code first)
                    await asyncio.sleep(0.2)
                    restarted = _children(service.pid)["vrscroll-pens"]
                    if restarted and restarted != children["vrscroll-pens"]:
                        break
                status = await client.status()  # answered once the new one has its session and its field
                after = await pens()
                await client.lock()  # a new lock: the old field no longer redirects
                client.send_pen(points[0] * 1e3, quats[0])
                await asyncio.sleep(0.3)
                stopped = client.drain("pen_redirected")
                await client.expect("done", "refused", "stopped", timeout=10)
                return before, after, status, stopped, restarted, slices

        before, after, status, stopped, restarted, slices = run(session())
    # the pen process asks the kernel for its shortest slice (twin/live/scheduling.py), where it takes such a
    # request; the worker keeps the default (its approximation is not cut into pieces)
    probe = subprocess.run([sys.executable, "-c", "from twin.live.scheduling import ask_short_slice, slice_s; "
                            "print(ask_short_slice() and slice_s())"], capture_output=True, text=True, env=cli_env())
    assert probe.returncode == 0, probe.stderr
    if probe.stdout.strip() == str(SLICE_S):
        assert slices[0] == SLICE_S and slices[1] > SLICE_S
    else:
        assert slices[0] == slices[1]
    assert len(restarted) == 1
    assert status["counts"]["pen_process_restarts"] == 1
    assert after == before and len(before) > 10
    assert stopped == []
    assert "pen process died" in (tmp_path / "serve.err").read_text()


def test_connections_are_bounded_and_a_silent_one_is_closed(twin_service):
    """Idle connections without hello (1,100 once exhausted the file descriptors): beyond the limit they are
    closed at once, a silent one within the hello timeout, and a well-behaved client is still served."""
    import websockets

    from twin.live.service import HELLO_TIMEOUT, MAX_UNGREETED

    def rss_mb() -> float:
        status = Path(f"/proc/{twin_service.pid}/status").read_text()
        return int(next(x for x in status.splitlines() if x.startswith("VmRSS:")).split()[1]) / 1024

    async def session():
        idle = [await websockets.connect(twin_service.url) for _ in range(MAX_UNGREETED)]
        extra = await websockets.connect(twin_service.url)
        with pytest.raises(websockets.ConnectionClosed) as closed:
            await asyncio.wait_for(extra.recv(), 5)
        assert closed.value.rcvd.code == 1013
        before = rss_mb()
        for _ in range(300):  # a flood beyond the limit: each refused at once, nothing kept
            flood = await websockets.connect(twin_service.url)
            with pytest.raises(websockets.ConnectionClosed):
                await asyncio.wait_for(flood.recv(), 5)
        assert rss_mb() - before < 20, f"the service grew from {before:.0f} MB to {rss_mb():.0f} MB"
        for ws in idle:  # the silent ones go after HELLO_TIMEOUT
            with pytest.raises(websockets.ConnectionClosed):
                await asyncio.wait_for(ws.recv(), HELLO_TIMEOUT + 5)
        async with LiveClient(twin_service.url) as client:  # the slots are free again
            await first_approximation(client)
            # nested too deeply: an error, no traceback (to the pose port, where this client's poses came from)
            client.send_raw_datagram(b"[" * (MAX_DATAGRAM_BYTES - 1), to="pose")
            await expect_error(client, "malformed", "datagram")

    run(session())
    assert "Traceback" not in twin_service.stderr_path.read_text()
