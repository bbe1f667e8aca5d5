"""What grows in documented use is bounded (issue 40, attack 7): the link's telemetry queue when nobody reads
it (`status --watch` after a `mirror` left telemetry on grew 0.45 MB/s), a sweep worker's twins and CBS
simulators (300 drawn plants grew a worker from 0.9 to 3.7 GB)."""

import collections
import json
import re
import time

import numpy as np

from controllers.encoder import target_counts
from twin.cli import main as vrscroll

from twin.evaluation import sweep
from twin.link import serial_link
from twin.link.serial_link import Link


def test_telemetry_nobody_reads_is_kept_to_the_newest(emulator, monkeypatch):
    monkeypatch.setattr(serial_link, "TELEMETRY_KEPT", 100)  # 0.2 s at 500 Hz instead of 20 s
    emu = emulator()
    with Link(emu.port) as link:
        link.set_telemetry_rate(500)
        time.sleep(1.0)
        link.set_telemetry_rate(0)
        time.sleep(0.1)
        kept = link.drain_telemetry()
        received, unread = link.telemetry_received, link.telemetry_unread
    assert 300 < received and len(kept) == 100 and unread == received - 100
    seqs = [seq for seq, _ in kept]
    assert seqs == list(range(seqs[0], seqs[0] + 100))  # the newest, in order


def test_a_sweep_worker_keeps_at_most_max_cached(monkeypatch):
    monkeypatch.setattr(sweep, "MAX_CACHED", 3)
    cache, made = collections.OrderedDict(), []

    def make(k):
        made.append(k)
        return k * 10

    for k in [1, 2, 3, 1, 4, 5, 1, 2]:
        assert sweep.cached(cache, k, lambda: make(k)) == k * 10
        assert len(cache) <= 3
    assert made == [1, 2, 3, 4, 5, 2]  # 1 kept by its use; 2 and 3 the least recently used
    assert list(cache) == [5, 1, 2]


def test_status_watch_after_a_mirror_reads_the_device_live_and_keeps_telemetry_bounded(emulator, spec, monkeypatch,
                                                                                       capsys, tmp_path):
    """End to end on the emulator: the device left as a mirror leaves it, holding its targets and streaming
    telemetry at 500 Hz; `status --watch` then prints the held angles five times a second while the frames it
    never reads are kept to the newest TELEMETRY_KEPT (here 100), the rest dropped and counted in the session
    log's close."""
    monkeypatch.setattr(serial_link, "TELEMETRY_KEPT", 100)
    emu = emulator()
    angles = [12.0, 0.0, 0.0, 0.0, 0.0, -12.0]
    with Link(emu.port) as link:
        link.set_targets(target_counts(spec, np.radians(angles)))
        time.sleep(1.0)  # settled (0.3-0.5 s on this plant)
        link.set_telemetry_rate(500)
    log = tmp_path / "watch.jsonl"
    assert vrscroll(["status", "--serial", emu.port, "--watch", "1.5", "--log", str(log)]) == 0
    lines = re.findall(r"^t=\s*([\d.]+) s((?:\s+-?\d+\.\d){6})  deg  (\w+)$", capsys.readouterr().out, re.M)
    assert 5 <= len(lines) <= 9, lines  # 1.5 s at WATCH_PERIOD_S = 0.2
    times = [float(t) for t, _, _ in lines]
    assert times == sorted(times) and times[-1] <= 1.5  # (printed to 0.1 s)
    for _, deg, state in lines:  # the device holds the mirror's targets while the watch reads it
        assert np.allclose([float(x) for x in deg.split()], angles, atol=2.0), deg
        assert state in ("ACTIVE", "HOLDING"), state
    close = [e for e in map(json.loads, log.read_text().splitlines()) if e["event"] == "close"][-1]
    assert close["telemetry_received"] > 300  # streaming all along: 500 Hz for 1.5 s and more
    assert close["telemetry_unread"] == close["telemetry_received"] - 100
