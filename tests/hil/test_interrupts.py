"""Ctrl-C, SIGTERM, SIGHUP, SIGQUIT or a closed terminal in a command that moves the device: the device is
e-stopped before the command ends, never left driving toward its targets until the watchdog (the emulator's
log shows the ESTOP, and the device, asked afterwards, is in ESTOP)."""

import os
import pty
import signal
import subprocess
import time

import pytest

from twin.commands.interrupts import STOP_SIGNALS
from twin.link import protocol as P
from twin.formats.scenario import scenario_of_steps, write_scenario
from twin.link.serial_link import Link
from twin.paths import cli_command, cli_env

LONG = scenario_of_steps("long", [(0.0, [30, 20, 10, 10, 20, 30]), (3.0, [5, 40, 25, 0, -10, 60])], 6.0)


def _rx(emu, name: str) -> list[dict]:
    return [e for e in emu.events("rx") if e["msg"] == name]


MIRROR = ["mirror", "--angles=60,-45,20,30,90,-100", "--settle-limit-s", "5", "--tolerance-deg", "170"]


def _start_moving(args, emu, tmp_path, within_s: float = 60.0, **popen):
    """The command started on the emulator, once its targets are in (within within_s) and the hinges moving:
    (process, the device time the targets arrived)."""
    # the stop signals as a terminal gives them, whatever this run inherited: a suite started in the background by a
    # non-interactive shell has SIGINT ignored, one under nohup SIGHUP, and a child that starts so never sees them
    preexec = popen.pop("preexec_fn", None) or (lambda: [signal.signal(s, signal.SIG_DFL) for s in STOP_SIGNALS])
    proc = subprocess.Popen(cli_command(*args, "--serial", emu.port, "--log", str(tmp_path / "session.jsonl")),
                            env=cli_env(), stderr=subprocess.PIPE, text=True, preexec_fn=preexec,
                            **{"stdout": subprocess.DEVNULL, **popen})
    deadline = time.monotonic() + within_s
    while not _rx(emu, "SET_TARGETS") and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.02)
    assert _rx(emu, "SET_TARGETS"), proc.stderr.read() if proc.poll() is not None else "no targets sent"
    time.sleep(0.1)  # moving now
    assert proc.poll() is None, proc.stderr.read()
    return proc, _rx(emu, "SET_TARGETS")[-1]["t"]


def _signalled(proc, sig) -> int:
    """Send sig to the command and wait for it (killed if it has not ended in 20 s); its exit status."""
    try:
        proc.send_signal(sig)
        return proc.wait(20)
    finally:
        proc.kill()


def _assert_e_stopped(emu, moved_at):
    """The ESTOP arrived after the targets (none of the command's own before), the device stopped in that
    tick, and the device, asked now, is in ESTOP."""
    assert not _rx(emu, "ESTOP") or _rx(emu, "ESTOP")[0]["t"] >= moved_at  # no e-stop of its own before
    estops = [e for e in _rx(emu, "ESTOP") if e["t"] >= moved_at]
    assert estops, "the device was not e-stopped"
    # stopped within one tick of the ESTOP's arrival: the core's fault is logged in the tick the frame came in
    stopped = [e for e in emu.events("fault") if e["fault"] == "ESTOP"]
    assert stopped and stopped[0]["t"] - estops[0]["t"] <= 0.001 + 1e-9, (estops[0], stopped)
    with Link(emu.port) as link:
        assert link.get_state().state == P.State.ESTOP


@pytest.mark.parametrize("command", ["mirror", "hil"])
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_an_interrupt_e_stops_the_device(command, sig, emulator, tmp_path):
    emu = emulator("--speed-scale", "0.3")  # slow: the move is still under way when interrupted
    scenario = tmp_path / "s.toml"
    write_scenario(scenario, LONG)
    # a tolerance no slow plant exceeds: the command is still watching the move when the signal comes
    args = {"mirror": MIRROR, "hil": ["hil", str(scenario), "--out", str(tmp_path / "run"), "--tolerance-deg", "170"]}
    proc, moved_at = _start_moving(args[command], emu, tmp_path)
    assert _signalled(proc, sig) == 130, proc.stderr.read()
    _assert_e_stopped(emu, moved_at)
    assert "interrupted" in proc.stderr.read()


@pytest.mark.slow  # the experiments run first: 40-60 s
def test_calibrate_serial_interrupted_in_its_held_out_run_e_stops_the_device(emulator, tmp_path):
    """calibrate --serial's held-out run (closed loop, after the open-loop experiments) moves the device under
    targets: SIGTERM there e-stops it, as in any other command that moves it."""
    emu = emulator("--lying-flat", "--speed-scale", "0.3")
    proc, moved_at = _start_moving(["calibrate"], emu, tmp_path, within_s=240)
    assert _signalled(proc, signal.SIGTERM) == 130, proc.stderr.read()
    _assert_e_stopped(emu, moved_at)


@pytest.mark.parametrize("sig", [signal.SIGHUP, pytest.param(signal.SIGQUIT, marks=pytest.mark.slow)],
                         ids=["SIGHUP", "SIGQUIT"])
def test_a_closed_terminal_or_ctrl_backslash_e_stops_the_device(sig, emulator, tmp_path):
    """SIGHUP (the terminal closed) and SIGQUIT (Ctrl-\\) used to end `mirror` at once, the device ACTIVE."""
    emu = emulator("--speed-scale", "0.3")
    proc, moved_at = _start_moving(MIRROR, emu, tmp_path)
    assert _signalled(proc, sig) == 130, proc.stderr.read()
    _assert_e_stopped(emu, moved_at)


@pytest.mark.slow
def test_losing_the_terminal_e_stops_the_device(emulator, tmp_path):
    """`mirror` on a terminal of its own (a pty, its controlling terminal, its output going there) that is
    closed mid-move: the kernel hangs it up, and the device is e-stopped."""
    emu = emulator("--speed-scale", "0.3")
    master, slave = pty.openpty()
    name = os.ttyname(slave)

    def own_terminal():
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        os.setsid()  # a session of its own, whose controlling terminal is the pty: closing it hangs up the session
        os.close(os.open(name, os.O_RDWR))

    proc, moved_at = _start_moving(MIRROR, emu, tmp_path, preexec_fn=own_terminal, stdout=slave)
    os.close(slave)
    try:
        os.close(master)  # the window closed
        proc.wait(20)
    finally:
        proc.kill()
    _assert_e_stopped(emu, moved_at)


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGHUP, signal.SIGTERM], ids=["SIGHUP", "SIGTERM"])
def test_the_live_service_e_stops_a_device_it_moved_as_it_stops(sig, emulator, tmp_path):
    """`serve --serial`: a morph sent, then the service stopped by a signal: the device is e-stopped, not left
    holding its last targets unwatched."""
    import asyncio

    from twin.live.client import LiveClient, LiveError
    from twin.live.process import ServiceProcess

    emu = emulator("--speed-scale", "0.3")
    with ServiceProcess("--shape", "cylinder", "--serial", emu.port, "--log", str(tmp_path / "session.jsonl"),
                        stderr_path=tmp_path / "serve.err") as service:
        async def morph():
            async with LiveClient(service.url) as client:
                for _ in range(20 * 90):  # the cylinder's start at 90 Hz until an approximation comes back
                    client.send_pose([10.0, 0.0, 190.0], [1.0, 0.0, 0.0, 0.0])
                    try:
                        await client.datagram("approximation", timeout=1 / 90)
                        break
                    except LiveError:
                        pass
                await client.lock()
                await client.expect("progress", timeout=20)

        asyncio.run(morph())
        moved_at = _rx(emu, "SET_TARGETS")[-1]["t"]
        service.proc.send_signal(sig)
        service.proc.wait(20)
    _assert_e_stopped(emu, moved_at)
