"""The worker's pose stream (twin/live/poses.py) on a real datagram socket: the session, the newest pose, the
rate limit, the errors reported with their counts."""

import socket
import time

from twin.live.datagrams import stamped_socket
from twin.live.messages import APPROXIMATION_RATE_HZ, encode_sample
from twin.live.poses import RATE_BURST, PoseIntake

SESSION = "ab" * 16
START = ([10.0, 0.0, 190.0], [1.0, 0.0, 0.0, 0.0])


def _deliver(intake: PoseIntake, sender: socket.socket, receiver: socket.socket, *datagrams: bytes) -> None:
    """Send the datagrams and let the intake take them off its socket."""
    for data in datagrams:
        sender.sendto(data, receiver.getsockname())
    time.sleep(0.05)  # loopback: delivered by then
    intake.drain(receiver)


def test_the_newest_pose_of_the_session_goes_and_the_rest_are_counted():
    receiver, sender = stamped_socket("127.0.0.1"), socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sender.bind(("127.0.0.1", 0))
    with receiver, sender:
        intake = PoseIntake()
        _deliver(intake, sender, receiver, encode_sample("pose", SESSION, 0, *START))
        assert intake.pending is None and intake.counts["unknown_session"] == 1  # no controller yet
        intake.set_session(SESSION)
        sent = time.perf_counter()
        _deliver(intake, sender, receiver,
                 encode_sample("pose", "cd" * 16, 9, *START),  # another session's
                 *(encode_sample("pose", SESSION, seq, [10.0 + seq, 0, 190], START[1]) for seq in (3, 5, 4)),
                 encode_sample("pen", SESSION, 6, *START), b"{nope")
        values, addr, arrived, taken, parsed = intake.next(time.perf_counter())
        # the newest of 3, 5 (4 came after 5: stale); the other session's dropped; the gap between 3 and 5 counted
        assert (values[0], values[2]) == (5, 0.015) and addr == sender.getsockname()
        assert sent <= arrived <= taken <= parsed  # the kernel's arrival stamp, on the same clock
        assert {k: intake.counts[k] for k in ("pose", "superseded", "stale", "missing", "unknown_session",
                                              "unknown_type", "malformed")} == \
            {"pose": 2, "superseded": 1, "stale": 1, "missing": 1, "unknown_session": 2, "unknown_type": 1,
             "malformed": 1}
        # each code reported once, for this session, naming what went wrong
        reports = {code: (session, message, count) for session, code, message, count in intake.reports}
        assert set(reports) == {"stale", "unknown_type", "malformed"}
        assert reports["unknown_type"][0] == SESSION and "pose_port" in reports["unknown_type"][1]
        assert intake.next(time.perf_counter()) is None  # nothing pending


def test_the_rate_limit_lets_a_burst_through_then_the_rate():
    intake = PoseIntake()
    intake.set_session(SESSION)
    now = time.perf_counter() + 1.0  # the bucket full
    gone = 0
    for seq in range(10):
        intake.take(encode_sample("pose", SESSION, seq, *START), ("127.0.0.1", 1), now, now)
        if intake.next(now) is not None:
            gone += 1
    assert gone == RATE_BURST  # back to back, then the newest waits for a token
    wait = intake.wait_s(now)
    assert wait == 1.0 / APPROXIMATION_RATE_HZ
    later = now + wait * 1.001  # a token again (a hair later: rounding)
    assert intake.next(later)[0][0] == 9 and intake.wait_s(later) is None


def test_errors_are_reported_at_most_once_a_tenth_of_a_second_with_their_count():
    intake = PoseIntake()
    intake.set_session(SESSION)
    addr = ("127.0.0.1", 1)
    intake.take(encode_sample("pose", SESSION, 0, *START), addr, 0.0, 0.0)  # the controller's address known
    for _ in range(500):
        intake.take(b"{nope", addr, 0.0, 0.0)
    intake.take(b"{nope", ("127.0.0.1", 2), 0.0, 0.0)  # from elsewhere: counted, not reported
    time.sleep(0.11)
    intake.take(b"{nope", addr, 0.0, 0.0)
    assert [(code, count) for _, code, _, count in intake.reports] == [("malformed", 1), ("malformed", 500)]
    assert intake.counts["malformed"] == 502
