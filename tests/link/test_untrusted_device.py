"""The host trusts nothing the device says (issue 40, attack 3 and item 5): the emulator (the real C core on
its plant, on a real pty) with one lie injected into the bytes it sends or the commands it runs: a clock
glitch that stamps telemetry before the ACK, an ACK 2,000 s ahead, a restart mid-move, a STATE with state 99
and every fault bit, telemetry of 1 hinge, a STATE of 0 hinges, a HELLO with a 0 Hz loop, gains ACKed and
not kept. Each is a named DeviceUntrusted; where the hinges may be moving the device ends in ESTOP and the
host stops feeding its watchdog."""

import dataclasses
import multiprocessing
import os
import subprocess

import numpy as np
import pytest

from controllers import core
from controllers.program import ProgramEnd
from controllers.pid import PidGains
from twin.device.spec import load_spec
from twin.hil.mirror import mirror
from twin.link import protocol as P
from twin.link.emulator import Emulator, EmulatorOptions
from twin.link.faults import FaultOptions
from twin.link.pty_device import open_pty, serve
from twin.link.serial_link import DeviceUntrusted, Link, LinkError, on_pty
from twin.paths import cli_command, cli_env

TARGETS = np.radians([40.0, -30.0, 20.0, 20.0, -30.0, 40.0])


class LyingEmulator(Emulator):
    """The emulator, with `lie(emu, seq, msg)` applied to every message it sends (None: dropped) and
    `deaf(emu, seq, msg)` to every command it hears (a reply, or None to run it)."""

    def __init__(self, spec, log_path, lie=None, deaf=None):
        super().__init__(spec, EmulatorOptions(faults=FaultOptions(latency_ms=0.0), zeroed=True), log_path)
        self.lie, self.deaf = lie, deaf
        self.told, self.heard = P.Decoder(), P.Decoder()
        self.moving_since = None  # the tick the first SET_TARGETS was ACKed

    def receive(self, data: bytes) -> None:
        if self.deaf is None:
            return super().receive(data)
        for seq, msg in self.heard.feed(data):
            answer = self.deaf(self, seq, msg)
            if answer is None:
                super().receive(P.encode(msg, seq))
            else:
                self.out += P.encode(answer, seq)

    def take_output(self, max_bytes: int = 4096) -> bytes:
        out = bytearray()
        for seq, msg in self.told.feed(super().take_output(max_bytes)):
            if isinstance(msg, P.Ack) and msg.acked == P.MsgId.SET_TARGETS and self.moving_since is None:
                self.moving_since = self.tick
            said = self.lie(self, seq, msg) if self.lie else msg
            if said is not None:
                out += P.encode(said, seq)
        return bytes(out)


def _serve(fd, ready, stop, log_path, lie, deaf):
    emu = LyingEmulator(load_spec(), log_path, lie, deaf)
    ready.set()
    serve(emu, fd, stop.is_set)
    emu.close()


@pytest.fixture
def liar(tmp_path):
    """start(lie=None, deaf=None) -> (the pty's path, its log reader); the device process stopped after."""
    started = []

    def start(lie=None, deaf=None):
        master, slave, path = open_pty()
        ctx = multiprocessing.get_context("fork")
        stop, ready = ctx.Event(), ctx.Event()
        log = tmp_path / f"liar{len(started)}.jsonl"
        proc = ctx.Process(target=_serve, args=(master, ready, stop, str(log), lie, deaf), daemon=True)
        proc.start()
        started.append((proc, stop, master, slave))
        assert ready.wait(60), "the emulator did not start"

        def events(kind):
            import json
            return [e for e in map(json.loads, log.read_text().splitlines()) if e["event"] == kind]

        return path, events

    yield start
    for proc, stop, master, slave in started:
        stop.set()
        proc.join(5)
        if proc.is_alive():
            proc.kill()
        os.close(master)
        os.close(slave)


def _rx(events, name):
    return [e for e in events("rx") if e["msg"] == name]


def _e_stopped_and_unfed(events, link):
    """The device was e-stopped (its core says so) and heard no heartbeat after the host stopped trusting it."""
    stops = _rx(events, "ESTOP")
    assert stops, "no ESTOP"
    assert [e for e in events("fault") if e["fault"] == "ESTOP"]
    assert not [e for e in _rx(events, "HEARTBEAT") if e["t"] > stops[0]["t"] + 0.01]
    assert link.untrusted is not None


def _moving(emu, seconds):
    return emu.moving_since is not None and emu.tick - emu.moving_since >= seconds * 1000


def _telemetry_stamped_before_the_ack(emu, seq, msg):
    if isinstance(msg, P.Telemetry) and emu.moving_since is not None:
        return dataclasses.replace(msg, time_us=(msg.time_us - 5_000_000) & 0xFFFFFFFF)  # a clock glitch
    return msg


def _ack_2000_s_ahead(emu, seq, msg):
    if isinstance(msg, P.Ack) and msg.acked == P.MsgId.SET_TARGETS:
        return dataclasses.replace(msg, time_us=(msg.time_us + 2_000_000_000) & 0xFFFFFFFF)
    return msg


def _one_hinge_telemetry(emu, seq, msg):
    if isinstance(msg, P.Telemetry) and _moving(emu, 0.1):
        return dataclasses.replace(msg, counts=msg.counts[:1], targets=msg.targets[:1], duty=msg.duty[:1],
                                   current_ma=msg.current_ma[:1])
    return msg


@pytest.mark.parametrize("lie, words", [(_telemetry_stamped_before_the_ack, "clock went back"),
                                        pytest.param(_ack_2000_s_ahead, "clock ran ahead", marks=pytest.mark.slow),
                                        pytest.param(_one_hinge_telemetry, "TELEMETRY has 1 hinges",
                                                     marks=pytest.mark.slow)],
                         ids=["telemetry-before-ack", "ack-2000-s-ahead", "one-hinge-telemetry"])
def test_a_lie_mid_move_is_named_and_the_device_e_stopped(liar, spec, lie, words):
    port, events = liar(lie)
    with pytest.raises(DeviceUntrusted, match=words):
        with Link(port, hinges=spec.n_hinges) as link:
            mirror(link, spec, TARGETS, tolerance_deg=170.0)
    _e_stopped_and_unfed(events, link)


def _restart(emu, seq, msg):
    """0.2 s into the move the board browns out and starts again: a fresh core, its clock from 0, no zero."""
    if _moving(emu, 0.2) and not getattr(emu, "restarted", False):
        emu.restarted = True
        emu.tick = 0
        emu.firmware = core.Core(core.config_from_spec(emu.spec), [PidGains.from_spec(emu.spec)] * emu.spec.n_hinges,
                                 emu.plant.counts)
        emu.firmware.set_reset_reason(P.ResetReason.BROWNOUT)
    return msg


@pytest.mark.slow
def test_a_restart_mid_move_is_named(liar, spec):
    port, events = liar(_restart)
    with pytest.raises(DeviceUntrusted, match="clock went back"):
        with Link(port, hinges=spec.n_hinges) as link:
            mirror(link, spec, TARGETS, tolerance_deg=170.0)
    assert link.untrusted is not None
    heard = [e["msg"] for e in events("rx")]  # in order (the restarted device's clock, and its log's, began again)
    assert "ESTOP" in heard and "HEARTBEAT" not in heard[len(heard) - heard[::-1].index("ESTOP"):]


def _state_99_every_fault(emu, seq, msg):
    return dataclasses.replace(msg, state=99, faults=0xFFFF) if isinstance(msg, P.StateMsg) else msg


def _state_of_0_hinges(emu, seq, msg):
    if isinstance(msg, P.StateMsg):
        return dataclasses.replace(msg, counts=(), targets=(), integral=())
    return msg


@pytest.mark.parametrize("lie, words", [(_state_99_every_fault, "state 99"), (_state_of_0_hinges, "STATE has 0 hinges")],
                         ids=["state-99", "state-0-hinges"])
def test_a_state_out_of_range_is_named_and_nothing_moves(liar, spec, lie, words):
    port, events = liar(lie)
    with Link(port, hinges=spec.n_hinges) as link:
        with pytest.raises(DeviceUntrusted, match=words):
            mirror(link, spec, TARGETS)
        with pytest.raises(DeviceUntrusted):  # and it stays untrusted
            link.get_gains(0)
    assert not _rx(events, "SET_TARGETS")


def _keeps_its_gains(emu, seq, msg):
    if isinstance(msg, P.SetGains):
        return P.Ack(P.MsgId.SET_GAINS, emu.tick * 1000)
    return None


def test_gains_acked_and_not_kept_are_named(liar, spec):
    port, events = liar(deaf=_keeps_its_gains)
    with Link(port, hinges=spec.n_hinges) as link:
        with pytest.raises(DeviceUntrusted, match="ACKed hinge 2's gains"):
            link.set_gains(PidGains.from_spec(spec).replace(kp=0.05), hinge=2)


def _hello_0_hz(emu, seq, msg):
    return dataclasses.replace(msg, loop_rate_hz=0) if isinstance(msg, P.HelloReply) else msg


def test_a_hello_with_a_0_hz_loop_is_a_one_line_error(liar):
    port, _ = liar(_hello_0_hz)
    run = subprocess.run(cli_command("status", "--serial", port), env=cli_env(), capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 2, run.stderr
    assert "loop_rate_hz 0" in run.stderr and "Traceback" not in run.stderr and len(run.stderr.splitlines()) == 1


def _heard_program(emu, seq, msg):
    if isinstance(msg, P.Program):
        emu.programmed = emu.tick
    return None  # run it


def _drives_on(emu, seq, msg):
    """After PROGRAM, every PROGRAM_STATUS says it still runs, its ticks counting on past its timeout."""
    if isinstance(msg, P.ProgramStatus) and getattr(emu, "programmed", None) is not None:
        return dataclasses.replace(msg, end=int(ProgramEnd.RUNNING), ticks=emu.tick - emu.programmed)
    return msg


def _stands_still(emu, seq, msg):
    """After PROGRAM, every PROGRAM_STATUS says it still runs at tick 5: a loop that stopped."""
    if isinstance(msg, P.ProgramStatus) and getattr(emu, "programmed", None) is not None:
        return dataclasses.replace(msg, end=int(ProgramEnd.RUNNING), ticks=5)
    return msg


@pytest.mark.parametrize("lie, words", [(_drives_on, r"after 1\.3\d* s of its own time \(its end at 1\.3 s\): e-stopped"),
                                        (_stands_still, r"after 0\.005 s of its own time \(its end at 1\.3 s\): e-stopped")],
                         ids=["past-its-timeout", "ticks-stand-still"])
def test_a_program_that_does_not_end_is_e_stopped_by_the_devices_own_clock(liar, spec, lie, words):
    """The host times a program by the ticks the device reports (a loaded host's emulator may lag the host's
    clock): a program whose ticks run past its end, or stop advancing for PROGRAM_STILL_S, is e-stopped."""
    port, events = liar(lie, _heard_program)
    with Link(port, hinges=spec.n_hinges) as link:
        with pytest.raises(LinkError, match=words):
            link.run_program(0, ((0.15, 0.3),), (round(-1.0 / spec.rad_per_count), round(1.0 / spec.rad_per_count)))
    assert _rx(events, "ESTOP") and [e for e in events("fault") if e["fault"] == "ESTOP"]


def test_only_a_pseudo_terminal_is_taken_for_an_emulator_on_this_host(tmp_path):
    """A Link waits PTY_RETRIES on a pseudo-terminal (an emulator sharing the host's CPU), the 4 tries a real
    device answers within on anything else."""
    master, slave, path = open_pty()
    try:
        assert on_pty(path)
    finally:
        os.close(master)
        os.close(slave)
    (tmp_path / "file").write_text("")
    assert not any(on_pty(p) for p in (str(tmp_path / "file"), "/dev/null", "/dev/ttyUSB9", "socket://x:1"))


def test_a_blamed_hinge_before_hello_is_judged_by_the_frames_own_count():
    """A session's first frames may come before HELLO has said how many hinges there are (an e-stopped device's
    telemetry blaming the jammed hinge, still streaming): a blamed hinge within the frame's own counts is
    plausible, one past them is not. (The jam test of tests/hil/test_mount.py met the first as DeviceUntrusted.)"""
    link = Link("/dev/null")  # never opened: only its judgement of frames
    frame = P.Telemetry(0, P.State.ESTOP, 0, 2, (0,) * 6, (0,) * 6, (0,) * 6, (0,) * 6)
    assert link._implausible(1, frame) is None
    assert "blames hinge 6, of 6" in link._implausible(2, dataclasses.replace(frame, fault_hinge=6, time_us=10))
