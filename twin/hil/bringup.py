"""Bring-up of a new board, as ODrive's and Klipper's commands check each motor and encoder and say what is wrong.

`bring_up(link, spec)` measures the wiring as it is (the device's correction set to the identity first):
for each hinge, a short low-duty pulse of its motor each way, open loop (PULSE), and the encoder input that
answers; where the hinge's own input does not, stronger and longer pulses, up to the firmware's largest
(PULSES: lying flat, the hinges beside the root flap lift three flaps, and the first pulse barely moves
them). The encoder that moves most between the two pulses is the hinge's (another hinge's, at the strongest
pulse: the cables are crossed); its sign says whether the motor turns the encoder up for positive drive; its size, against
the spec's no-load speed, whether the counts per degree are plausible. A motor that turns no encoder is a
dead encoder or an unconnected motor: named, and the hinge disabled on the device (braked, never driven, through
any CLEAR_FAULT and power cycle) until a bring-up run finds it healthy; nothing else stored. An encoder counting down for positive drive
means the motor's leads or the encoder's A and B are swapped, and the wrong guess leaves the device reporting
+10 deg for a flap standing at -10 deg. A person tells them apart by bending the flap up by hand (`hand`);
without one, lying flat, the table does (`lifting_way`: the way that lifts the flap moves it freely, the other
pushes it into the table, blocked beside the root and tenting the flaps further out), asked of every hinge: an
encoder and a motor both reversed count up for positive drive as a hinge wired right does, and only the table
tells them apart; where the pulses show no table (hanging: at the flaps' rest gravity's pull along the hinge
vanishes) bring-up names the hinge, says how to decide, and stores nothing. The hand's
bend also names the flap's own encoder input: the bridge whose pulses turned that input drives the flap's motor
(motors on each other's bridges, corrected by the bridge map). Hanging, gravity adds to the pulse that lowers a
flap, so after a hinge's pulses short pulses hold the flap they turned where they found it, and a flap hanging
within a pulse's reach of its range is lifted before it is pulsed. The correction goes to the device (SET_WIRING, kept
across power cycles), which leaves its zero unconfirmed. Units: counts, s, duty.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from controllers.sketch import wiring as board_wiring
from twin.device.spec import DeviceSpec
from twin.errors import UserError
from twin.link import protocol as P
from twin.hil.mirror import mirror
from twin.link.serial_link import Link

# (duty, s) of the bring-up pulses, each tried only where none before moved the hinge's own encoder input most
# and by MIN_SHARE of the first's no-load reach: lying flat, hinges 2-3 of the emulator's drawn plants moved
# 1-18 counts at the first two and 40-126 at the last, where the outer hinges move 143-269 (so each hinge
# starts at the first); at the second, a neighbour back-driven by the lift moved up to twice as far as the
# hinge itself, so another input answering is taken (cables crossed) only at the last
PULSES = ((0.2, 0.05), (0.3, 0.1), (P.PULSE_MAX_DUTY, 0.15))
PULSE_DUTY, PULSE_S = PULSES[0]
SETTLE_S = 0.1  # s waited after a pulse before the counts are read
MIN_SHARE = 0.15  # the answering encoder must move at least this share of what the spec's no-load speed gives
MAX_SHARE = 1.6  # ... and at most this share (more: counts per degree unlike the spec's)
HAND_COUNTS = 15  # counts a hand's bend must move an encoder by
HOLD_SHARE = 0.2  # a flap is held where the pulses found it: brought back unless within this share of a pulse
# the weaker way's share of the stronger below which a motor turns one way only (a bridge input open), judged at
# the strongest pulse: the first pulse lifts or pushes, the second brings the flap back, so a healthy hinge moved
# both ways alike (the emulator's plants, lying flat and hanging: 0.55-1.0 at the strongest; hanging, at the first
# pulse hinge 3 moved 6 counts up against gravity and 30 down with it, so a weaker pulse cannot judge)
ONE_WAY_SHARE = 0.25
# Lying flat, which way lifts a flap tells a reversed encoder from a reversed motor: at the strongest pulse, each way
# from the flap's rest, the way that lifts it off the table moves it freely and the other pushes it into the table.
# Beside the root that way is blocked (benchmarks/bench_bringup_table.py: the spec's plant and drawn seeds 7-61, at
# most 0.02 of the lifting way's counts, 41-124); further out the flap tents, its outer end on the table, lifting
# the flaps between it and the root (the inputs between: 0.35-0.59 of its own counts pushing, at most 0.01
# lifting). Hanging, the same pulses from the flaps' rest moved beside the root 0.53-0.98 as far one way as the
# other, either way the larger, further out the inputs between at most 0.12 of its own either way; from flaps still
# sagging (100 ms after power-on) 0.18-0.37 beside the root and up to 0.63 pushing further out, which could pass for
# a table: so the flaps must be still first (lying flat, nothing sags), and where the pulses do not show a flap on
# a table, nothing is decided.
# beside the root: the pushing way moves the hinge's input at most this share of the lifting way. Asked of every hinge
# (a hinge wired right too), the slow sweeps saw hinge 2 of drawn seeds 37 and 47 lying flat push 0.10-0.16 of its
# lift (14-19 counts of 98-126: after its lifting pulse and the hold); hanging, 0.53 at the least: the bar between
BLOCKED_SHARE = 0.25
TENT_SHARE = 0.25  # further out: pushing moves the inputs between it and the root by at least this share of its own
STILL_SHARE = 0.12  # ... and lifting by at most this share
STILL_COUNTS, STILL_S, STILL_WAIT_S = 1, 0.2, 2.0  # still: no input moves more than this many counts in STILL_S


BRIDGES_PER_BOARD = 2  # each DRV8833 carries bridges A and B: bridge k is board k // 2 + 1's (docs/firmware.md)
# what bring-up leaves a board it cannot correct with: nothing stored, every bridge braked and latched there
LEFT = ("the device keeps its wiring as built and is left e-stopped, every bridge braked: it takes no target until "
        "the fault is cleared (`vrscroll status --serial PORT --clear-fault`) or it is powered off and on (then "
        "not before `vrscroll zero`)")
MEND = ("no correction drives a hinge with a dead wire safely (docs/firmware.md, \"What software cannot mend\"): "
        "mend it and run bring-up again")


def encoder_pins(hinge: int) -> str:
    """Where to measure hinge's encoder (pins.h): its connector's supply and its two channels' GPIOs."""
    w = board_wiring()
    return (f"encoder {hinge}'s connector: 3.3 V between Vcc and GND, and A (GPIO{w.enc_a[hinge]}) and B "
            f"(GPIO{w.enc_b[hinge]}) each switching between 0 and 3.3 V as flap {hinge} is turned slowly by hand "
            "(a channel that stays put is dead)")


def bridge_pins(bridge: int, pin: str | None = None) -> str:
    """Where to measure bridge's inputs (pins.h) and outputs: its DRV8833 board and channel; pin: 'IN1' or 'IN2'
    alone."""
    w = board_wiring()
    board, ch = bridge // BRIDGES_PER_BOARD + 1, "AB"[bridge % BRIDGES_PER_BOARD]
    gpio = {"IN1": w.in1[bridge], "IN2": w.in2[bridge]}
    ins = [pin] if pin else ["IN1", "IN2"]
    return (f"DRV8833 board {board}, channel {ch}: " + " and ".join(f"{ch}{i} (from GPIO{gpio[i]})" for i in ins)
            + f", {ch}OUT1 and {ch}OUT2 to the motor")


class BringupError(UserError):
    """The board cannot be corrected from here (a dead encoder, a set-up fault): what is wrong, per line."""


@dataclasses.dataclass(frozen=True)
class HingeCheck:
    """What the pulses (and the hand) found for one hinge: the input its encoder is on, the bridge its motor is on."""

    hinge: int
    encoder: int  # the encoder input that is the hinge's
    encoder_reversed: bool
    motor_reversed: bool
    counts: float  # |counts| the encoder moved per pulse
    expected: float  # |counts| the spec's no-load speed would give, an upper bound
    note: str  # what was wrong, "" if nothing
    decided: bool = True  # False: not corrected here (named, nothing stored): a person decides or rewires
    bridge: int | None = None  # the H-bridge that drives its motor (None: bridge `hinge`, until bring_up maps them)
    turns: int | None = None  # the encoder input bridge `hinge`'s pulses turned (None: `encoder`)
    turns_up: bool = True  # whether positive drive of bridge `hinge` turned that input up
    told: str = ""  # how the encoder's direction was told without a hand (lying flat: the way that lifts), for the note
    dead: bool = False  # a dead wire named (no encoder answered, a bridge input open, a motor unconnected): disabled
    no_table: bool = False  # without a hand, the way that lifts the flap was asked and the pulses showed no table

    @property
    def flags(self) -> int:
        return (P.WIRING_ENCODER_REVERSED if self.encoder_reversed else 0) | \
            (P.WIRING_MOTOR_REVERSED if self.motor_reversed else 0)


def pulse_counts(spec: DeviceSpec, duty: float = PULSE_DUTY, seconds: float = PULSE_S) -> float:
    """|counts| a pulse turns the output at the spec's no-load speed (rad/s at duty 1): an upper bound."""
    return spec.no_load_speed * duty * seconds / spec.rad_per_count


def _device_wait(link: Link, since_us: int, seconds: float) -> P.StateMsg:
    """The device's state once its own clock (STATE's time_us, wrapping us) is `seconds` past since_us. Waits are
    the device's time, not the host's: a device that runs slower than the wall clock (an emulator starved by its
    host's load) used to be read mid-pulse, the rest of the pulse then counted in the next, and on drawn seed 61
    lying flat motors on each other's bridges were named as a dead encoder 2 runs in 25 under load."""
    while True:
        state = link.get_state()
        left = seconds - P.elapsed_s(since_us, state.time_us)
        if left <= 0:
            return state
        time.sleep(left)


def _measure(link: Link, hinge: int, duty: float, seconds: float) -> np.ndarray:
    """Each encoder input's change over one pulse of hinge's motor at duty for seconds (and SETTLE_S after it)."""
    before = np.asarray(link.get_state().counts)
    started = link.pulse(hinge, duty, seconds).time_us
    return np.asarray(_device_wait(link, started, seconds + SETTLE_S).counts) - before


def _toward(link: Link, bridge: int, j: int, goal: float, way: float, duty: float, seconds: float,
            per_pulse: float, tries: int = 4) -> int:
    """Short pulses of bridge (each from a braked start) bring encoder input j toward goal counts: way is the sign
    in which positive duty turns input j, per_pulse the counts a pulse of duty for seconds turned it. Hanging,
    gravity adds to the pulse that lowers a flap and takes from the one that lifts it: a pair of pulses leaves it
    lower, and a few pairs sag it to its range; these hold it where bring-up found it. Returns input j's counts."""
    at = link.get_state().counts[j]
    for _ in range(tries):
        off = at - goal
        if abs(off) <= HOLD_SHARE * per_pulse:
            break
        length = round(min(seconds, max(0.01, seconds * abs(off) / per_pulse)), 3)
        started = link.pulse(bridge, -float(np.sign(off) * way) * duty, length).time_us
        at = _device_wait(link, started, length + SETTLE_S).counts[j]
    return at


def _lift(link: Link, hinge: int, expected: float, limit: float) -> int | None:
    """Hinge's own input's counts, after short pulses of its bridge lifted it off its range where it hung within a
    pulse's reach of it (a probe first, which the firmware's range ends if it goes the wrong way: its answer says
    which way lifts); None where the bridge does not turn that input (another hinge's motor: its pulses leave it
    where it hangs)."""
    at = link.get_state().counts[hinge]
    if abs(at) + expected <= limit or abs(at) >= limit:  # beyond its range the firmware refuses every pulse
        return at
    duty, seconds = PULSES[0]
    moved = _measure(link, hinge, duty, seconds)[hinge]
    if abs(moved) < MIN_SHARE * expected:
        return None
    goal = np.sign(at) * (limit - 2 * expected)
    return _toward(link, hinge, hinge, goal, np.sign(moved), duty, seconds, abs(moved), tries=8)


def _still(link: Link) -> bool:
    """Whether the flaps come to rest (no input moving by more than STILL_COUNTS in STILL_S) within STILL_WAIT_S,
    both the device's time."""
    first = last = link.get_state()
    while True:
        now = _device_wait(link, last.time_us, STILL_S)
        if np.abs(np.asarray(now.counts) - np.asarray(last.counts)).max() <= STILL_COUNTS:
            return True
        if P.elapsed_s(first.time_us, now.time_us) > STILL_WAIT_S:
            return False
        last = now


def between_root(spec: DeviceSpec, hinge: int) -> list[int]:
    """The hinges between `hinge` and the root flap (flap k lies between hinges k - 1 and k)."""
    r = spec.root_flap
    return list(range(hinge + 1, r)) if hinge < r else list(range(r, hinge))


def lifting_way(link: Link, spec: DeviceSpec, hinge: int, goal: float, way: float) -> tuple[int | None, str]:
    """Lying flat: the sign of the duty that lifts flap `hinge` off the table (+1, -1; None where the pulses do not
    show a device lying flat), and the figures that say so. The strongest pulse each way from the flap's rest (held
    back at `goal` counts between them; way: the sign in which positive duty turns the hinge's input): the lifting
    way moves it freely; the other is blocked (beside the root) or tents the flap, its outer end on the table, and
    lifts the flaps between it and the root (further out)."""
    duty, seconds = PULSES[-1]
    moved = {}
    for sign in (1, -1):
        if not _still(link):
            return None, f"the flaps did not come to rest within {STILL_WAIT_S:g} s (lying flat, nothing sags)"
        moved[sign] = _measure(link, hinge, sign * duty, seconds)
        _toward(link, hinge, hinge, goal, way, duty, seconds, max(abs(moved[sign][hinge]), 1.0))
    own = {sign: abs(float(m[hinge])) for sign, m in moved.items()}
    lift = 1 if own[1] >= own[-1] else -1
    push = -lift
    agrees = np.sign(moved[lift][hinge]) == lift * way  # the pulses from rest turn the input as the pairs did
    beside = between_root(spec, hinge)
    if not beside:
        shown = own[push] <= BLOCKED_SHARE * own[lift]
        figures = (f"at duty {duty:g} for {seconds:g} s from rest, {own[lift]:.0f} counts one way and {own[push]:.0f} "
                   f"the other (lying flat beside the root, the way into the table moves at most "
                   f"{BLOCKED_SHARE:g} of the other)")
    else:
        def share(m):
            return float(np.abs(m[beside]).sum()) / max(abs(float(m[hinge])), 1.0)
        shown = share(moved[push]) >= TENT_SHARE and share(moved[lift]) <= STILL_SHARE
        named = ("hinges " if len(beside) > 1 else "hinge ") + ", ".join(map(str, beside))
        figures = (f"at duty {duty:g} for {seconds:g} s from rest, {own[lift]:.0f} counts one way moving {named} by "
                   f"{share(moved[lift]):.2f} of that, {own[push]:.0f} the other moving them by "
                   f"{share(moved[push]):.2f} (lying flat, pushing into the table tents the flap and "
                   f"lifts them by at least {TENT_SHARE:g}, lifting moves them at most {STILL_SHARE:g})")
    return (lift if shown and agrees else None), figures


def check_hinge(link: Link, spec: DeviceSpec, hinge: int, hand=None) -> HingeCheck:
    """Pulse one hinge's motor each way and name what answers (the device IDLE, its wiring the identity)."""
    expected = pulse_counts(spec)
    limit = spec.hinge_limit / spec.rad_per_count  # counts
    # the gate of the first pulse: its farthest reach unloaded stays inside the range (the two pulses go opposite
    # ways); the stronger ones follow only where it moved the hinge's own input little (a load, or no encoder), and
    # the firmware's range ends every pulse. Hanging, hinges 2-3 sag to 70-98 deg within seconds (the emulator's
    # drawn plants): a flap that near its range is first lifted by short pulses of its bridge from the braked start
    at = _lift(link, hinge, expected, limit)
    if at is not None and abs(at) + expected > limit:
        return HingeCheck(hinge, hinge, False, False, 0.0, expected,
                          f"hinge {hinge}: at {abs(at)} counts from flat, too near its range for a pulse, and its "
                          "bridge's pulses did not lift it: lay the device flat and run again", decided=False)
    start = np.asarray(link.get_state().counts)
    for duty, seconds in PULSES:  # stronger while no encoder answers, or another input than the hinge's own
        up, down = _measure(link, hinge, duty, seconds), _measure(link, hinge, -duty, seconds)
        swing = (up - down) / 2  # sagging cancels
        j = int(np.argmax(np.abs(swing)))
        moved = float(abs(swing[j]))
        weak, strong = sorted((abs(up[j]), abs(down[j])))
        # each pulse against its own reach: at the second, a neighbour's motor turned this input from beside by 12
        # counts (12 of its 187 unloaded), above the first pulse's bar, and with the motors of hinges 1 and 2 on each
        # other's bridges (drawn seed 61 lying flat) that input was taken for the hinge's own 1 run in 10
        if moved >= MIN_SHARE * pulse_counts(spec, duty, seconds) and j == hinge and weak >= ONE_WAY_SHARE * strong:
            break
    if moved < MIN_SHARE * expected:
        return HingeCheck(hinge, hinge, False, False, moved, expected,
                          f"hinge {hinge}: its motor was pulsed and no encoder answered ({moved:.0f} counts at "
                          f"duty {duty:g} for {seconds:g} s; at duty {PULSE_DUTY:g} for {PULSE_S:g} s it turns "
                          f"up to {expected:.0f} unloaded): a dead encoder (power, or an A or B wire: one channel "
                          f"alone counts back and forth by one) or a motor not connected to bridge {hinge} (its "
                          f"leads, or a bridge input open). Measure {encoder_pins(hinge)}; if both switch, the "
                          f"motor's wires: {bridge_pins(hinge)}; {MEND}", decided=False, dead=True)
    expected = pulse_counts(spec, duty, seconds)  # the pulse that answered: its reach unloaded
    if (duty, seconds) == PULSES[-1] and weak < ONE_WAY_SHARE * strong:
        # lying flat, a hinge beside the root driven the wrong way first pushes into the table (blocked), then lifts:
        # a third pulse, the first's way again, brings it back where that way is driven at all
        again = _measure(link, hinge, duty, seconds)
        weak, strong = sorted((max(abs(up[j]), abs(again[j])), abs(down[j])))
    # hanging, gravity helped each pulse that lowered the flap: held where the pulses found it (once the input it
    # turns is known: at a weaker pulse the input that moved most may be a neighbour's, turned from beside)
    _toward(link, hinge, j, start[j], np.sign(swing[j]), duty, seconds, moved)
    if (duty, seconds) == PULSES[-1] and weak < ONE_WAY_SHARE * strong:  # a healthy hinge moved both ways
        way, pin = ("positive", "IN2") if abs(up[j]) < abs(down[j]) else ("negative", "IN1")
        return HingeCheck(hinge, j, False, False, moved, expected,
                          f"hinge {hinge}: its motor turns one way only ({up[j]:+.0f} counts at positive duty, "
                          f"{down[j]:+.0f} at negative): bridge {hinge}'s {pin}, which drives the {way} way, is "
                          "open (the board's pull-up holds it high: that way brakes). Measure "
                          f"{bridge_pins(hinge, pin)}: the board off, {pin} and its GPIO connected (under an ohm); "
                          f"powered, {pin} falling to 0 V while that way is pulsed, not staying at 3.3 V; {MEND}",
                          decided=False, dead=True)
    if hand is not None:
        bent = np.asarray(hand(hinge))
        # of the input that answered the bridge and the hinge's own, the one the bend moved more (the others may be
        # sagging meanwhile): the flap's encoder; the bridge that turns it is its motor's (bring_up maps them)
        k = j if abs(bent[j]) >= abs(bent[hinge]) else hinge
        if abs(bent[k]) < HAND_COUNTS:
            return HingeCheck(hinge, j, False, False, moved, expected,
                              f"hinge {hinge}: the hand's bend moved input {j} by {bent[j]:.0f} counts and input "
                              f"{hinge} by {bent[hinge]:.0f}: bend flap {hinge}'s free end up by about 20 deg and run "
                              "again", decided=False)
        return HingeCheck(hinge, k, bool(bent[k] < 0), False, moved, expected, "", turns=j,
                          turns_up=bool(swing[j] > 0))
    which = "pulses cannot tell which"
    if j == hinge:
        # lying flat, the way that lifts the flap says which is reversed: the encoder counts that way's sign, the
        # duty's sign is the motor's. Asked of a hinge counting up too: an encoder and a motor both reversed count up
        # for positive drive, and the flap moves opposite to what the device reports (the first gated move "settled"
        # at +10 deg with the flap at -10)
        lift, figures = lifting_way(link, spec, hinge, start[j], np.sign(swing[j]))
        if lift is not None:
            return HingeCheck(hinge, j, bool(lift * swing[j] < 0), False, moved, expected, "", turns=j,
                              turns_up=bool(swing[j] > 0),
                              told=f"told lying flat: duty {'+' if lift > 0 else '-'} lifts the flap, {figures}")
        which = (f"lying flat, the way that lifts the flap would tell which, but the pulses did not show a flap on "
                 f"a table ({figures})")
    what = [f"hinge {hinge}: its bridge turns encoder input {j}: the encoder cables of hinges {hinge} and {j} "
            "are crossed, or their motors are on each other's bridges"] if j != hinge else []
    what += [reversal(hinge, j, swing[j] > 0)] if j == hinge or swing[j] < 0 else []
    return HingeCheck(hinge, j, False, False, moved, expected,
                      "; ".join(what) + f"; {which}. {how_to_decide(hinge, j == hinge)}", decided=False,
                      no_table=j == hinge)


def reversal(hinge: int, j: int, up: bool) -> str:
    """What pulses say of hinge's bridge turning input j up (or down) for positive drive."""
    if up:
        return (f"hinge {hinge}: positive drive turns encoder input {j} up: as built, or with its encoder's A and B "
                "and its motor's leads both swapped (then the flap moves opposite to what the device reports, and "
                "pulses see nothing wrong)")
    return (f"hinge {hinge}: positive drive turns encoder input {j} down: its motor's leads or its encoder's A and "
            "B are swapped")


def how_to_decide(hinge: int, table: bool = True) -> str:
    """How a person tells a reversed encoder from a reversed motor on hinge (and crossed encoder cables from motors on
    each other's bridges); table: whether lying flat would tell the first without a hand."""
    return (("Lay the device flat on a table and run again, or run" if table else "Run") + " `vrscroll bringup "
            f"--hand` and bend the flap up when asked (or bend flap {hinge}'s free end up by hand watching `vrscroll "
            "status --watch`: the input that moves is its encoder's; counting down, swap that encoder's A and B; then "
            "positive drive counting down, swap the motor's leads)")


def on_one_table(checks: list[HingeCheck]) -> list[HingeCheck]:
    """Without a hand, a direction told by the table only where no hinge asked showed none: lying flat every hinge
    shows the table, and a device held otherwise (hanging) can pass for one on a single hinge (hinge 4 hanging on
    drawn seed 23, after the table test of the hinges before it had moved their flaps): there each told hinge is
    named, not corrected."""
    none = [c.hinge for c in checks if c.no_table]
    if not none:
        return checks
    shown = f"hinge{'s' if len(none) > 1 else ''} {', '.join(map(str, none))} showed no table"
    return [dataclasses.replace(c, encoder_reversed=False, decided=False, told="", note=(
        f"{reversal(c.hinge, c.encoder, c.turns_up)}; the way that lifts flap {c.hinge} seemed to tell which "
        f"({c.told}), but "
        f"{shown}: the device is not lying flat, and nothing is told. {how_to_decide(c.hinge)}")) if c.told else c
        for c in checks]


def mapped(checks: list[HingeCheck], spec: DeviceSpec) -> list[HingeCheck]:
    """Each hinge's bridge (the one whose pulses turned the hinge's encoder input) and flags, with what was wrong
    said; a hinge whose input no bridge turned, named and not decided. Units: counts."""
    by_input = {c.turns: c for c in checks}
    out = []
    for c in checks:
        b = by_input.get(c.encoder)
        if b is None:
            out.append(dataclasses.replace(c, decided=False, note=(
                f"hinge {c.hinge}: bending flap {c.hinge} turns input {c.encoder}, which no bridge's pulse turned: "
                "its motor is not connected (check its leads and its bridge's wires)"), dead=True))
            continue
        notes = []
        if c.encoder != c.hinge:
            notes.append(f"hinge {c.hinge}: its encoder is on input {c.encoder}: the encoder cables of hinges "
                         f"{c.hinge} and {c.encoder} are crossed (corrected: hinge {c.hinge} reads input {c.encoder})")
        if b.hinge != c.hinge:
            notes.append(f"hinge {c.hinge}: its motor is on bridge {b.hinge}: the motors of hinges {c.hinge} and "
                         f"{b.hinge} are on each other's bridges (corrected: hinge {c.hinge} drives bridge {b.hinge})")
        told = f", {c.told}" if c.told else ""
        if c.encoder_reversed:
            notes.append(f"hinge {c.hinge}: its encoder counts down when the flap bends up: A and B swapped "
                         f"(corrected: counted the other way{told})")
        motor_reversed = b.turns_up == c.encoder_reversed
        if motor_reversed:
            notes.append(f"hinge {c.hinge}: positive drive turns it the negative way: motor leads swapped "
                         f"(corrected: driven the other way{told})")
        if b.counts > MAX_SHARE * b.expected:
            notes.append(f"hinge {c.hinge}: {b.counts:.0f} counts per pulse, more than the spec's no-load speed "
                         f"allows ({b.expected:.0f}): counts per degree unlike the spec's (gear ratio, encoder CPR)")
        out.append(dataclasses.replace(c, motor_reversed=motor_reversed, counts=b.counts, expected=b.expected,
                                       bridge=b.hinge, note="; ".join(notes)))
    return out


def bring_up(link: Link, spec: DeviceSpec, hand=None, say=print) -> list[HingeCheck]:
    """Check the board, measure each hinge's wiring, store the correction on the device. BringupError, and nothing
    stored, for what cannot be corrected here."""
    info = link.info
    say(f"firmware {'.'.join(map(str, info.firmware))}, protocol {info.protocol}, {info.n_hinges} hinges; started "
        f"{P.enum_name(P.ResetReason, info.reset_reason)}")
    if info.setup_error != P.SetupStep.NONE:
        raise BringupError(f"the board's set-up failed at {P.enum_name(P.SetupStep, info.setup_error)}: nothing "
                           "moves until it starts (docs/firmware.md, 'Set-up faults')")
    state = link.get_state()
    if state.state == P.State.FAULT and state.faults == P.Fault.WATCHDOG:
        link.clear_fault()
        state = link.get_state()
    if state.state != P.State.IDLE:
        raise BringupError(f"the device is {P.enum_name(P.State, state.state)}: bring-up starts from IDLE "
                           "(`vrscroll status --serial PORT --clear-fault`, or power it off and on)")
    n = spec.n_hinges
    link.set_wiring(range(n), [0] * n, range(n))  # measure the wires as they are
    checks = []
    for k in range(n):
        c = check_hinge(link, spec, k, hand)
        plain = c.decided and c.turns == k and c.turns_up and not c.encoder_reversed
        say(f"hinge {k}: encoder input {c.encoder if c.turns is None else c.turns}, {c.counts:.0f} counts per pulse "
            f"(at most {c.expected:.0f}) " + ("ok" if plain else c.note.split(": ", 1)[1] if c.note else "see below"))
        checks.append(c)
    if hand is None:
        checks = on_one_table(checks)
    dead = [c.note for c in checks if not c.decided]
    off = {c.hinge for c in checks if c.dead}  # hinges with a dead wire: disabled on the device
    turned = [c.encoder if c.turns is None else c.turns for c in checks]
    for i in sorted({i for i in turned if turned.count(i) > 1}):
        both = [c.hinge for c in checks if i in (c.turns, c.encoder)]
        others = [h for h in both if h != i]
        off.update(others)
        dead.append(f"hinges {', '.join(map(str, both))} each turn encoder input {i}: hinge "
                    f"{', '.join(map(str, others))} moved it from beside, through the flaps (its own encoder dead, or "
                    f"its motor on another bridge); measure " + "; ".join(map(encoder_pins, others))
                    + f"; then each motor's bridge wires; if an encoder is dead, {MEND}")
    if not dead:
        checks = mapped(checks, spec)
        dead = [c.note for c in checks if not c.decided]
        off.update(c.hinge for c in checks if c.dead)
        inputs = [c.encoder for c in checks]
        twice = sorted({i for i in inputs if inputs.count(i) > 1})
        dead += [f"bending flaps {', '.join(str(c.hinge) for c in checks if c.encoder == i)} each turned input {i}: "
                 "bend each flap alone, the others held still" for i in twice]
    if dead:
        stored = "nothing stored"
        if off:  # the wires as built, the hinges with a dead wire disabled: braked through any CLEAR_FAULT
            link.set_wiring(range(n), [P.WIRING_DISABLED if k in off else 0 for k in range(n)], range(n))
            stored = (f"{'hinges' if len(off) > 1 else 'hinge'} {', '.join(map(str, sorted(off)))} disabled on the "
                      f"device (kept across power cycles: braked, never driven, until bring-up finds "
                      f"{'them' if len(off) > 1 else 'it'} healthy), nothing else stored")
        link.estop()  # latched: nothing moves until a person clears it
        raise BringupError(f"{stored}: " + "; ".join(dead) + f". {LEFT[0].upper()}{LEFT[1:]}")
    for c in checks:
        if c.note:
            say(c.note)
    inputs, flags, bridges = [c.encoder for c in checks], [c.flags for c in checks], [c.bridge for c in checks]
    link.set_wiring(inputs, flags, bridges)  # every hinge healthy: none disabled
    wiring = link.get_wiring()
    if (list(wiring.encoder), list(wiring.flags), list(wiring.bridge)) != (inputs, flags, bridges):
        raise BringupError(f"the device holds wiring {wiring}, not what was sent")
    return checks


FIRST_MOVE_DEG = 10.0  # the first gated move: every hinge this far, then back to flat


def first_move(link: Link, spec: DeviceSpec, tolerance_deg: float, say=print) -> None:
    """Bring-up's first gated move once the zero is confirmed: every hinge to FIRST_MOVE_DEG and back to flat,
    each leg said as it ends; tolerance_deg: the e-stop's bound on device against twin (twin.hil.mirror).
    UserError naming the outcome for a leg that does not settle; GateRefused for one the gate refuses."""
    for deg in (FIRST_MOVE_DEG, 0.0):
        # lying flat for the zero, as it still is: the twin holds it on its table too
        result = mirror(link, spec, np.radians([deg] * spec.n_hinges), tolerance_deg, mount="flat")
        say(f"move     every hinge to {deg:g} deg: {result.outcome}"
            + (f" (hinge {result.hinge})" if result.hinge is not None else ""))
        if result.outcome != "settled":
            raise UserError(f"the first gated move did not settle ({result.outcome}); check the hinge named")


def hand_by_prompt(link: Link, wait_s: float = 30.0, ask=input):
    """hand(hinge) for a person: asks for flap hinge to be bent up, returns each input's change (counts)."""
    def hand(hinge: int) -> np.ndarray:
        before = np.asarray(link.get_state().counts)
        ask(f"bend flap {hinge}'s free end up (toward the touch side) by about 20 deg and hold it; press Enter ")
        deadline = time.monotonic() + wait_s
        while True:
            moved = np.asarray(link.get_state().counts) - before
            if np.abs(moved).max() >= HAND_COUNTS or time.monotonic() > deadline:
                ask("let it go; press Enter ")
                return moved
            time.sleep(0.1)
    return hand

