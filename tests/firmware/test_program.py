"""Open-loop duty programs (PROGRAM; PULSE is one of one segment): the core bounds them whatever the host sends,
ends them itself (its segments' end, the window's edge, a stall, its timeout, a quiet host, a state change),
streams a sample per tick, and runs them alike in the twin, the batch twin, the emulator and the sketch."""

import dataclasses

import numpy as np
import pytest

from controllers import core
from controllers.pid import PidGains
from controllers.program import COAST, ProgramEnd
from twin.link import protocol as P
from twin.link.emulator import Emulator, EmulatorOptions, drawn_options
from twin.link.faults import FaultOptions
from twin.link.serial_link import Link, NackError, program_message
from twin.sim.batch import TwinBatch
from twin.sim.drive import DECAY_COAST
from twin.sim.plant import PlantRanges, as_twin
from twin.sim.twin import Twin

MAX_WIRE = round(P.PROGRAM_MAX_DUTY * P.DUTY_SCALE)
PAD = P.PROGRAM_MAX_SEGMENTS


def make(spec, zeroed: bool = True, **config) -> core.Core:
    cfg = core.config_from_spec(spec)
    for k, v in config.items():
        setattr(cfg, k, v)
    c = core.Core(cfg, [PidGains.from_spec(spec)] * spec.n_hinges, [0] * spec.n_hinges)
    if zeroed:
        c.mark_zero_confirmed()
    return c


def raw_program(hinge=2, low=-300, high=300, timeout_ms=100, duty=(0.5,), ms=(100,), n=None) -> P.Program:
    """A PROGRAM frame's message as any host may send it: duty in [-1, 1] (to wire units) or COAST, nothing
    checked."""
    wire = tuple(P.PROGRAM_COAST if d == COAST else round(d * P.DUTY_SCALE) for d in duty)
    return P.Program(hinge, low, high, timeout_ms, len(duty) if n is None else n,
                     wire + (0,) * (PAD - len(wire)), tuple(ms) + (0,) * (PAD - len(ms)))


def frames(c) -> list:
    return P.Decoder().feed(c.tx())


class FirstOrderHinge:
    """A hinge for the bare core: speed follows duty * top_speed with time constant tau_s (braked to rest as
    fast at duty 0), counts the rounded position; coasting (its windings open) it keeps its speed; `jammed`
    holds it still. `coasted`: per tick, whether its bridge coasted it."""

    def __init__(self, top_speed=6000.0, tau_s=0.02, dt=0.001, jammed=False):
        self.top, self.a, self.dt, self.jammed = top_speed, dt / tau_s, dt, jammed
        self.pos = self.speed = 0.0
        self.coasted = []

    def step(self, duty: float, coasting: bool = False) -> int:
        self.coasted.append(coasting)
        if not self.jammed:
            self.speed += 0.0 if coasting else (duty * self.top - self.speed) * self.a
            self.pos += self.speed * self.dt
        return round(self.pos)


def run(c, msg, ticks, hinge_model=None, hinge=2, heartbeat_ms=50, events=()):
    """Send msg at device time 0, then tick the core `ticks` times (1 ms each) on a FirstOrderHinge (or the
    given one) for `hinge`, the others still, a heartbeat every heartbeat_ms (0: none); events: {tick: bytes}
    received before that tick. Returns (the reply to msg, duties (ticks, n), counts of `hinge` per tick,
    PROGRAM_SAMPLEs (seq, msg), status)."""
    h = hinge_model or FirstOrderHinge()
    counts = [0] * c.n
    c.tick(0, counts)
    c.rx(P.encode(msg, 1), 0)
    (reply,) = [m for _, m in frames(c)]
    duties, seen, out = [], [], []
    duty, decay = np.zeros(c.n), np.ones(c.n)
    events = dict(events)
    for i in range(1, ticks + 1):
        counts[hinge] = h.step(float(duty[hinge]), bool(decay[hinge] == DECAY_COAST))
        if heartbeat_ms and i % heartbeat_ms == 0:
            c.rx(P.encode(P.Heartbeat(), 100 + i), i * 1000)
        if i in events:
            c.rx(events[i], i * 1000)
        duty, decay = c.tick(i * 1000, counts)
        duties.append(duty)
        seen.append(counts[hinge])
        out += frames(c)
    samples = [(s, m) for s, m in out if isinstance(m, P.ProgramSample)]
    return reply, np.array(duties), np.array(seen), samples, c.program_status()


# ---- the core ---------------------------------------------------------------------------------

def test_a_program_runs_its_segments_brakes_the_others_and_streams_each_tick(spec):
    c = make(spec)
    msg = raw_program(2, -300, 300, 45, duty=(0.3, 0.0, -0.6), ms=(20, 10, 15))
    reply, duties, counts, samples, st = run(c, msg, 60)
    assert reply == P.Ack(P.MsgId.PROGRAM, 0)
    want = [0.3] * 20 + [0.0] * 10 + [-0.6] * 15 + [0.0] * 15
    np.testing.assert_allclose(duties[:, 2], want, atol=1e-4)
    assert not duties[:, [0, 1, 3, 4, 5]].any() and c.state == P.State.IDLE
    assert (st.end, st.ticks, st.dropped, st.hinge) == (ProgramEnd.DONE, 45, 0, 2)
    assert [s for s, _ in samples] == list(range(45))
    assert [m.duty for _, m in samples] == [round(d * P.DUTY_SCALE) for d in want[:45]]
    assert [m.counts for _, m in samples] == list(counts[:45]) and counts[19] > 5 and counts[44] < counts[29]


@pytest.mark.parametrize("duty", [0.8, -0.8, 0.3])
def test_the_window_ends_a_program_before_its_edge(spec, duty):
    """Toward an edge at full speed for 2 s: the core ends it at the window (not its segments' end) and the
    braked hinge stops inside the window."""
    c = make(spec)
    low, high = -300, 350
    _, duties, counts, samples, st = run(c, raw_program(2, low, high, 2000, (duty,), (2000,)), 400)
    assert st.end == ProgramEnd.WINDOW and 10 < st.ticks < 400 and len(samples) == st.ticks
    assert low <= counts.min() and counts.max() <= high, (counts.min(), counts.max())
    assert not duties[st.ticks:].any()
    ahead = round(P.PROGRAM_LOOKAHEAD_MS * 1e-3 * core.config_from_spec(spec).loop_rate_hz)
    k = P.PROGRAM_RATE_TICKS

    def predicted(t):  # where the core puts the hinge `ahead` ticks on, at tick t of the program (counts[t])
        return counts[t] + int((counts[t] - counts[t - k]) * ahead / k)

    edge = high if duty > 0 else low
    sign = 1 if duty > 0 else -1
    assert sign * predicted(st.ticks) > sign * edge >= sign * predicted(st.ticks - 1)  # ended on the tick it must


def test_a_stall_ends_a_program_above_the_duty_that_can_overheat_a_jammed_motor(spec):
    cfg = core.config_from_spec(spec)
    stall_ticks = cfg.stall_ms  # 1 kHz
    stall_duty = cfg.continuous_current_ma / cfg.stall_current_ma
    c = make(spec)
    _, duties, _, _, st = run(c, raw_program(2, timeout_ms=1000, duty=(stall_duty + 0.05,), ms=(1000,)), 600,
                              FirstOrderHinge(jammed=True))
    assert st.end == ProgramEnd.STALL and stall_ticks <= st.ticks <= stall_ticks + 2, st.ticks
    assert not duties[st.ticks:].any()
    c = make(spec)  # below it, a hinge that does not move is a hinge held by friction: the program runs on
    _, _, _, _, st = run(c, raw_program(2, timeout_ms=500, duty=(stall_duty - 0.05,), ms=(500,)), 600,
                         FirstOrderHinge(jammed=True))
    assert (st.end, st.ticks) == (ProgramEnd.DONE, 500)


def test_a_pulse_is_a_program_a_stall_ends_and_its_range_bounds(spec):
    """PULSE at its largest on a jammed hinge ends on the stall (300 ms of its 500), where the supervisor's
    STALL (duty 0.5 and up) never looked at it; a PULSE from beyond the range is refused."""
    stall_ms = core.config_from_spec(spec).stall_ms
    c = make(spec)
    reply, duties, _, samples, st = run(c, P.Pulse(2, int(P.PULSE_MAX_DUTY * P.DUTY_SCALE), P.PULSE_MAX_MS), 600,
                                        FirstOrderHinge(jammed=True))
    assert reply == P.Ack(P.MsgId.PULSE, 0) and st.end == ProgramEnd.STALL and stall_ms <= st.ticks <= stall_ms + 2
    assert not duties[st.ticks:].any() and len(samples) == st.ticks and c.state == P.State.IDLE
    lim = core.config_from_spec(spec).limit_counts
    c = make(spec)
    c.tick(0, [0, 0, lim + 3, 0, 0, 0])  # sagged past its range
    c.rx(P.encode(P.Pulse(2, 1000, 100), 1), 0)
    assert [m for _, m in frames(c)] == [P.NackMsg(P.MsgId.PULSE, P.Nack.OUT_OF_RANGE, 2)]


def test_a_timeout_shorter_than_the_segments_ends_the_program(spec):
    c = make(spec)
    _, duties, _, _, st = run(c, raw_program(2, timeout_ms=100, duty=(0.05, -0.05), ms=(150, 150)), 200)
    assert (st.end, st.ticks) == (ProgramEnd.TIMEOUT, 100) and not duties[100:].any()


def test_a_quiet_host_ends_the_program_after_the_watchdogs_period(spec):
    watchdog = core.config_from_spec(spec).watchdog_ms
    _, duties, _, _, st = run(make(spec), raw_program(2, timeout_ms=1000, duty=(0.01,), ms=(1000,)), 1100,
                              heartbeat_ms=0)
    assert st.end == ProgramEnd.HOST_QUIET and watchdog <= st.ticks <= watchdog + 2 and not duties[st.ticks:].any()
    _, _, _, _, st = run(make(spec), raw_program(2, timeout_ms=1000, duty=(0.01,), ms=(1000,)), 1100)
    assert (st.end, st.ticks) == (ProgramEnd.DONE, 1000)


@pytest.mark.parametrize("cleared", [False, True], ids=["estop", "estop and clear_fault at once"])
def test_any_state_change_ends_the_program_for_good(spec, cleared):
    events = {50: P.encode(P.EStop(), 7) + (P.encode(P.ClearFault(), 8) if cleared else b"")}
    c = make(spec)
    _, duties, _, _, st = run(c, raw_program(2, timeout_ms=300, duty=(0.2,), ms=(300,)), 200, events=events)
    assert st.end == ProgramEnd.STATE and st.ticks == 49 and not duties[49:].any()
    assert c.state == (P.State.IDLE if cleared else P.State.ESTOP)


@pytest.mark.parametrize("change", ["zero", "wiring"])
def test_a_new_zero_or_wiring_ends_the_program(spec, change):
    """CONFIRM_ZERO or SET_WIRING (IDLE commands) mid-program would move its window under the hinge: it ends."""
    msg = P.ConfirmZero() if change == "zero" else P.SetWiring((0, 1, 3, 2, 4, 5), (0,) * 6, tuple(range(6)))
    c = make(spec)
    _, duties, _, _, st = run(c, raw_program(2, timeout_ms=300, duty=(0.2,), ms=(300,)), 200,
                              events={50: P.encode(msg, 7)})
    assert st.end == ProgramEnd.STATE and st.ticks == 49 and not duties[49:].any() and c.state == P.State.IDLE


def test_a_coasting_segment_opens_the_hinges_bridge_and_its_samples_say_so(spec):
    """Driven, coasting, driven: the coasting ticks' bridge is open and its duty 0, their samples say
    PROGRAM_COAST; the hinge keeps turning through them; every other tick and bridge brakes. Wired to another
    bridge, the hinge's own coasts."""
    c = make(spec)
    h = FirstOrderHinge()
    msg = raw_program(2, -300, 300, 60, duty=(0.3, COAST, -0.3), ms=(20, 25, 15))
    reply, duties, counts, samples, st = run(c, msg, 80, h)
    assert reply == P.Ack(P.MsgId.PROGRAM, 0) and (st.end, st.ticks) == (ProgramEnd.DONE, 60)
    want = [False] * 20 + [True] * 25 + [False] * 35
    assert h.coasted[1:] == want[:-1]  # the plant sees a tick's decay from the next
    assert not duties[20:45].any()
    assert [m.duty for _, m in samples[20:45]] == [P.PROGRAM_COAST] * 25
    assert [m.duty for _, m in samples[:20]] == [round(0.3 * P.DUTY_SCALE)] * 20
    assert counts[44] - counts[21] > 0.9 * (counts[20] - counts[0]) * 23 / 20  # it kept its speed, undriven
    assert (c.tick(81_000, [0] * 6)[1] == 1).all()
    c = make(spec)
    c.rx(P.encode(P.SetWiring(tuple(range(6)), (0,) * 6, (0, 1, 3, 2, 4, 5)), 1), 0)  # hinge 2 on bridge 3
    assert [m for _, m in frames(c)] == [P.Ack(P.MsgId.SET_WIRING, 0)]
    c.mark_zero_confirmed()
    assert c.program(core.program_spec(2, [(COAST, 0.05)], (-300, 300))) == 0
    assert list(c.tick(1000, [0] * 6)[1]) == [1, 1, 1, DECAY_COAST, 1, 1]


def coasting(spec, ticks, events=(), heartbeat_ms=50, high=370, timeout_ms=1000):
    """A program driven 20 ms and coasting on (FirstOrderHinge keeps its speed), run `ticks`: (status, whether
    the hinge coasted per tick, counts per tick)."""
    h = FirstOrderHinge()
    *_, counts, _, st = run(make(spec), raw_program(2, -300, high, timeout_ms, duty=(0.3, COAST), ms=(20, 980)), ticks,
                            h, heartbeat_ms=heartbeat_ms, events=events)
    return st, np.array(h.coasted[1:]), counts


def test_the_cores_guards_end_a_coasting_program_and_brake(spec):
    """Whatever ends a program while it coasts brakes the hinge from the next tick: the window's edge (the
    coasting hinge heading for it), its timeout, a host gone quiet, a state change (ESTOP)."""
    st, coasted, counts = coasting(spec, 400, high=250)
    assert st.end == ProgramEnd.WINDOW and 20 < st.ticks < 400 and coasted[20:st.ticks].all()
    assert not coasted[st.ticks:].any() and counts.max() <= 250
    st, coasted, _ = coasting(spec, 300, timeout_ms=150)
    assert (st.end, st.ticks) == (ProgramEnd.TIMEOUT, 150) and coasted[20:150].all() and not coasted[150:].any()
    watchdog = core.config_from_spec(spec).watchdog_ms
    st, coasted, _ = coasting(spec, 400, heartbeat_ms=0)
    assert st.end == ProgramEnd.HOST_QUIET and watchdog <= st.ticks <= watchdog + 2
    assert coasted[20:st.ticks].all() and not coasted[st.ticks:].any()
    st, coasted, _ = coasting(spec, 300, events={100: P.encode(P.EStop(), 7)})
    assert (st.end, st.ticks) == (ProgramEnd.STATE, 99) and coasted[20:99].all() and not coasted[99:].any()


def test_a_coast_is_no_duty_the_core_takes_otherwise(spec):
    """PROGRAM_COAST is a segment's whole duty: the core refuses a coast bit past the last segment or beside a
    duty (its own API), and a core reads no coast from the duty just above it (-DUTY_SCALE: full reverse)."""
    for bits, duty in ((0b10, 0.0), (0b1, 0.2)):
        p = core.program_spec(2, [(duty, 0.05)], (-300, 300))
        p.coast = bits
        assert make(spec).program(p) == P.Nack.BAD_VALUE
    assert core.program_spec(2, [(0.2, 0.05), (COAST, 0.05)], (-300, 300)).coast == 0b10
    assert program_message(2, [(COAST, 0.05)], (-300, 300)).duty[0] == P.PROGRAM_COAST == -P.DUTY_SCALE - 1
    _, duties, _, samples, _ = run(make(spec), raw_program(2, timeout_ms=10, duty=(-0.8,), ms=(10,)), 5)
    assert duties[0, 2] < 0 and all(m.duty != P.PROGRAM_COAST for _, m in samples)


def refused_programs(spec):
    lim = core.config_from_spec(spec).limit_counts
    return [
        ("a window past the range", raw_program(low=-300, high=lim + 1), P.Nack.OUT_OF_RANGE),
        ("a window past -range", raw_program(low=-lim - 1, high=10), P.Nack.OUT_OF_RANGE),
        ("the hinge outside its window", raw_program(low=10, high=100), P.Nack.OUT_OF_RANGE),
        ("an empty window", raw_program(low=0, high=0), P.Nack.OUT_OF_RANGE),
        ("too strong by one step", P.Program(2, -300, 300, 10, 1, (MAX_WIRE + 1,) + (0,) * (PAD - 1),
                                             (10,) + (0,) * (PAD - 1)), P.Nack.BAD_VALUE),
        ("too strong backwards", P.Program(2, -300, 300, 10, 2, (0, -MAX_WIRE - 1) + (0,) * (PAD - 2),
                                           (5, 5) + (0,) * (PAD - 2)), P.Nack.BAD_VALUE),
        ("too long", raw_program(timeout_ms=P.PROGRAM_MAX_MS, duty=(0.1, 0.1), ms=(P.PROGRAM_MAX_MS, 1)),
         P.Nack.BAD_VALUE),
        ("a timeout too long", raw_program(timeout_ms=P.PROGRAM_MAX_MS + 1), P.Nack.BAD_VALUE),
        ("no timeout", raw_program(timeout_ms=0), P.Nack.BAD_VALUE),
        ("no segments", raw_program(n=0), P.Nack.BAD_VALUE),
        ("more segments than it holds", raw_program(n=PAD + 1), P.Nack.BAD_VALUE),
        ("a segment of 0 ms", raw_program(duty=(0.1, 0.1), ms=(10, 0)), P.Nack.BAD_VALUE),
        ("hinge 6", raw_program(hinge=6), P.Nack.BAD_VALUE),
    ]


def test_programs_out_of_bounds_are_refused_and_change_nothing(spec):
    for name, msg, reason in refused_programs(spec):
        c = make(spec)
        reply, duties, _, samples, st = run(c, msg, 5)
        assert reply == P.NackMsg(P.MsgId.PROGRAM, reason, reply.detail), name
        assert (st.hinge, st.end, st.ticks) == (0xFF, ProgramEnd.NONE, 0) and not duties.any() and not samples, name
    c = make(spec)  # the strongest and longest allowed are taken
    reply, *_ = run(c, P.Program(2, -300, 300, P.PROGRAM_MAX_MS, 2, (MAX_WIRE, -MAX_WIRE) + (0,) * (PAD - 2),
                                 (P.PROGRAM_MAX_MS - 1, 1) + (0,) * (PAD - 2)), 1)
    assert reply == P.Ack(P.MsgId.PROGRAM, 0)


def test_a_program_runs_only_idle_with_the_zero_confirmed_and_one_at_a_time(spec):
    c = make(spec, zeroed=False)
    assert run(c, raw_program(), 1)[0] == P.NackMsg(P.MsgId.PROGRAM, P.Nack.ZERO_UNCONFIRMED, 0xFF)
    c = make(spec)
    c.set_targets([0] * c.n, 0)
    assert run(c, raw_program(), 1)[0] == P.NackMsg(P.MsgId.PROGRAM, P.Nack.BAD_STATE, P.State.ACTIVE)
    c = make(spec)
    assert run(c, raw_program(timeout_ms=100, ms=(100,)), 10)[0].MSG == P.MsgId.ACK
    c.rx(P.encode(raw_program(hinge=3), 2), 11_000)
    assert [m for _, m in frames(c)] == [P.NackMsg(P.MsgId.PROGRAM, P.Nack.BAD_STATE, P.State.IDLE)]
    assert c.program_status().hinge == 2


def test_a_retried_program_gets_its_first_ack_and_does_not_start_again(spec):
    """The host resends a command whose ACK it missed (same seq, same bytes): the core answers from its kept
    replies, and the program that started goes on, neither restarted nor refused as 'one already runs'."""
    c = make(spec)
    msg = raw_program(timeout_ms=100, duty=(0.1,), ms=(100,))
    first, *_ = run(c, msg, 30)
    c.rx(P.encode(msg, 1), 31_000)
    assert [m for _, m in frames(c)] == [first] == [P.Ack(P.MsgId.PROGRAM, 0)]
    for t in range(31, 120):
        c.tick(t * 1000, [0] * c.n)
    assert (c.program_status().end, c.program_status().ticks) == (ProgramEnd.DONE, 100)


def test_the_host_refuses_what_the_core_would_before_sending():
    for bad in ([(0.81, 0.1)], [(0.1, 0.1)] * (PAD + 1), [(0.1, P.PROGRAM_MAX_MS / 1000), (0.1, 0.001)],
                [(0.1, 0.0)], []):
        with pytest.raises(ValueError):
            program_message(2, bad, (-10, 10))
    with pytest.raises(ValueError):
        program_message(2, [(0.1, 0.1)], (10, 10))
    assert program_message(2, [(0.8, 0.1)], (-10, 10)).duty[0] == MAX_WIRE


# ---- chained PULSEs (issue 40, attack 4) ---------------------------------------------------------

def test_chained_pulses_stop_at_the_hinges_range_on_drawn_plants(spec):
    """PULSE at its largest back to back on hinge 1 (and 2), each way, hanging: each stops at the range
    (before it, by the look-ahead), never passes +-limit_counts nor the LIMIT threshold; before they were
    a program, they reached 390 counts against +-376."""
    lim = core.config_from_spec(spec).limit_counts
    for seed in (1, 2):
        emu = Emulator(spec, drawn_options(PlantRanges(), FaultOptions(), seed, zeroed=True))
        reach, seq = [], 1
        for hinge, sign in ((1, 1), (1, -1), (2, -1)):
            for _ in range(2):
                emu.receive(P.encode(P.Pulse(hinge, sign * int(P.PULSE_MAX_DUTY * P.DUTY_SCALE), P.PULSE_MAX_MS),
                                     seq))
                seq += 1
                for _ in range(P.PULSE_MAX_MS + 50):
                    emu.step()
                    reach.append(np.abs(emu.counts[hinge]))
                emu.take_output()
            assert max(reach) > lim - 60, (seed, hinge, max(reach))  # it did go to the range
        assert max(reach) <= lim and emu.firmware.state == P.State.IDLE and emu.firmware.faults == 0, max(reach)


@pytest.mark.slow
def test_programs_at_full_duty_stop_inside_their_window_on_drawn_plants(spec):
    """Every hinge of 4 drawn plants, hanging and lying flat, driven at the largest duty toward the range both
    ways: the window (the range) ends each program, and the braked hinge coasts to a stop before the range's
    edge (with a 30 ms look-ahead one lying flat coasted 7 counts past it)."""
    lim = core.config_from_spec(spec).limit_counts
    worst, ended = -lim, 0
    for seed in range(1, 5):
        for flat in (False, True):
            opt = drawn_options(PlantRanges(), FaultOptions(), seed, zeroed=True)
            opt = dataclasses.replace(opt, plant=dataclasses.replace(opt.plant, mount="flat" if flat else "hanging"))
            for hinge in range(spec.n_hinges):
                for sign in (1, -1):
                    emu = Emulator(spec, opt)
                    for _ in range(300):  # the flaps sag or settle first
                        emu.step()
                    at = int(emu.counts[hinge])
                    window = (at - 1, lim) if sign > 0 else (-lim, at + 1)
                    if not -lim < at < lim:
                        continue
                    emu.receive(P.encode(program_message(hinge, [(sign * P.PROGRAM_MAX_DUTY, 1.5)], window), 1))
                    out = bytearray()
                    for i in range(1700):
                        if i % 50 == 0:
                            emu.receive(P.encode(P.Heartbeat(), 2 + i))
                        emu.step()
                        out += emu.take_output()
                        worst = max(worst, sign * int(emu.counts[hinge]) - lim)
                    emu.receive(P.encode(P.GetProgram(), 9999))
                    for _ in range(10):  # the drawn command latency: up to 3 ms
                        emu.step()
                    (status,) = [m for _, m in P.Decoder().feed(bytes(out) + emu.take_output())
                                 if isinstance(m, P.ProgramStatus)]
                    ended += status.end == ProgramEnd.WINDOW
    assert worst < 0 and ended > 60, (worst, ended)


# ---- one program everywhere --------------------------------------------------------------------

SEGMENTS = [(0.3, 0.08), (COAST, 0.05), (-0.5, 0.1), (0.6, 0.1)]
WINDOW = (-200, 200)


def emulated_program(spec, opt, segments, window, ticks, heartbeat_every=50, hinge=2):
    """Run a program on an in-process emulator: (samples [(seq, ProgramSample)], ProgramStatus, emulator)."""
    emu = Emulator(spec, opt)
    emu.receive(P.encode(program_message(hinge, segments, window), 1))
    out = bytearray()
    for i in range(ticks):
        if heartbeat_every and i % heartbeat_every == 0:
            emu.receive(P.encode(P.Heartbeat(), 2 + i))
        emu.step()
        out += emu.take_output()
    emu.receive(P.encode(P.GetProgram(), 9999))
    for _ in range(10):  # the command latency, if any
        emu.step()
        out += emu.take_output()
    got = P.Decoder().feed(bytes(out))
    (status,) = [m for _, m in got if isinstance(m, P.ProgramStatus)]
    return [(s, m) for s, m in got if isinstance(m, P.ProgramSample)], status, emu


def test_the_twin_the_batch_twin_and_the_emulator_run_a_program_alike_to_the_count(spec):
    single = Twin(spec).run_program(2, SEGMENTS, WINDOW)
    assert single.end == "window" and 150 < len(single.time_s) < 330  # it reversed, then met the window
    batch = TwinBatch(2, spec, nthread=1).run_program(2, SEGMENTS, WINDOW)
    opt = EmulatorOptions(plant=as_twin(spec), faults=FaultOptions(latency_ms=0.0), zeroed=True)
    samples, status, _ = emulated_program(spec, opt, SEGMENTS, WINDOW, 400)
    for run_ in batch:
        assert run_.end == single.end
        np.testing.assert_array_equal(run_.counts, single.counts)
        np.testing.assert_allclose(run_.duty, single.duty, atol=1e-6)
        np.testing.assert_array_equal(run_.coasting, single.coasting)
    assert P.ProgramEnd(status.end).name.lower() == single.end and status.ticks == len(single.counts)
    np.testing.assert_array_equal([m.counts for _, m in samples], single.counts)
    wire = np.array([m.duty for _, m in samples])
    np.testing.assert_array_equal(wire == P.PROGRAM_COAST, single.coasting)
    np.testing.assert_allclose(np.where(single.coasting, 0, wire) / P.DUTY_SCALE, single.duty, atol=1e-4)
    np.testing.assert_allclose(single.duty[:80], 0.3, atol=1e-4)
    assert single.coasting[80:130].all() and single.coasting.sum() == 50 and not single.duty[80:130].any()


def test_the_sketch_in_the_loop_ends_programs_itself(spec):
    """The whole ESP32-S3 sketch: the same program as the twin within a few counts; then each way the core
    ends a program on the board: window, stall (a jammed hinge), timeout, a host gone quiet."""
    single = Twin(spec).run_program(2, SEGMENTS, WINDOW)
    base = EmulatorOptions(plant=as_twin(spec), faults=FaultOptions(latency_ms=0.0), zeroed=True, sketch=True)
    samples, status, _ = emulated_program(spec, base, SEGMENTS, WINDOW, 400)
    counts = np.array([m.counts for _, m in samples])
    assert status.end == ProgramEnd.WINDOW and abs(len(counts) - len(single.counts)) <= 5
    n = min(len(counts), len(single.counts))
    assert np.abs(counts[:n] - single.counts[:n]).max() <= 3
    jam = EmulatorOptions(plant=as_twin(spec), faults=FaultOptions(latency_ms=0.0, jam_hinge=2, jam_after=0.02),
                          zeroed=True, sketch=True)
    _, status, _ = emulated_program(spec, jam, [(0.5, 1.0)], (-370, 370), 600)
    stall_ms = core.config_from_spec(spec).stall_ms
    assert status.end == ProgramEnd.STALL and stall_ms < status.ticks < stall_ms + 60, status
    _, status, _ = emulated_program(spec, base, [(0.05, 0.3), (-0.05, 0.3)], (-370, 370), 400)
    assert (status.end, status.ticks) == (ProgramEnd.DONE, 600) or status.end == ProgramEnd.RUNNING
    timeout = program_message(2, [(0.05, 0.3)], (-370, 370), timeout_s=0.12)
    emu = Emulator(spec, base)
    emu.receive(P.encode(timeout, 1))
    for i in range(200):
        if i % 50 == 0:
            emu.receive(P.encode(P.Heartbeat(), 2 + i))
        emu.step()
    emu.take_output()
    emu.receive(P.encode(P.GetProgram(), 99))
    for _ in range(3):
        emu.step()
    (status,) = [m for _, m in P.Decoder().feed(emu.take_output()) if isinstance(m, P.ProgramStatus)]
    assert (status.end, status.ticks) == (ProgramEnd.TIMEOUT, 120)
    _, status, _ = emulated_program(spec, base, [(0.05, 1.0)], (-370, 370), 400, heartbeat_every=0)
    watchdog = core.config_from_spec(spec).watchdog_ms
    assert status.end == ProgramEnd.HOST_QUIET and watchdog <= status.ticks <= watchdog + 5, status


def test_the_sketch_in_the_loop_coasts_and_brakes_where_the_core_ends_it(spec):
    """The whole ESP32-S3 sketch: a raise, then a coast (the plant's motor with its windings open: the flap
    rises on, turns and falls under its weight) that its window's edge, its timeout or a host gone quiet ends;
    from each end the bridge brakes."""
    base = EmulatorOptions(plant=as_twin(spec), faults=FaultOptions(latency_ms=0.0), zeroed=True, sketch=True)
    cases = [((-370, 100), None, 50, ProgramEnd.WINDOW), ((-370, 370), 0.15, 50, ProgramEnd.TIMEOUT),
             ((-370, 370), None, 0, ProgramEnd.HOST_QUIET)]
    for window, timeout_s, heartbeat_ms, end in cases:
        emu = Emulator(spec, base)
        emu.receive(P.encode(program_message(2, [(0.4, 0.06), (COAST, 1.0)], window, timeout_s), 1))
        coasted, out = [], bytearray()
        for i in range(400):
            if heartbeat_ms and i % heartbeat_ms == 0:
                emu.receive(P.encode(P.Heartbeat(), 2 + i))
            emu.step()
            coasted.append(emu.plant.decay[2] == DECAY_COAST)
            out += emu.take_output()
        emu.receive(P.encode(P.GetProgram(), 9999))
        for _ in range(3):
            emu.step()
        (st,) = [m for _, m in P.Decoder().feed(bytes(out) + emu.take_output()) if isinstance(m, P.ProgramStatus)]
        coasted = np.array(coasted)
        assert st.end == end and 100 < st.ticks < 400, (end, st)
        assert coasted[65:st.ticks - 2].all() and not coasted[:55].any() and not coasted[st.ticks + 3:].any(), end


# ---- over a real pty -------------------------------------------------------------------------------

@pytest.mark.parametrize("sketch", [False, pytest.param(True, marks=pytest.mark.slow)], ids=["core", "sketch"])
def test_a_program_over_a_pty_returns_every_tick(emulator, sketch):
    """Link.run_program against `vrscroll emulate` (the core, or the whole sketch) on its pseudo-terminal: the
    device ends the program at its window, the host gets a sample per tick with the applied duty, and a
    program the device refuses is a NackError."""
    dev = emulator(*(["--sketch"] if sketch else []))
    with Link(dev.port) as link:
        run_ = link.run_program(2, [(0.4, 0.1), (0.0, 0.05), (-0.4, 0.6)], (-150, 150))
        with pytest.raises(NackError, match="OUT_OF_RANGE"):
            link.run_program(2, [(0.1, 0.1)], (100, 200))  # the hinge is not inside this window
        state = link.get_state()
    assert run_.end == "window" and run_.hinge == 2 and run_.battery_mV and run_.battery_mV > 5000
    assert len(run_.time_s) + run_.samples_lost > 150 and run_.samples_lost <= 5, run_.samples_lost
    assert np.all(np.diff(run_.time_s) > 0) and run_.counts.dtype.kind == "i"
    first = run_.time_s < 0.1
    np.testing.assert_allclose(run_.duty[first], 0.4, atol=1e-4)
    assert run_.counts[first][-1] > 20 and run_.counts[-1] < 0 and -150 <= run_.counts.min()
    assert state.state == P.State.IDLE and state.faults == 0
