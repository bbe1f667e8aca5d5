"""The C firmware core's supervisor, through its serial bytes and its control tick: refusals that
change nothing, the watchdog, repeated commands, stall, limit, overcurrent, e-stop, telemetry."""

import dataclasses
import struct

import numba
import numpy as np
import pytest

from controllers import core
from controllers.pid import GAIN_BOUNDS, PidGains
from twin.link import protocol as P


def make(spec, zeroed: bool = True, counts=None, **config) -> core.Core:
    """A core with the spec's config (config's fields changed), started at counts (default 0), its zero
    confirmed there unless zeroed=False."""
    cfg = core.config_from_spec(spec)
    for k, v in config.items():
        setattr(cfg, k, v)
    c = core.Core(cfg, [PidGains.from_spec(spec)] * spec.n_hinges, counts or [0] * spec.n_hinges)
    if zeroed:
        c.mark_zero_confirmed()
    return c


def replies(c: core.Core) -> list:
    return P.Decoder().feed(c.tx())


def ask(c: core.Core, msg, seq: int = 1, now_us: int = 0):
    c.rx(P.encode(msg, seq), now_us)
    (got,) = replies(c)
    return got


def raw(version: int, mid: int, seq: int, body: bytes) -> bytes:
    payload = struct.pack("<BBH", version, mid, seq) + body
    return P.cobs_encode(payload + struct.pack("<H", P.crc16(payload))) + b"\x00"


def snapshot(c: core.Core) -> tuple:
    return (c.state, c.faults, c.fault_hinge, tuple(c.targets), tuple(c.gains(k) for k in range(c.n)),
            c.rx_bad_frames)


def limit(spec) -> int:
    return core.config_from_spec(spec).limit_counts


# ---- refusals: a NACK with its reason, and nothing changed --------------------------------------

def _bad_gains(spec):
    ok = P.Gains.from_pid(PidGains.from_spec(spec))
    return [("kp", ok.__class__(**{**ok.__dict__, "kp": 2**31 - 1})),  # 214 duty per count
            ("kp<0", ok.__class__(**{**ok.__dict__, "kp": -1})),
            ("ki", ok.__class__(**{**ok.__dict__, "ki": 10 * P.GAIN_SCALE + 100})),
            ("kd", ok.__class__(**{**ok.__dict__, "kd": int(0.05 * P.GAIN_SCALE) + 1})),
            ("cutoff0", ok.__class__(**{**ok.__dict__, "cutoff": 0})),
            ("cutoff", ok.__class__(**{**ok.__dict__, "cutoff": 4501})),
            ("integral_limit", ok.__class__(**{**ok.__dict__, "integral_limit": 2 * P.DUTY_SCALE})),
            ("deadband", ok.__class__(**{**ok.__dict__, "deadband": P.DUTY_SCALE // 2 + 2})),
            ("hold_band", ok.__class__(**{**ok.__dict__, "hold_band": 51}))]


def refusals(spec):
    n, lim = spec.n_hinges, limit(spec)
    out = [("target beyond +range", P.encode(P.SetTargets((0, 0, lim + 1, 0, 0, 0)), 9), P.MsgId.SET_TARGETS,
            P.Nack.OUT_OF_RANGE, 2),
           ("target beyond -range", P.encode(P.SetTargets((-lim - 1,) + (0,) * (n - 1)), 9), P.MsgId.SET_TARGETS,
            P.Nack.OUT_OF_RANGE, 0),
           ("five targets", P.encode(P.SetTargets((1,) * 5), 9), P.MsgId.SET_TARGETS, P.Nack.BAD_LENGTH, 5),
           ("targets body short", raw(P.PROTOCOL_VERSION, 0x03, 9, bytes([6]) + b"\x01" * 20), P.MsgId.SET_TARGETS,
            P.Nack.BAD_LENGTH, 6),
           ("gains body short", raw(P.PROTOCOL_VERSION, 0x04, 9, b"\xff" * 19), P.MsgId.SET_GAINS, P.Nack.BAD_LENGTH, 0),
           ("hello with a body", raw(P.PROTOCOL_VERSION, 0x01, 9, b"\x01"), P.MsgId.HELLO, P.Nack.BAD_LENGTH, 0),
           ("another protocol version", raw(P.PROTOCOL_VERSION + 1, 0x03, 9, bytes([n]) + b"\x01" * 4 * n),
            P.MsgId.SET_TARGETS, P.Nack.BAD_VERSION, P.PROTOCOL_VERSION),
           ("unknown id 0x55", raw(P.PROTOCOL_VERSION, 0x55, 9, b""), 0x55, P.Nack.UNKNOWN_MESSAGE, 0),
           ("telemetry rate over the maximum", P.encode(P.SetTelemetryRate(501), 9), P.MsgId.SET_TELEMETRY_RATE,
            P.Nack.BAD_VALUE, 0),
           ("gains for hinge 6", P.encode(P.SetGains(n, P.Gains.from_pid(PidGains.from_spec(spec))), 9),
            P.MsgId.SET_GAINS, P.Nack.BAD_VALUE, n),
           ("get gains of hinge 6", P.encode(P.GetGains(n), 9), P.MsgId.GET_GAINS, P.Nack.BAD_VALUE, n)]
    for m in P.MsgId:
        if m >= 0x80:  # a device -> host message sent to the device
            frame = P.encode(next(x for x in _DEVICE_MESSAGES if x.MSG == m), 9)
            out.append((f"device message {m.name}", frame, m, P.Nack.UNKNOWN_MESSAGE, 0))
    for name, g in _bad_gains(spec):
        out.append((f"gains {name}", P.encode(P.SetGains(P.BROADCAST, g), 9), P.MsgId.SET_GAINS, P.Nack.BAD_VALUE,
                    P.BROADCAST))
    return out


_DEVICE_MESSAGES = [P.Ack(3, 5), P.NackMsg(3, 4, 1), P.HelloReply((0, 1, 0), 1, 6, 1000, 200, 500),
                    P.StateMsg((0, 1, 0), 0, 0, 255, 1, 0, (0,) * 6, (0,) * 6, (0,) * 6),
                    P.GainsReply(0, P.Gains(*[1] * 7)),
                    P.WiringReply((0, 1, 2, 3, 4, 5), (0,) * 6, (0, 1, 2, 3, 4, 5)),
                    P.Telemetry(1, 0, 0, 255, (0,) * 6, (0,) * 6, (0,) * 6, (0,) * 6),
                    P.ProgramStatus(0, 0, 0, 0, 0, 0), P.ProgramSample(0, 0)]


@pytest.mark.parametrize("active", [False, True], ids=["idle", "active"])
def test_every_refusal_is_a_nack_and_changes_nothing(spec, active):
    for name, frame, acked, reason, detail in refusals(spec):
        c = make(spec)
        c.tick(0, [0] * c.n)
        if active:
            assert ask(c, P.SetTargets((10,) * c.n), 1)[1] == P.Ack(P.MsgId.SET_TARGETS, 0)
        before = snapshot(c)
        c.rx(frame, 1000)
        assert replies(c) == [(9, P.NackMsg(acked, reason, detail))], name
        assert snapshot(c) == before, name


def test_targets_refused_in_estop_and_fault(spec):
    c = make(spec)
    c.estop()
    before = snapshot(c)
    assert ask(c, P.SetTargets((1,) * c.n))[1] == P.NackMsg(P.MsgId.SET_TARGETS, P.Nack.BAD_STATE, P.State.ESTOP)
    assert snapshot(c) == before
    assert c.set_targets([1] * c.n, 0) == P.Nack.BAD_STATE


def test_host_api_refusals_change_nothing(spec):
    c = make(spec)
    before = snapshot(c)
    assert c.set_targets([limit(spec) + 1] + [0] * (c.n - 1), 0) == P.Nack.OUT_OF_RANGE
    for g in (PidGains.from_spec(spec).replace(kp=1.5), PidGains.from_spec(spec).replace(derivative_cutoff=0.5),
              PidGains.from_spec(spec).replace(integral_limit=float("nan"))):
        assert c.set_gains(P.BROADCAST, g) == P.Nack.BAD_VALUE
    assert c.set_gains(c.n, PidGains.from_spec(spec)) == P.Nack.BAD_VALUE
    assert snapshot(c) == before
    g = PidGains.from_spec(spec).replace(kp=1.0, ki=10.0, kd=0.05, derivative_cutoff=450.0, hold_band=50)
    assert c.set_gains(2, g) == 0 and c.gains(2).hold_band == 50  # the bounds are inclusive


def test_gains_at_their_bounds_pass_the_host_and_the_device_alike(spec):
    """Bounds compared in wire units (issue 40 item 6): the device decoded a gain to float and compared that, so
    a deadband of 0.5, which the host's check passes and sends as 16384, was 0.500015 and refused. Each gain at
    each end, as the host checks and encodes it, is taken; one wire unit beyond is refused."""
    from twin.formats.gains import check_gains

    for (field, bounds), (wire_field, code) in zip(GAIN_BOUNDS.items(), P.GAINS_BLOCK):
        for side, step in ((0, -1), (1, 1)):
            g = PidGains.from_spec(spec).replace(**{field: bounds[side]})
            check_gains([g])
            c = make(spec)
            wire = P.Gains.from_pid(g)
            assert ask(c, P.SetGains(2, wire), 1)[1] == P.Ack(P.MsgId.SET_GAINS, 0), (field, bounds[side])
            assert ask(c, P.GetGains(2), 2)[1] == P.GainsReply(2, wire)
            beyond = getattr(wire, wire_field) + step
            if code == "H" and beyond < 0:
                continue  # not a value the wire can carry
            before = snapshot(c)
            got = ask(c, P.SetGains(2, dataclasses.replace(wire, **{wire_field: beyond})), 3)[1]
            assert got == P.NackMsg(P.MsgId.SET_GAINS, P.Nack.BAD_VALUE, 2), (field, beyond)
            assert snapshot(c) == before


def test_gains_set_on_the_wire_read_back_exactly(spec):
    c = make(spec)
    g = P.Gains(123457, 654321, 987, 1234, 16000, 1500, 7)
    assert ask(c, P.SetGains(4, g), 3)[1] == P.Ack(P.MsgId.SET_GAINS, 0)
    assert ask(c, P.GetGains(4), 4)[1] == P.GainsReply(4, g)
    assert ask(c, P.GetGains(3), 5)[1] == P.GainsReply(3, P.Gains.from_pid(PidGains.from_spec(spec)))


# ---- the watchdog and repeated commands ---------------------------------------------------------

def test_watchdog_stops_the_motors_200_ms_after_the_last_valid_frame(spec):
    c = make(spec, host_away_hold_ms=0)
    c.rx(P.encode(P.SetTargets((200,) * c.n), 1), 0)
    last_frame = 150_000
    for t in range(1000, 400_001, 1000):
        if t == last_frame:
            c.rx(P.encode(P.Heartbeat(), 2), t)
        if t == 300_000:
            c.rx(b"\x00\x05garbage\x00", t)  # not a valid frame: does not feed the watchdog
        duty, decay = c.tick(t, [t // 5000] * c.n)  # moving: no stall
        if t <= last_frame + 200_000:
            assert c.state == P.State.ACTIVE and np.all(duty > 0.5), t
        else:
            assert c.state == P.State.FAULT and c.faults == P.Fault.WATCHDOG, t
            assert np.all(duty == 0) and np.all(decay == 1), t  # off, braking
            break
    assert t == last_frame + 201_000


def test_no_watchdog_when_configured_off(spec):
    c = make(spec, watchdog_ms=0)
    c.set_targets([50] * c.n, 0)
    for t in range(0, 2_000_000, 1000):
        c.tick(t, [50] * c.n)
    assert c.state == P.State.ACTIVE


def test_repeated_set_targets_gets_the_original_ack_and_is_not_run_again(spec):
    c = make(spec)
    first = P.encode(P.SetTargets((100,) * c.n), 77)
    c.rx(first, 1_000)
    (a,) = replies(c)
    c.tick(2_000, [0] * c.n)
    c.rx(P.encode(P.SetTargets((-100,) * c.n), 78), 30_000)
    replies(c)
    c.rx(P.encode(P.Heartbeat(), 79), 40_000)  # a heartbeat between a command and its retry
    c.rx(first, 51_000)  # the retry, 50 ms later
    (b,) = replies(c)
    assert a == b == (77, P.Ack(P.MsgId.SET_TARGETS, 1_000))
    assert tuple(c.targets) == (-100,) * c.n


def test_a_new_command_with_a_reused_seq_is_run(spec):
    c = make(spec)
    c.rx(P.encode(P.SetTargets((100,) * c.n), 5), 1_000)
    c.rx(P.encode(P.SetTargets((30,) * c.n), 5), 9_000)
    assert [m for _, m in replies(c)] == [P.Ack(P.MsgId.SET_TARGETS, 1_000), P.Ack(P.MsgId.SET_TARGETS, 9_000)]
    assert tuple(c.targets) == (30,) * c.n


def test_queries_are_answered_afresh_under_a_repeated_seq(spec):
    """`vrscroll status` twice: each run's GET_STATE has the same seq and bytes, and must see now."""
    c = make(spec)
    c.tick(1_000, [3] * c.n)
    assert ask(c, P.GetState(), 2, 1_500)[1].counts == (3,) * c.n
    c.tick(2_000, [9] * c.n)
    assert ask(c, P.GetState(), 2, 2_500)[1].counts == (9,) * c.n


def test_a_new_session_runs_the_same_command_again(spec):
    """The same SET_TARGETS under the same seq in a later session (after HELLO, or a second later)
    is a new command: it runs and gets its own ACK."""
    for between, gap_us in ((P.Hello(), 20_000), (P.Heartbeat(), 1_000_000)):
        c = make(spec)
        move = P.encode(P.SetTargets((100,) * c.n), 5)
        c.rx(move, 1_000)
        c.estop()
        c.clear_fault()
        c.rx(P.encode(between, 1), 1_000 + gap_us // 2)
        replies(c)
        c.rx(move, 1_000 + gap_us)
        assert replies(c) == [(5, P.Ack(P.MsgId.SET_TARGETS, 1_000 + gap_us))]
        assert c.state == P.State.ACTIVE


# ---- faults -------------------------------------------------------------------------------------

def test_stall_faults_a_jammed_hinge(spec):
    c = make(spec, watchdog_ms=0)
    c.set_targets([0, 0, 300, 0, 0, 0], 0)
    t = 0
    while c.state == P.State.ACTIVE and t < 1_000_000:
        t += 1000
        c.tick(t, [0, 0, 5, 0, 0, 0])  # hinge 2 stuck at 5 counts under full duty
    assert (c.state, c.faults, c.fault_hinge) == (P.State.FAULT, P.Fault.STALL, 2)
    assert 300_000 < t <= 303_000


def test_limit_fault_past_the_range(spec):
    c = make(spec, watchdog_ms=0)
    far = limit(spec) + core.config_from_spec(spec).limit_margin_counts
    c.set_targets([0] * c.n, 0)
    c.tick(1000, [0, 0, 0, 0, far, 0])
    assert c.state == P.State.ACTIVE
    duty, _ = c.tick(2000, [0, 0, 0, 0, far + 1, 0])
    assert (c.state, c.faults, c.fault_hinge) == (P.State.FAULT, P.Fault.LIMIT, 4) and not duty.any()


def test_overcurrent_only_where_current_is_sensed(spec):
    c = make(spec, watchdog_ms=0, overcurrent_ma=1000)
    c.set_targets([100] * c.n, 0)
    c.tick(1000, [0] * c.n)
    c.tick(2000, [0] * c.n, current_ma=[0, 1000, 0, 0, 0, 0])
    assert c.state == P.State.ACTIVE
    c.tick(3000, [0] * c.n, current_ma=[0, 0, 0, -1001, 0, 0])
    assert (c.state, c.faults, c.fault_hinge) == (P.State.FAULT, P.Fault.OVERCURRENT, 3)
    off = make(spec, watchdog_ms=0)
    off.set_targets([100] * c.n, 0)
    off.tick(1000, [0] * c.n, current_ma=[30000] * c.n)
    assert off.state == P.State.ACTIVE


def test_estop_brakes_and_clear_fault_idles_at_the_present_counts(spec):
    c = make(spec, watchdog_ms=0)
    c.set_targets([100] * c.n, 0)
    duty, decay = c.tick(1000, [0] * c.n)
    assert duty.all() and decay.all()  # driving: brake (slow decay)
    assert ask(c, P.EStop(), 3, 1500)[1] == P.Ack(P.MsgId.ESTOP, 1500)
    duty, decay = c.tick(2000, [7] * c.n)
    assert (c.state, c.faults) == (P.State.ESTOP, P.Fault.ESTOP) and not duty.any() and decay.all()
    assert ask(c, P.ClearFault(), 4, 3000)[1] == P.Ack(P.MsgId.CLEAR_FAULT, 3000)
    duty, decay = c.tick(4000, [7] * c.n)
    assert (c.state, c.faults, c.fault_hinge) == (P.State.IDLE, 0, 0xFF)
    assert tuple(c.targets) == (7,) * c.n and not duty.any() and decay.all()  # idle: brake too


def test_hello_and_state_report_the_config_and_the_tick(spec):
    c = make(spec)
    assert ask(c, P.Hello())[1] == P.HelloReply(core.FIRMWARE_VERSION, P.PROTOCOL_VERSION, 6, 1000, 200, 500,
                                                  zero_confirmed=1)
    c.rx(b"\x01\x02\x00", 0)
    c.tick(5000, [1, 2, 3, 4, 5, 6])
    assert ask(c, P.GetState(), 2, 6000)[1] == P.StateMsg(core.FIRMWARE_VERSION, P.State.IDLE, 0, 0xFF, 6000, 1,
                                                          (1, 2, 3, 4, 5, 6), (0,) * 6, (0,) * 6,
                                                          zero_confirmed=1)


def test_state_reports_the_integral_the_pid_holds_each_hinge_with(spec):
    """At rest within the hold band the PID's duty is off and its integral frozen: only STATE shows it."""
    c = make(spec, watchdog_ms=0)
    c.set_targets([0, 10, -10, 0, 0, 0], 0)
    for k in range(200):  # hinges 1 and 2 held 10 counts off their targets: their integrals wind up, opposite
        c.tick(k * 1000, [0, 0, 0, 0, 0, 0])
    held = core.pid_memory(c).integral.copy()
    assert held[1] > 0 > held[2] and held[0] == 0
    state = ask(c, P.GetState(), 3, 200_000)[1]
    assert state.integral == tuple(int(round(float(x) * P.DUTY_SCALE)) for x in held)
    assert state.integral_duty == pytest.approx(held, abs=1 / P.DUTY_SCALE)


def test_telemetry_at_the_set_rate_with_the_counts_the_pid_used(spec):
    c = make(spec, watchdog_ms=0)
    assert ask(c, P.SetTelemetryRate(300))[1].MSG == P.MsgId.ACK
    c.set_targets([40] * c.n, 0)
    sent, frames = [], []
    for k in range(300):
        duty, _ = c.tick(k * 1000, [k % 50] * c.n)
        sent.append((k, duty))
        frames += replies(c)
    assert [s for s, _ in frames] == list(range(100))  # every 3rd tick (1000 / 300 rounded), seq +1 each
    for (seq, m), (k, duty) in zip(frames, sent[::3]):
        assert m.time_us == k * 1000 and m.counts == (k % 50,) * c.n and m.targets == (40,) * c.n
        assert m.duty == tuple(int(round(float(d) * P.DUTY_SCALE)) for d in duty)


def test_telemetry_dropped_not_replies_when_nobody_reads(spec):
    c = make(spec, watchdog_ms=0)
    c.set_telemetry_rate(500)
    for k in range(2000):
        c.tick(k * 1000, [0] * c.n)
    assert c.telemetry_dropped > 0
    c.tx()
    c.rx(P.encode(P.GetState(), 3), 0)
    assert isinstance(replies(c)[0][1], P.StateMsg)


def test_numba_calls_the_core_tick_by_address(spec):
    lib = core.library()
    tick = lib.vrs_tick

    @numba.njit
    def run(address, counts, duty, decay, n_ticks):
        for k in range(n_ticks):
            counts[:] = k // 10
            tick(address, k * 1000, counts.ctypes.data, 0, duty.ctypes.data, decay.ctypes.data)
        return duty[0]

    a, b = make(spec, watchdog_ms=0), make(spec, watchdog_ms=0)
    for x in (a, b):
        x.set_targets([120] * x.n, 0)
    counts, duty, decay = np.zeros(8, np.int32), np.zeros(8, np.float32), np.zeros(8, np.uint8)
    got = run(a.address, counts, duty, decay, 500)
    for k in range(500):
        want, _ = b.tick(k * 1000, [k // 10] * b.n)
    assert got == want[0] and np.array_equal(duty[:6], want)


# ---- the zero, LIMIT's way back, I2t, the host away ---------------------------------------------------

def test_after_a_start_targets_wait_for_the_zero_and_confirming_makes_the_present_counts_zero(spec):
    c = make(spec, zeroed=False, counts=[40, -7, 0, 0, 0, 300], watchdog_ms=0)
    c.tick(1000, [40, -7, 0, 0, 0, 300])
    assert ask(c, P.Hello())[1].zero_confirmed == 0
    nack = ask(c, P.SetTargets((0,) * c.n), 2, 1000)[1]
    assert nack == P.NackMsg(P.MsgId.SET_TARGETS, P.Nack.ZERO_UNCONFIRMED, 0xFF) and c.state == P.State.IDLE
    assert ask(c, P.ConfirmZero(), 3, 1000)[1] == P.Ack(P.MsgId.CONFIRM_ZERO, 1000)
    c.tick(2000, [41, -7, 0, 0, 0, 300])  # raw counts: the zero is subtracted
    state = ask(c, P.GetState(), 4, 2000)[1]
    assert state.counts == (1, 0, 0, 0, 0, 0) and state.zero_confirmed == 1
    assert ask(c, P.SetTargets((10,) * c.n), 5, 2000)[1] == P.Ack(P.MsgId.SET_TARGETS, 2000)
    assert ask(c, P.ConfirmZero(), 6, 2000)[1] == P.NackMsg(P.MsgId.CONFIRM_ZERO, P.Nack.BAD_STATE, P.State.ACTIVE)


def test_a_hinge_past_its_range_can_be_driven_back_but_not_further_out(spec):
    far = limit(spec) + spec.limit_margin
    out = [far + 40] + [0] * (spec.n_hinges - 1)  # sagged past the range while IDLE
    back = make(spec, counts=out, watchdog_ms=0)
    back.tick(0, out)
    assert ask(back, P.SetTargets((limit(spec) - 10,) + (0,) * 5))[1].MSG == P.MsgId.ACK
    for i, c0 in enumerate(range(far + 40, far - 30, -1)):  # on its way back: no LIMIT
        back.tick(1000 * (i + 1), [c0] + [0] * 5)
        assert back.state == P.State.ACTIVE, c0
    back.tick(10**6, [far + 10] + [0] * 5)  # out again, past where it came back to: LIMIT
    assert back.state == P.State.FAULT and back.faults == P.Fault.LIMIT and back.fault_hinge == 0
    away = make(spec, counts=out, watchdog_ms=0)
    away.tick(0, out)
    ask(away, P.SetTargets((limit(spec) - 10,) + (0,) * 5))
    away.tick(1000, [far + 41] + [0] * 5)  # a hinge that runs away from the range (a reversed encoder)
    assert away.state == P.State.FAULT and away.faults == P.Fault.LIMIT


def test_i2t_derates_a_jammed_hinge_before_its_overload_time_and_recovers(spec):
    """Held against a jam at duty 0.45 (0.72 A, 1.8x the motor's continuous 0.4 A): the budget
    (stall^2 - continuous^2) x overload_time lasts budget / (I^2 - continuous^2); then the duty is held to the
    continuous rating, and released once the estimate falls to half the budget."""
    c = make(spec, watchdog_ms=0, stall_duty=2.0)  # no STALL fault: a hand that holds the flap
    kp = 0.45 / 100  # duty 0.45 at an error of 100 counts, all P
    c.set_gains(P.BROADCAST, PidGains(kp, 0.0, 0.0, 50.0, 0.0, 0.0, 0))
    ask(c, P.SetTargets((100,) + (0,) * 5))
    i_stall, i_cont = spec.stall_current, spec.continuous_current
    allowed = (i_stall**2 - i_cont**2) * spec.overload_time / ((0.45 * i_stall)**2 - i_cont**2)
    derated_at = None
    for t in range(1, 30_001):
        duty, _ = c.tick(t * 1000, [0] * 6)
        if derated_at is None:
            assert duty[0] == pytest.approx(0.45)
            derated_at = t / 1000 if c.derated & 1 else None
        else:
            assert duty[0] == pytest.approx(i_cont / i_stall, rel=1e-3)  # from the next tick on
    assert derated_at == pytest.approx(allowed, abs=0.01) and c.heat[0] == pytest.approx(1.0, abs=0.01)
    assert ask(c, P.GetState(), 2)[1].derated == 1
    t0 = 30_001
    for t in range(t0, t0 + 20_000):  # at the target: no current, the estimate cools
        c.tick(t * 1000, [100, 0, 0, 0, 0, 0])
    assert c.derated == 0 and c.heat[0] < 0.5


def test_a_host_gone_quiet_leaves_the_targets_held_for_the_stated_time_then_released(spec):
    hold_ms = round(spec.host_away_hold * 1000)
    c = make(spec, stall_duty=2.0)  # flaps held short of their targets, driven, no STALL
    ask(c, P.SetTargets((50,) * c.n))
    for t in range(1000, 201_000 + hold_ms * 1000 + 1000, 1000):  # the watchdog at 201 ms, then the hold
        duty, decay = c.tick(t, [40] * c.n)
        if t <= 200_000:
            assert c.state == P.State.ACTIVE, t
        elif t < 201_000 + hold_ms * 1000:
            assert c.state == P.State.HOLDING and np.all(duty > 0), t  # still holding the gated targets
    assert c.state == P.State.FAULT and c.faults == P.Fault.WATCHDOG and np.all(duty == 0) and np.all(decay == 1)
    back = make(spec, stall_duty=2.0)
    ask(back, P.SetTargets((50,) * back.n))
    for t in range(1000, 400_000, 1000):
        back.tick(t, [40] * back.n)
    assert back.state == P.State.HOLDING
    back.rx(P.encode(P.Heartbeat(), 9), 400_000)  # the host is back within the hold
    back.tick(401_000, [40] * back.n)
    assert back.state == P.State.ACTIVE and back.faults == 0


def test_a_pulse_drives_one_hinge_open_loop_for_its_time_in_idle_only(spec):
    c = make(spec, watchdog_ms=0)
    c.tick(0, [0] * 6)
    assert ask(c, P.Pulse(2, round(0.2 * P.DUTY_SCALE), 30), 1, 0)[1] == P.Ack(P.MsgId.PULSE, 0)
    duties = [c.tick(t * 1000, [0] * 6)[0] for t in range(1, 40)]
    on = [d[2] for d in duties]
    assert on[:30] == [pytest.approx(0.2, abs=1e-4)] * 30 and on[30:] == [0.0] * 9  # 30 ticks of 1 ms
    assert all(d[k] == 0 for d in duties for k in (0, 1, 3, 4, 5)) and c.state == P.State.IDLE
    samples = replies(c)  # a PULSE is a program: a PROGRAM_SAMPLE per tick it drove
    assert [seq for seq, _ in samples] == list(range(30)) and {m.duty for _, m in samples} == {round(0.2 * P.DUTY_SCALE)}
    for bad in (P.Pulse(2, round(0.5 * P.DUTY_SCALE), 30), P.Pulse(2, 100, P.PULSE_MAX_MS + 1), P.Pulse(6, 100, 30)):
        assert ask(c, bad, 2, 50_000)[1].reason == P.Nack.BAD_VALUE, bad
    ask(c, P.SetTargets((0,) * 6), 3, 50_000)
    assert ask(c, P.Pulse(2, 100, 30), 4, 50_000)[1].reason == P.Nack.BAD_STATE


def test_the_wiring_correction_reads_the_named_input_turned_around_and_drives_the_motor_reversed(spec):
    c = make(spec, watchdog_ms=0)
    raw = [10, 20, 30, 40, 50, 60]
    flags = (0, P.WIRING_ENCODER_REVERSED, 0, P.WIRING_MOTOR_REVERSED, 0, 0)
    assert ask(c, P.SetWiring((0, 3, 2, 1, 4, 5), flags, tuple(range(6))))[1].MSG == P.MsgId.ACK
    assert ask(c, P.Hello(), 2)[1].wiring_set == 1 and ask(c, P.GetWiring(), 3)[1].flags == flags
    c.tick(1000, raw)
    assert ask(c, P.GetState(), 4, 1000)[1].counts == (10, -40, 30, 20, 50, 60)  # zero unconfirmed again
    assert ask(c, P.SetTargets((0,) * 6), 5, 1000)[1].reason == P.Nack.ZERO_UNCONFIRMED
    ask(c, P.ConfirmZero(), 6, 1000)
    ask(c, P.SetTargets((0, 0, 0, 50, 0, 0)), 7, 1000)
    duty, _ = c.tick(2000, raw)
    assert duty[3] < 0  # the PID asks hinge 3 for positive duty; its motor's bridge gets it reversed
    identity = tuple(range(6))
    for bad in ((0, 0, 2, 3, 4, 5), (0, 1, 2, 3, 4, 6)):
        assert ask(c, P.SetWiring(bad, (0,) * 6, identity), 8)[1].reason == P.Nack.BAD_STATE  # ACTIVE now
    idle = make(spec, watchdog_ms=0)
    for bad in ((0, 0, 2, 3, 4, 5), (0, 1, 2, 3, 4, 6)):
        assert ask(idle, P.SetWiring(bad, (0,) * 6, identity))[1].reason == P.Nack.BAD_VALUE
        assert ask(idle, P.SetWiring(identity, (0,) * 6, bad))[1].reason == P.Nack.BAD_VALUE  # bridges too
    assert ask(idle, P.SetWiring(identity, (8,) * 6, identity))[1].reason == P.Nack.BAD_VALUE  # no such flag


def test_a_disabled_hinge_stays_braked_and_its_motion_is_refused_through_a_cleared_fault(spec):
    """Hinge 2 disabled, its motor on bridge 4 (a dead wire bring-up named): HELLO and STATE say so, its PULSE and
    PROGRAM and a target that moves it are refused naming it, and in ACTIVE, HOLDING and after a fault cleared its
    bridge stays at zero duty, braked, while the others are driven; its encoder reading past the range stops nothing.
    Enabled again, with the zero kept, it is driven."""
    c = make(spec, watchdog_ms=200, host_away_hold_ms=500, stall_duty=2.0)
    bridge, flags = (0, 1, 4, 3, 2, 5), (0, 0, P.WIRING_DISABLED, 0, 0, 0)
    c.tick(0, [0] * 6)
    assert ask(c, P.SetWiring(tuple(range(6)), flags, bridge), 1)[1].MSG == P.MsgId.ACK
    hello = ask(c, P.Hello(), 2)[1]
    assert hello.disabled == 0b100 and hello.wiring_set == 1 and ask(c, P.GetWiring(), 3)[1].flags == flags
    ask(c, P.ConfirmZero(), 4)
    program = P.Program(2, -100, 100, 100, 1, (1000,) + (0,) * 15, (50,) + (0,) * 15)
    moving = P.SetTargets((10, 0, spec.stall_counts + 1, 0, 0, 0))
    for seq, cmd in enumerate((P.Pulse(2, 1000, 30), program, moving), 5):
        assert ask(c, cmd, seq)[1] == P.NackMsg(cmd.MSG, P.Nack.HINGE_DISABLED, 2), cmd
    assert ask(c, P.Pulse(1, 1000, 30), 8)[1].MSG == P.MsgId.ACK  # the others are driven
    for t in range(1, 40):
        c.tick(t * 1000, [0] * 6)
    assert {m.MSG for _, m in replies(c)} == {P.MsgId.PROGRAM_SAMPLE}
    far = limit(spec) + spec.limit_margin + 100  # counts: past the LIMIT fault's bound
    raw, up = [0] * 6, (30, 30, None, 30, 30, 30)

    def targets(at):
        return tuple(at if k == 2 else x for k, x in enumerate(up))

    assert ask(c, P.SetTargets(targets(spec.stall_counts)), 9, 40_000)[1].MSG == P.MsgId.ACK  # where it stands
    for seq, ticks in enumerate((range(41, 600), range(600, 1200)), 10):
        for t in ticks:
            raw[2] = far if t % 2 else 0  # a dead channel, glitching
            duty, decay = c.tick(t * 1000, raw)
            assert duty[4] == 0 and decay[4] == 1 and duty[0] > 0 and duty[2] > 0, (t, duty)  # bridge 2: hinge 4
            if t % 100 == 0:
                c.rx(P.encode(P.Heartbeat(), t), t * 1000)
        state = ask(c, P.GetState(), seq, t * 1000)[1]
        assert state.disabled == 0b100 and state.targets[2] == state.counts[2] == raw[2]
        assert c.state == P.State.ACTIVE and c.faults == 0
        c.estop()
        assert c.clear_fault() == 0 and c.state == P.State.IDLE  # a cleared fault ...
        assert ask(c, P.SetTargets(targets(raw[2] + 50)), seq + 10, t * 1000)[1] == \
            P.NackMsg(P.MsgId.SET_TARGETS, P.Nack.HINGE_DISABLED, 2)  # ... cannot drive it
        assert ask(c, P.SetTargets(targets(raw[2])), seq + 20, t * 1000)[1].MSG == P.MsgId.ACK
    for t in range(1200, 2000):  # the host gone quiet: HOLDING holds the others, hinge 2 still braked
        duty, _ = c.tick(t * 1000, raw)
        assert duty[4] == 0
    assert c.state == P.State.FAULT and c.faults == P.Fault.WATCHDOG and c.clear_fault() == 0
    c.tick(2_000_000, [0] * 6)
    assert ask(c, P.SetWiring(tuple(range(6)), (0,) * 6, bridge), 40, 2_000_000)[1].MSG == P.MsgId.ACK
    assert ask(c, P.Hello(), 41, 2_000_000)[1].disabled == 0
    assert ask(c, P.SetTargets((0, 0, 60, 0, 0, 0)), 42, 2_000_000)[1].MSG == P.MsgId.ACK  # the zero kept
    duty, _ = c.tick(2_001_000, [0] * 6)
    assert duty[4] > 0  # enabled again: driven on its bridge


def test_the_bridge_map_drives_each_hinge_on_its_bridge_and_reads_its_current_there(spec):
    """Motors on each other's bridges (hinge 1's on bridge 4, hinge 4's on bridge 1): the core sends hinge 1's
    duty to bridge 4, reads its current from bridge 4, and HELLO says a correction is applied."""
    c = make(spec, watchdog_ms=0)
    bridge = (0, 4, 2, 3, 1, 5)
    assert ask(c, P.SetWiring(tuple(range(6)), (0,) * 6, bridge))[1].MSG == P.MsgId.ACK
    assert ask(c, P.Hello(), 2)[1].wiring_set == 1 and ask(c, P.GetWiring(), 3)[1].bridge == bridge
    ask(c, P.ConfirmZero(), 4)
    ask(c, P.SetTelemetryRate(500), 5)
    ask(c, P.SetTargets((0, 80, 0, 0, 0, 0)), 6)
    duty, _ = c.tick(1000, [0] * 6, [0, 11, 0, 0, 444, 0])
    assert duty[4] > 0 and not np.any(np.delete(duty, 4)), duty  # hinge 1's PID drives bridge 4 alone
    (_, telemetry), = replies(c)
    assert telemetry.current_ma[1] == 444 and telemetry.current_ma[4] == 11 and telemetry.duty[1] > 0
