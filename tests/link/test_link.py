"""The serial link, the gate and the live comparison, against the device emulator on a real pty.

Each test starts its own emulator process (`vrscroll emulate`) with the
imperfections or faults it needs, and talks to it through pyserial like to a
device on /dev/ttyACM0.
"""

import json
import re
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from controllers.core import FIRMWARE_VERSION
from controllers.encoder import target_counts
from twin.link import protocol as P
from twin.cli import main as vrscroll
from twin.sim.gate import GateRefused
from twin.link.serial_link import Link, LinkError, LinkTimeout, NackError
from twin.hil.mirror import mirror
from twin.sim.response import move_settle_time
from twin.sim.settle import SettleTracker

SAFE_DEG = [25.0, 10.0, 0.0, 0.0, -10.0, -25.0]


def session_log(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_round_trip_mirror_settles_and_matches_the_twin(emulator, spec, tmp_path):
    emu = emulator()
    log = tmp_path / "session.jsonl"
    targets = np.radians(SAFE_DEG)
    with Link(emu.port, log_path=log) as link:
        assert link.info.n_hinges == spec.n_hinges and link.info.watchdog_ms == 200
        result = mirror(link, spec, targets, tolerance_deg=5.0)
        state = link.get_state()
        lost = link.telemetry_lost
    assert result.ok, result.message
    assert result.report.passed
    # the device ends where it was sent, and never parted from the twin by more than the tolerance
    assert np.all(np.abs(np.asarray(state.counts) - target_counts(spec, targets)) <= spec.settle_band)
    assert result.max_deviation_deg.max() < 5.0
    assert state.state == P.State.ACTIVE and state.faults == 0
    # telemetry at 500 Hz: every frame arrived, in device time order, about 2 ms apart
    assert lost == 0 and result.frames >= 0.8 * result.elapsed * 500
    events = session_log(log)
    kinds = {e["event"] for e in events}
    assert {"open", "gate", "tx", "rx", "telemetry", "mirror_result", "close"} <= kinds
    sent = [e for e in events if e["event"] == "tx" and e["msg"] == "SET_TARGETS"]
    assert sent and sent[-1]["counts"] == target_counts(spec, targets).tolist()
    assert [e["counts"] for e in emu.events("rx") if e["msg"] == "SET_TARGETS"] == [sent[-1]["counts"]]
    # the frames as one Trace (telemetry_trace, the one conversion): the watch's final angle is the last frame's
    # encoder angle, and its settle time the settle rule's on the frames, fed as they came (twin.sim.settle, the
    # watch's own) and looking back over them (twin.sim.response, the reports')
    rec, tgt = result.telemetry, target_counts(spec, targets)
    assert len(rec.time) == result.frames and np.array_equal(rec.angle, rec.counts * spec.rad_per_count)
    assert np.degrees(rec.angle[-1]) == pytest.approx(result.final_deg, abs=1e-12)
    tracker = SettleTracker(tgt, spec.settle_band, spec.settle_hold, 1 / 500)
    fed = [s for t, c in zip(rec.time, rec.counts) if (s := tracker.feed(t, c)) is not None]
    assert fed == [result.settle_time]  # first settled on the last frame, where the watch stopped
    assert move_settle_time(spec, rec.time, rec.counts, tgt, start=0.0) == pytest.approx(result.settle_time, abs=1e-9)


@pytest.mark.parametrize("deg, check", [([60.0] * 6, "collision"), ([130.0, 0, 0, 0, 0, 0], "range")])
def test_unsafe_target_is_refused_and_never_reaches_the_device(emulator, spec, tmp_path, deg, check):
    emu = emulator()
    log = tmp_path / "session.jsonl"
    with Link(emu.port, log_path=log) as link:
        with pytest.raises(GateRefused) as refused:
            mirror(link, spec, np.radians(deg))
        link.get_state()  # the link is still fine
    failed = [c.name for c in refused.value.report.failed]
    assert check in failed
    assert check in str(refused.value)
    time.sleep(0.05)
    received = {e["msg"] for e in emu.events("rx")}
    assert "SET_TARGETS" not in received  # the emulator's own log: no target ever arrived
    assert {"HELLO", "GET_STATE", "GET_GAINS"} <= received
    assert any(e["event"] == "gate_refused" for e in session_log(log))


def test_cli_mirror_and_status(emulator, tmp_path, capsys):
    emu = emulator()
    log = str(tmp_path / "cli.jsonl")
    target = tmp_path / "target.json"
    target.write_text(json.dumps({"angles_deg": SAFE_DEG}))
    assert vrscroll(["mirror", str(target), "--serial", emu.port, "--log", log]) == 0
    assert "mirror: settled" in capsys.readouterr().out
    assert vrscroll(["mirror", "--angles=130,0,0,0,0,0", "--serial", emu.port, "--log", log]) == 2
    assert "range 130.000 deg over limit 112.500 deg (hinge 0)" in capsys.readouterr().err
    assert vrscroll(["status", "--serial", emu.port]) == 0
    out = capsys.readouterr().out
    assert f"firmware {'.'.join(map(str, FIRMWARE_VERSION))}" in out and "angles" in out and "faults" in out
    assert re.search(r"^integral( +-?\d+\.\d){6}  % duty", out, re.M), out


def test_a_device_of_another_protocol_version_is_named_as_such(emulator, monkeypatch):
    """A host and a device flashed apart (a version-3 device, a host that speaks 2): the device refuses every
    frame with a NACK in its own version, which the host cannot decode; it says so, not just "no reply"."""
    emu = emulator()
    monkeypatch.setattr(P, "PROTOCOL_VERSION", P.PROTOCOL_VERSION - 1)
    with pytest.raises(LinkTimeout, match=rf"answers in protocol version {P.PROTOCOL_VERSION + 1}, this host "
                                          rf"speaks {P.PROTOCOL_VERSION}: flash the firmware this host ships"):
        Link(emu.port).open()


def test_device_refuses_out_of_range_targets_itself(emulator, spec):
    emu = emulator()
    with Link(emu.port) as link:
        limit = int(spec.hinge_limit / spec.rad_per_count)
        with pytest.raises(NackError) as nack:
            link.set_targets([0, 0, limit + 50, 0, 0, 0])
        assert nack.value.reason == P.Nack.OUT_OF_RANGE and nack.value.detail == 2
        with pytest.raises(NackError):
            link.set_targets([0, 0])
    assert [e["reason"] for e in emu.events("nack")] == ["OUT_OF_RANGE", "BAD_LENGTH"]


@pytest.fixture
def device(emulator):
    emu = emulator()
    with Link(emu.port) as link:
        yield emu, link


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(garbage=st.binary(min_size=1, max_size=400))
def test_garbage_into_the_device_is_counted_and_the_link_recovers(device, garbage):
    emu, link = device
    before = link.get_state().rx_bad_frames
    link.write_raw(garbage)
    state = link.get_state()  # a garbled first try is retried with the same sequence number
    assert state.rx_bad_frames >= before
    assert emu.proc.poll() is None  # the device did not crash


def test_garbage_from_the_device_is_counted_and_the_link_recovers(emulator):
    emu = emulator("--corrupt", "0.05", "--seed", "3")
    with Link(emu.port, timeout=0.05, retries=8) as link:
        link.set_telemetry_rate(500)
        for _ in range(100):
            assert link.get_state().firmware == FIRMWARE_VERSION
        time.sleep(0.3)
        frames = link.drain_telemetry()
        assert link.decoder.bad_frames > 0
        assert len(frames) > 100  # telemetry still flows; damaged frames show as sequence gaps
        assert all(isinstance(f, P.Telemetry) for _, f in frames)
        assert link.telemetry_lost > 0


def test_watchdog_holds_then_stops_the_motors_when_the_host_goes_quiet(emulator, spec):
    """The host goes quiet: after the watchdog the device holds its targets (HOLDING) for the stated time,
    then releases (FAULT WATCHDOG, motors off); the hold shortened to 0.3 s here."""
    emu = emulator("--host-away-hold-ms", "300")
    with Link(emu.port) as link:
        state = link.get_state()
        link.set_telemetry_rate(500)
        link.set_targets(np.asarray(state.counts) + 30)  # a small move, then hold
        time.sleep(0.3)
        link.drain_telemetry()
        link.stop_heartbeat()
        quiet_from = time.monotonic()
        stopped = None
        held = []
        while time.monotonic() - quiet_from < 1.5:
            _, f = link.telemetry(timeout=0.5)
            held += [f] if f.state == P.State.HOLDING else []
            if f.faults & P.Fault.WATCHDOG:
                stopped = f
                break
        assert stopped is not None, "watchdog never tripped"
        assert stopped.state == P.State.FAULT and all(d == 0 for d in stopped.duty)
        assert held and all(f.targets == held[0].targets for f in held)
        host_delay = time.monotonic() - quiet_from
        after = [f for _, f in [link.telemetry(timeout=0.5) for _ in range(50)]]
        assert all(f.state == P.State.FAULT and all(d == 0 for d in f.duty) for f in after)
    away, fault = emu.events("host_away")[0], emu.events("fault")[0]
    assert fault["fault"] == "WATCHDOG"
    # device time from the last frame heard to the hold: the stated 200 ms, within one tick; then the hold
    assert 0.200 <= away["t"] - away["last_rx_t"] <= 0.200 + 2 * spec.firmware_dt
    assert 0.300 <= fault["t"] - away["t"] <= 0.300 + 2 * spec.firmware_dt
    assert host_delay < 0.8


def test_jammed_hinge_is_caught_by_the_live_comparison(emulator, spec, tmp_path):
    emu = emulator("--jam-hinge", "2", "--jam-after-s", "0.0")
    log = tmp_path / "session.jsonl"
    targets = np.radians([20.0, 10.0, 40.0, 0.0, -10.0, -20.0])
    with Link(emu.port, log_path=log) as link:
        result = mirror(link, spec, targets, tolerance_deg=5.0)
        state = link.get_state()
    assert result.outcome == "diverged" and result.hinge == 2, result.message
    assert "hinge 2 parted from the twin" in result.message
    assert result.elapsed < 0.2  # caught while moving, long before the device's own stall detector
    assert state.state == P.State.ESTOP
    assert any(e["msg"] == "ESTOP" for e in emu.events("rx"))


def test_port_disappearing_mid_run_is_a_clear_error_and_the_log_survives(emulator, tmp_path):
    emu = emulator()
    log = tmp_path / "session.jsonl"
    link = Link(emu.port, log_path=log).open()
    try:
        link.set_telemetry_rate(200)
        link.set_targets(link.get_state().counts)
        time.sleep(0.3)
        emu.kill()
        with pytest.raises(LinkError, match="port went away"):
            while True:
                link.telemetry(timeout=2.0)
        with pytest.raises(LinkError):
            link.get_state()
        received = link.telemetry_received
    finally:
        link.close()
    events = session_log(log)  # every line is whole JSON
    assert sum(e["event"] == "telemetry" for e in events) == received > 30
    assert [e["event"] for e in events if e["event"] == "link_error"] == ["link_error"]
    assert any(e["event"] == "tx" and e["msg"] == "SET_TARGETS" for e in events)


def test_a_device_that_stops_answering_times_out(emulator):
    emu = emulator("--drop-after-s", "0.5")
    with Link(emu.port, timeout=0.05, retries=2) as link:
        link.get_state()
        time.sleep(0.6)
        with pytest.raises(LinkTimeout, match="no reply to GET_STATE after 3 tries"):
            link.get_state()


def test_override_is_logged_and_the_device_limit_still_holds(emulator, tmp_path, capsys):
    emu = emulator()
    log = tmp_path / "override.jsonl"
    rc = vrscroll(["mirror", "--angles=130,0,0,0,0,0", "--serial", emu.port, "--log", str(log), "--override"])
    assert rc == 2
    assert "device refused SET_TARGETS: OUT_OF_RANGE (detail 0)" in capsys.readouterr().err
    events = session_log(log)
    assert any(e["event"] == "gate_override" and "range" in e["reason"] for e in events)
    assert [e["reason"] for e in emu.events("nack")] == ["OUT_OF_RANGE"]


@pytest.mark.parametrize("angles", ["nan,0,0,0,0,0", "1e308,0,0,0,0,0", "0,0,0,0,0,-inf"])
def test_mirror_override_refuses_angles_that_are_no_angles(emulator, tmp_path, capsys, angles):
    """Once a struct.error traceback: --override skipped the gate's range check and the count overflowed."""
    emu = emulator()
    rc = vrscroll(["mirror", f"--angles={angles}", "--serial", emu.port, "--log", str(tmp_path / "l.jsonl"),
                   "--override"])
    assert rc == 2
    err = capsys.readouterr().err
    assert err.startswith("vrscroll mirror: error: --angles") and len(err.splitlines()) == 1
    assert emu.events("nack") == [] and not any(e.get("msg") == "SET_TARGETS" for e in emu.events())


def test_a_second_host_on_the_same_port_is_refused_at_open(emulator):
    emu = emulator()
    with Link(emu.port) as first:
        with pytest.raises(LinkError, match="the port is in use"):
            Link(emu.port).open()
        assert first.get_state().state in (P.State.IDLE, P.State.ACTIVE)  # the first session goes on undisturbed
    with Link(emu.port) as again:  # and once it closed, the port is free
        assert again.get_state()


@pytest.mark.parametrize("mid", [0x00, 0x7E])
def test_an_unknown_message_id_is_refused_and_the_logging_emulator_lives_on(emulator, mid):
    import struct

    emu = emulator()
    payload = struct.pack("<BBH", P.PROTOCOL_VERSION, mid, 7)
    frame = P.cobs_encode(payload + struct.pack("<H", P.crc16(payload))) + b"\x00"
    with Link(emu.port) as link:
        link.write_raw(frame)
        time.sleep(0.2)
        assert link.get_state().state is not None  # still answering
    assert emu.proc.poll() is None
    assert any(e.get("msg") == f"0x{mid:02X}" for e in emu.events("nack"))


@pytest.mark.parametrize("option", [["--watchdog-ms", "-1"], ["--watchdog-ms", "70000"], ["--speed-scale", "0"],
                                    ["--corrupt", "5"], ["--drop-after-s", "-1"], ["--backlash-deg", "1e9"],
                                    ["--latency-ms", "nan"]])
def test_emulator_options_out_of_range_are_refused(option, capsys):
    assert vrscroll(["emulate", *option]) == 2
    err = capsys.readouterr().err
    assert option[0] in err and "Traceback" not in err


def test_a_looped_back_line_is_named_not_taken_for_a_device(capsys):
    """The host's own HELLO echoed with its sequence number is not a HELLO_REPLY (it once ended in an
    AttributeError on every command)."""
    with pytest.raises(LinkTimeout, match="looped-back"):
        Link("loop://", timeout=0.05, retries=1).open()
    assert vrscroll(["status", "--serial", "loop://"]) == 2
    err = capsys.readouterr().err
    assert "looped-back" in err and "Traceback" not in err


def test_a_reply_for_another_command_is_not_taken():
    ack_for_hello = P.Ack(acked=int(P.MsgId.ESTOP), time_us=0)
    assert not P.answers(P.MsgId.HELLO, ack_for_hello) and not P.answers(P.MsgId.SET_TARGETS, ack_for_hello)
    assert P.answers(P.MsgId.ESTOP, ack_for_hello)
    assert P.answers(P.MsgId.HELLO, P.NackMsg(acked=int(P.MsgId.HELLO), reason=1, detail=0))
    assert not P.answers(P.MsgId.HELLO, P.Ack(acked=int(P.MsgId.HELLO), time_us=0))  # HELLO wants its data


def test_a_gains_push_interrupted_half_way_leaves_the_device_as_it_was(emulator, spec):
    """Ctrl-C during a push once left hinge 0 with the new gains and the others with the old."""
    from twin.hil.device_gains import device_gains, push_gains

    emu = emulator()
    with Link(emu.port) as link:
        before = device_gains(link, spec.n_hinges)
        new = [g.replace(kp=g.kp * 0.8) for g in before]
        send = link.set_gains
        calls = []

        def interrupted_at_hinge_2(gains, hinge):
            calls.append(hinge)
            if len(calls) == 3:  # the third hinge of the push: the user presses Ctrl-C
                raise KeyboardInterrupt
            return send(gains, hinge=hinge)

        link.set_gains = interrupted_at_hinge_2
        with pytest.raises(KeyboardInterrupt):
            push_gains(link, new, spec.n_hinges)
        link.set_gains = send
        after = device_gains(link, spec.n_hinges)
    assert [a.kp for a in after] == pytest.approx([b.kp for b in before], rel=1e-3)


def test_the_devices_own_configuration_wins_and_is_said(emulator, capsys, spec):
    emu = emulator("--watchdog-ms", "400")
    assert vrscroll(["status", "--serial", emu.port]) == 0
    out = capsys.readouterr().out
    assert f"the device's watchdog is 400 ms, the profile's spec says {spec.watchdog * 1e3:g} ms" in out
    with pytest.raises(LinkError, match="the device has 6 hinges, the spec this host uses 5"):
        Link(emu.port, hinges=5).open()


def test_a_fifo_as_the_target_is_refused_not_waited_on(tmp_path, capsys):
    import os

    fifo = tmp_path / "target.json"
    os.mkfifo(fifo)
    assert vrscroll(["mirror", str(fifo), "--serial", "/dev/null"]) == 2
    assert "not a regular file" in capsys.readouterr().err
