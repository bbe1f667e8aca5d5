"""An ESTOP always runs: a late retry of one (same seq, same bytes) after CLEAR_FAULT and new targets leaves
the device in ESTOP, never answered from the replies kept for repeats. Frames are built here from
docs/protocol.md alone (COBS, CRC-16/CCITT-FALSE, the header and bodies as the tables give them), not with the
host's encoder, and sent to the C core, the emulator tick by tick (core and sketch) and the emulator on a pty."""

import os
import select
import struct
import time

import pytest

from controllers import core
from controllers.pid import PidGains
from twin.link.emulator import Emulator, EmulatorOptions
from twin.link.faults import FaultOptions
from twin.sim.plant import as_twin

from raw_frames import frame, parse, uncobs

HELLO, SET_TARGETS, GET_STATE, ESTOP, CLEAR_FAULT = 0x01, 0x03, 0x05, 0x06, 0x07
ACK, STATE = 0x80, 0x83
IDLE, ACTIVE, ESTOP_STATE = 0, 1, 2


def targets(counts) -> bytes:
    return struct.pack(f"<B{len(counts)}i", len(counts), *counts)


def state_of(replies) -> int:
    """STATE's `state` (after fw_major, fw_minor, fw_patch)."""
    (body,) = [b for mid, _, b in replies if mid == STATE]
    return body[3]


def the_sequence(n: int):
    """(frame, what the device's state must be after it): an ESTOP under seq 7, CLEAR_FAULT, new targets,
    then the ESTOP's late retry, byte for byte, well within the 1 s repeats are kept."""
    estop = frame(ESTOP, 7)
    return [(frame(SET_TARGETS, 5, targets([40] * n)), ACTIVE), (estop, ESTOP_STATE),
            (frame(CLEAR_FAULT, 8), IDLE), (frame(SET_TARGETS, 9, targets([-60] * n)), ACTIVE),
            (estop, ESTOP_STATE)]


def test_the_core_runs_a_late_estop_retry(spec):
    c = core.Core(core.config_from_spec(spec), [PidGains.from_spec(spec)] * spec.n_hinges, [0] * spec.n_hinges)
    c.mark_zero_confirmed()
    t = 1000
    for k, (f, want) in enumerate(the_sequence(spec.n_hinges)):
        c.rx(f, t)
        c.tick(t, [0] * spec.n_hinges)
        c.rx(frame(GET_STATE, 100 + k), t + 10)
        got = parse(c.tx())
        assert state_of(got) == want, k
        t += 50_000
    acks = [struct.unpack("<BI", b) for mid, seq, b in got if mid == ACK and seq == 7]
    assert acks == [(ESTOP, t - 50_000)]  # run again now: its own ACK, not the kept one of the first ESTOP


@pytest.mark.parametrize("sketch", [False, True], ids=["core", "sketch"])
def test_the_emulator_runs_a_late_estop_retry(spec, sketch):
    emu = Emulator(spec, EmulatorOptions(plant=as_twin(spec), faults=FaultOptions(latency_ms=0.0), zeroed=True,
                                         sketch=sketch))
    for k, (f, want) in enumerate(the_sequence(spec.n_hinges)):
        emu.receive(f)
        for _ in range(20):
            emu.step()
        emu.receive(frame(GET_STATE, 100 + k))
        for _ in range(20):
            emu.step()
        assert state_of(parse(emu.take_output())) == want, k


def test_the_emulator_on_its_pty_runs_a_late_estop_retry(spec, emulator):
    emu = emulator()
    fd = os.open(emu.port, os.O_RDWR | os.O_NOCTTY)
    try:
        import termios
        import tty
        tty.setraw(fd)
        attrs = termios.tcgetattr(fd)
        attrs[3] &= ~termios.ECHO
        termios.tcsetattr(fd, termios.TCSANOW, attrs)

        def ask(f: bytes, want_id: int, seq: int) -> bytes:
            os.write(fd, f)
            got, deadline = b"", time.monotonic() + 3.0
            while time.monotonic() < deadline:
                if select.select([fd], [], [], 0.05)[0]:
                    got += os.read(fd, 4096)
                    match = [b for mid, s, b in parse(got) if mid == want_id and s == seq]
                    if match:
                        return match[0]
            raise AssertionError(f"no reply {want_id:#x} to seq {seq}")

        ask(frame(HELLO, 1), 0x82, 1)
        for k, (f, want) in enumerate(the_sequence(spec.n_hinges)):
            seq = struct.unpack("<H", uncobs(f.strip(b"\x00"))[2:4])[0]
            ask(f, ACK, seq)
            assert ask(frame(GET_STATE, 100 + k), STATE, 100 + k)[3] == want, k
    finally:
        os.close(fd)
