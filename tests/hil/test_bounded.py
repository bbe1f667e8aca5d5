"""What grows in documented use is bounded (issue 40, attack 7): the link's telemetry queue when nobody reads
it (`status --watch` after a `mirror` left telemetry on grew 0.45 MB/s), a sweep worker's twins and CBS
simulators (300 drawn plants grew a worker from 0.9 to 3.7 GB)."""

import collections
import time

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
