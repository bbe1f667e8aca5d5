"""The C core under any byte stream (issue 40, item 5): noise, one endless frame, a stream of frames of another
protocol version. Its receive buffer stays bounded and it answers the next intact frame after a 0x00; only this
protocol version's frames feed its watchdog. (The emulator on its pty under a 1 MB/s flood:
benchmarks/bench_emulator_flood.py.)"""

import numpy as np
import pytest

from controllers import core
from controllers.pid import PidGains
from twin.link import protocol as P

from raw_frames import frame, parse

STATE_ID = 0x83


def _core(spec):
    c = core.Core(core.config_from_spec(spec), [PidGains.from_spec(spec)] * spec.n_hinges, [0] * spec.n_hinges)
    c.mark_zero_confirmed()
    return c


FLOODS = {
    "noise": lambda rng, n: rng.integers(0, 256, n, dtype=np.uint8).tobytes(),
    "no delimiter": lambda rng, n: rng.integers(1, 256, n, dtype=np.uint8).tobytes(),
}


@pytest.mark.parametrize("kind", sorted(FLOODS))
def test_the_core_answers_through_a_flood(spec, kind):
    c = _core(spec)
    rng = np.random.default_rng(1)
    t = 0
    for k in range(200):  # 200 kB in 1 kB pieces, a GET_STATE after every tenth
        t += 1000
        c.rx(FLOODS[kind](rng, 1000), t)
        c.tick(t, [0] * spec.n_hinges)
        if k % 10 == 9:
            c.rx(frame(0x05, 1000 + k), t)  # frame() starts with a 0x00: the noise before it ends there
            got = [seq for mid, seq, _ in parse(c.tx()) if mid == STATE_ID]
            assert got == [1000 + k], k
    assert c.rx_bad_frames > 0


def test_frames_of_another_version_do_not_feed_the_watchdog(spec):
    """An intact SET_TARGETS of version 2 every 10 ms is answered (NACK BAD_VERSION) but leaves the device to
    its watchdog: HOLDING 200 ms after the last frame of this version."""
    c = _core(spec)
    c.rx(frame(0x03, 1, bytes([spec.n_hinges]) + b"\x00" * 4 * spec.n_hinges), 0)
    assert c.state == P.State.ACTIVE
    other = bytearray(P.encode(P.GetState(), 2))
    payload = bytearray(P.cobs_decode(bytes(other[:-1])))
    payload[0] = P.PROTOCOL_VERSION - 1
    payload[-2:] = P.crc16(bytes(payload[:-2])).to_bytes(2, "little")
    other = b"\x00" + P.cobs_encode(bytes(payload)) + b"\x00"
    for t in range(1000, 400_001, 1000):
        if t % 10_000 == 0:
            c.rx(other, t)
        c.tick(t, [t // 5000] * spec.n_hinges)
        if c.state != P.State.ACTIVE:
            break
    assert c.state == P.State.HOLDING and 200_000 < t <= 202_000, (c.state, t)
    reasons = [body[1] for mid, _, body in parse(c.tx()) if mid == 0x81]  # NACK: acked_id, reason, detail
    assert reasons and set(reasons) == {P.Nack.BAD_VERSION}
