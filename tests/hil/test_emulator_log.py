"""The emulator's log under a flood of frames each answered with a NACK (frames of another protocol version):
it reads a bounded number of the firmware's answers a tick and counts the rest, so the work per tick stays
bounded; the count is complete, and what follows the flood is logged again."""

import json
import struct

from twin.link import protocol as P
from twin.link.emulator import LOG_FRAMES_PER_TICK, Emulator, EmulatorOptions


def _other_version_frames(n: int) -> bytes:
    payload = struct.pack("<BBH", P.PROTOCOL_VERSION - 1, P.MsgId.SET_TARGETS, 7) + bytes([6]) + b"\x01" * 24
    return (P.cobs_encode(payload + struct.pack("<H", P.crc16(payload))) + b"\x00") * n


def test_a_flood_of_nacked_frames_is_counted_not_read_frame_by_frame(spec, tmp_path):
    log = tmp_path / "emulator.jsonl"
    emu = Emulator(spec, EmulatorOptions(zeroed=True), log_path=str(log))
    answers = P.Decoder()
    nacks = 0
    ticks = int(1.2 / emu.dt)  # past the once-a-second count
    for _ in range(ticks):
        emu.receive(_other_version_frames(30))  # 1 kB a tick: 1 MB/s at 1 kHz
        emu.step()
        nacks += sum(isinstance(m, P.NackMsg) for _, m in answers.feed(emu.take_output()))
    limit = int(spec.hinge_limit / spec.rad_per_count)
    emu.receive(P.encode(P.SetTargets([0, 0, limit + 50, 0, 0, 0]), 9))  # the flood over: one refusal
    for _ in range(20):
        emu.step()
        nacks += sum(isinstance(m, P.NackMsg) for _, m in answers.feed(emu.take_output()))
    emu.close()
    events = [json.loads(line) for line in log.read_text().splitlines()]
    logged = [e for e in events if e["event"] == "nack"]
    unlogged = [e["frames"] for e in events if e["event"] == "tx_unlogged"]
    assert nacks > 20 * ticks  # the firmware answered nearly every frame
    assert len(logged) + sum(unlogged) == nacks  # every answer logged or counted
    assert len(unlogged) >= 2  # counted once a second, the rest at the end
    per_tick = {}
    for e in logged:
        per_tick[e["t"]] = per_tick.get(e["t"], 0) + 1
    assert max(per_tick.values(), default=0) <= LOG_FRAMES_PER_TICK
    assert logged[-1]["reason"] == "OUT_OF_RANGE" and logged[-1]["seq"] == 9  # read again once the flood ended
