"""Outputs never replace what is not a regular file (issue 40, attack 5): every writer goes through
twin.paths.replacing, which writes a FIFO with a reader (or a character device) in place, refuses a FIFO nobody
reads at once instead of waiting forever, and refuses a folder or a socket; `hil --out` onto a recorded run is
refused unless --overwrite."""

import json
import os
import socket
import stat
import subprocess
import threading
import time

import pytest

from controllers.pid import PidGains
from twin.commands.options import write_json
from twin.device.spec import SPEC_PATH
from twin.device.spec_toml import write_spec_toml
from twin.formats.gains import read_gains, write_gains
from twin.formats.scenario import Scenario, write_scenario
from twin.formats.sweep import write_sweep
from twin.formats.target import write_approximation
from twin.formats.trials import write_trials
from twin.paths import cli_command, cli_env, replacing
from twin.records.gains import Gains

WRITERS = {
    "gains": lambda p, spec: write_gains(p, Gains([PidGains.from_spec(spec)] * spec.n_hinges)),
    "scenario": lambda p, spec: write_scenario(p, Scenario("s", [0.0] * 6, [0.0], [[0.1] * 6], 1.0)),
    "spec": lambda p, spec: write_spec_toml(p, SPEC_PATH, {}, "test"),
    "trials": lambda p, spec: write_trials(p, [{"participant": "a", "condition": 1.0, "natural": True,
                                                "confidence": 3}], "mm"),
    "sweep": lambda p, spec: write_sweep(p, ["cube"], 1, 0, ["full"], {"flap_gap": [0.001]}),
    "json": lambda p, spec: write_json(str(p), {"a": 1}),
    "approximation": lambda p, spec: write_approximation(p, {}),
}


def _read_fifo(fd: int, got: list):
    """Read the FIFO (opened for reading by the test) until its writer has written and closed it."""
    os.set_blocking(fd, True)
    data, deadline = b"", time.monotonic() + 10
    while time.monotonic() < deadline:
        chunk = os.read(fd, 65536)
        if chunk:
            data += chunk
        elif data:
            break  # the writer wrote and closed
        else:
            time.sleep(0.01)  # no writer yet
    got.append(data)
    os.close(fd)


@pytest.mark.parametrize("writer", sorted(WRITERS))
def test_a_fifo_with_a_reader_is_written_in_place_and_stays_a_fifo(writer, tmp_path, spec):
    fifo = tmp_path / "out"
    os.mkfifo(fifo)
    got = []
    reader = threading.Thread(target=_read_fifo, args=(os.open(fifo, os.O_RDONLY | os.O_NONBLOCK), got), daemon=True)
    reader.start()
    WRITERS[writer](fifo, spec)
    reader.join(15)
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    assert not (tmp_path / "out.part").exists()
    assert got and got[0], "the reader got nothing"


@pytest.mark.parametrize("writer", sorted(WRITERS))
def test_a_fifo_nobody_reads_is_refused_at_once(writer, tmp_path, spec):
    fifo = tmp_path / "out"
    os.mkfifo(fifo)
    started = time.monotonic()
    with pytest.raises(ValueError, match="FIFO that nobody reads"):
        WRITERS[writer](fifo, spec)
    assert time.monotonic() - started < 5
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)


def test_a_character_device_is_written_in_place(tmp_path, spec):
    with replacing("/dev/null") as tmp:
        assert str(tmp) == "/dev/null"
    write_gains("/dev/null", Gains([PidGains.from_spec(spec)] * spec.n_hinges))
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


def test_a_folder_or_a_socket_is_refused(tmp_path, spec):
    (tmp_path / "folder").mkdir()
    server = socket.socket(socket.AF_UNIX)
    server.bind(str(tmp_path / "sock"))
    try:
        for name, kind in (("folder", "a folder"), ("sock", "a socket")):
            with pytest.raises(ValueError, match=kind):
                write_gains(tmp_path / name, Gains([PidGains.from_spec(spec)] * spec.n_hinges))
    finally:
        server.close()
    assert stat.S_ISSOCK(os.stat(tmp_path / "sock").st_mode)


def test_a_regular_file_is_still_replaced_whole(tmp_path, spec):
    path = tmp_path / "g.json"
    path.write_text("old")
    write_gains(path, Gains([PidGains.from_spec(spec)] * spec.n_hinges))
    assert len(read_gains(path, spec.n_hinges).hinges) == spec.n_hinges


@pytest.mark.slow
def test_the_command_line_refuses_a_fifo_nobody_reads_in_one_line(tmp_path):
    fifo = tmp_path / "scenario.toml"
    os.mkfifo(fifo)
    run = subprocess.run(cli_command("scenario", str(fifo)), env=cli_env(), capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 2 and "nobody reads" in run.stderr and len(run.stderr.splitlines()) == 1, run.stderr
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)


@pytest.mark.parametrize("status", ["complete", pytest.param("interrupted", marks=pytest.mark.slow)])
def test_hil_refuses_to_record_over_a_run(tmp_path, status):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    meta = json.dumps({"status": status, "scenario": "s"})
    (run_dir / "run.json").write_text(meta)
    scenario = tmp_path / "s.toml"
    write_scenario(scenario, Scenario("s", [0.0] * 6, [0.0], [[0.1] * 6], 1.0))
    # no device on this port: the refusal comes before the port is opened
    run = subprocess.run(cli_command("hil", str(scenario), "--serial", str(tmp_path / "no-such-port"), "--out",
                                     str(run_dir)), env=cli_env(), capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and "holds a run already" in run.stderr and status in run.stderr, run.stderr
    assert (run_dir / "run.json").read_text() == meta
    run = subprocess.run(cli_command("hil", str(scenario), "--serial", str(tmp_path / "no-such-port"), "--out",
                                     str(run_dir), "--overwrite"), env=cli_env(), capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 2 and "holds a run" not in run.stderr and "no-such-port" in run.stderr, run.stderr


def test_a_reader_that_reads_to_the_end_gets_the_whole_file(tmp_path, spec):
    """`cat FIFO > FILE` as the reader: it stops at the first end of input, so the writer's check for a reader
    must not be one (an open and a close of the FIFO once let cat finish empty and the write wait forever)."""
    fifo, copy = tmp_path / "out", tmp_path / "copy.json"
    os.mkfifo(fifo)
    with open(copy, "wb") as sink:
        cat = subprocess.Popen(["cat", str(fifo)], stdout=sink)
    try:
        done = []

        def write():
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:
                try:  # refused until cat has the FIFO open
                    write_gains(fifo, Gains([PidGains.from_spec(spec)] * spec.n_hinges))
                    done.append(True)
                    return
                except ValueError:
                    time.sleep(0.02)

        writer = threading.Thread(target=write, daemon=True)
        writer.start()
        writer.join(15)
        assert done, "the write did not finish"
        cat.wait(10)
    finally:
        cat.kill()
    assert len(read_gains(copy, spec.n_hinges).hinges) == spec.n_hinges
