"""Ctrl-C or SIGTERM in a command that moves the device: the device is e-stopped before the command ends,
never left driving toward its targets until the watchdog (the emulator's log shows the ESTOP)."""

import signal
import subprocess
import time

import pytest

from twin.paths import cli_command, cli_env

LONG = """name = "long"
duration_s = 6.0
[[step]]
t_s = 0.0
angles_deg = [30, 20, 10, 10, 20, 30]
[[step]]
t_s = 3.0
angles_deg = [5, 40, 25, 0, -10, 60]
"""


def _rx(emu, name: str) -> list[dict]:
    return [e for e in emu.events("rx") if e["msg"] == name]


@pytest.mark.parametrize("command", ["mirror", "hil"])
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_an_interrupt_e_stops_the_device(command, sig, emulator, tmp_path):
    emu = emulator("--speed-scale", "0.3")  # slow: the move is still under way when interrupted
    scenario = tmp_path / "s.toml"
    scenario.write_text(LONG)
    # a tolerance no slow plant exceeds: the command is still watching the move when the signal comes
    args = {"mirror": ["mirror", "--angles=60,-45,20,30,90,-100", "--settle-limit-s", "5", "--tolerance-deg", "170"],
            "hil": ["hil", str(scenario), "--out", str(tmp_path / "run"), "--tolerance-deg", "170"]}[command]
    # SIGINT as a terminal gives it, whatever this run inherited: a suite started in the background by a
    # non-interactive shell has SIGINT ignored, and a child that starts so never sees Ctrl-C
    proc = subprocess.Popen(cli_command(*args, "--serial", emu.port, "--log", str(tmp_path / "session.jsonl")),
                            env=cli_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 60
        while not _rx(emu, "SET_TARGETS") and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.02)
        assert _rx(emu, "SET_TARGETS"), proc.stderr.read() if proc.poll() is not None else "no targets sent"
        time.sleep(0.1)  # moving now
        assert proc.poll() is None, proc.stderr.read()
        moved_at = _rx(emu, "SET_TARGETS")[-1]["t"]
        proc.send_signal(sig)
        rc = proc.wait(20)
    finally:
        proc.kill()
    assert rc == 130, proc.stderr.read()
    assert not _rx(emu, "ESTOP") or _rx(emu, "ESTOP")[0]["t"] >= moved_at  # no e-stop of its own before
    estops = [e for e in _rx(emu, "ESTOP") if e["t"] >= moved_at]
    assert estops, "the device was not e-stopped"
    # stopped within one tick of the ESTOP's arrival: the core's fault is logged in the tick the frame came in
    stopped = [e for e in emu.events("fault") if e["fault"] == "ESTOP"]
    assert stopped and stopped[0]["t"] - estops[0]["t"] <= 0.001 + 1e-9, (estops[0], stopped)
    assert "interrupted" in proc.stderr.read()
