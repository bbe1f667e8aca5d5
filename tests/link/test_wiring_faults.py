"""Each wiring fault the emulator injects (twin.link.faults), seen at the board's edge: one open-loop PULSE of one
bridge on the core in the loop, its plant lying flat (nothing sags: a hinge moves only when driven), and what the
plant's shafts did beside what the firmware's encoder inputs read. Bring-up's tests name and correct these faults;
these show that each fault is there to be found (issue 38, item 7: a dead encoder channel, a motor on the wrong
bridge, an open driver input, beside the swaps)."""

import dataclasses

import numpy as np
import pytest

from twin.link import protocol as P
from twin.link.emulator import Emulator, EmulatorOptions
from twin.link.faults import FaultOptions
from twin.sim.plant import as_twin

DUTY, PULSE_MS = 0.4, 150  # the firmware's strongest PULSE: an outer hinge moves 190-280 counts lying flat
MOVES = 100  # counts a pulsed shaft moves at least; a still one, at most STILL
STILL = 2


def pulsed(spec, wiring: tuple[str, ...], bridge: int, duty: float):
    """One PULSE of `bridge` at `duty` for PULSE_MS on an emulator with these wiring faults, lying flat, after 0.3 s
    at rest: (each plant shaft's change, counts (n,); each encoder input's change as the firmware read it, counts
    (n,); the pulsed input's count at each tick of the pulse from its PROGRAM_SAMPLEs, relative to before)."""
    flat = dataclasses.replace(as_twin(spec), mount="flat")
    emu = Emulator(spec, EmulatorOptions(plant=flat, faults=FaultOptions(latency_ms=0.0, wiring=wiring)))
    replies = P.Decoder()

    def send(msg, seq, ticks=1):
        emu.receive(P.encode(msg, seq))
        out = []
        for _ in range(ticks):
            emu.step()
            out += [m for _, m in replies.feed(emu.take_output())]
        return out

    def counts(seq):
        return np.array(next(m for m in send(P.GetState(), seq) if isinstance(m, P.StateMsg)).counts)

    for _ in range(300):
        emu.step()
    emu.take_output()
    before, shaft = counts(1), emu.plant.counts.copy()
    said = send(P.Pulse(bridge, round(duty * P.DUTY_SCALE), PULSE_MS), 2, PULSE_MS + 100)
    assert said[0].MSG == P.MsgId.ACK, said[0]
    samples = np.array([m.counts for m in said if isinstance(m, P.ProgramSample)]) - before[bridge]
    return emu.plant.counts - shaft, counts(3) - before, samples


def test_as_built_a_pulse_turns_its_own_shaft_and_its_own_input_alike(spec):
    """The reference for the faults below: bridge 5 turns motor 5, and input 5 reads it count for count."""
    shaft, board, _ = pulsed(spec, (), 5, DUTY)
    assert shaft[5] > MOVES and np.abs(np.delete(shaft, 5)).max() <= STILL, shaft
    assert np.array_equal(board, shaft), (board, shaft)


@pytest.mark.parametrize("fault, turns, reads", [("motor-reversed:5", -1, 1), ("encoder-reversed:5", 1, -1)])
def test_swapped_leads_turn_the_shaft_the_other_way_and_a_swapped_encoder_counts_it_the_other_way(spec, fault, turns,
                                                                                                  reads):
    shaft, board, _ = pulsed(spec, (fault,), 5, DUTY)
    assert turns * shaft[5] > MOVES and board[5] == reads * shaft[5], (shaft, board)


def test_crossed_encoder_cables_each_input_reads_the_other_motor(spec):
    shaft, board, _ = pulsed(spec, ("crossed:0,5",), 5, DUTY)
    assert shaft[5] > MOVES and board[0] == shaft[5] and abs(board[5]) <= STILL, (shaft, board)


def test_a_dead_encoder_reads_nothing_while_its_shaft_turns(spec):
    shaft, board, _ = pulsed(spec, ("encoder-dead:5",), 5, DUTY)
    assert shaft[5] > MOVES and board[5] == 0, (shaft, board)


def test_one_dead_channel_counts_back_and_forth_by_one_while_its_shaft_turns(spec):
    """Channel B open: the decoder sees A's edges alone, each read as a step one way then back (the direction of a
    quadrature edge is the other channel's level): the count never strays more than one from where it was."""
    shaft, board, samples = pulsed(spec, ("channel-dead:5",), 5, DUTY)
    assert shaft[5] > MOVES, shaft
    assert set(np.unique(samples)) <= {-1, 0, 1} and len(np.unique(samples)) == 2, np.unique(samples)
    assert abs(board[5]) <= 1


def test_motors_on_each_others_bridges_each_bridge_turns_the_other_motor(spec):
    shaft, board, _ = pulsed(spec, ("bridges-crossed:0,5",), 0, DUTY)
    assert shaft[5] > MOVES and abs(shaft[0]) <= STILL and board[5] == shaft[5], (shaft, board)


@pytest.mark.parametrize("fault, braked", [("input-open:5,2", 1), ("input-open:5,1", -1)])
def test_an_open_bridge_input_held_high_brakes_the_way_it_drives_and_drives_the_other(spec, fault, braked):
    """IN2 open (pulled up) brakes forward (IN1 high, IN2 high) and leaves reverse; IN1 open the mirror image."""
    blocked, _, _ = pulsed(spec, (fault,), 5, braked * DUTY)
    free, _, _ = pulsed(spec, (fault,), 5, -braked * DUTY)
    assert abs(blocked[5]) <= STILL and -braked * free[5] > MOVES, (blocked, free)
