"""Open-loop duty programs: what the firmware core runs on one hinge for identification (and PULSE, a program
of one segment), and what a run of one gives back, on the device (twin.link.serial_link.Link.run_program) and
on the twin (twin.sim.twin.Twin.run_program, twin.sim.batch.TwinBatch.run_program) alike.

A program is a few segments, each a signed duty held for a duration (or COAST), on one hinge, the other hinges
braked;
the core bounds it whatever the host sends (docs/protocol.md, "PROGRAM"; docs/firmware.md, "Open-loop motion")
and ends it itself: at the end of its segments, at its angle window's edge, on a stall, on its timeout, when
the host goes quiet, on any change of state.
"""

from __future__ import annotations

import enum
from typing import NamedTuple

import numpy as np

COAST = "coast"  # a segment's duty that coasts: the hinge's windings open (no current, no back-EMF braking) for it


class ProgramEnd(enum.IntEnum):
    """Why a program ended (the core's VRS_PROGRAM_END_*; PROGRAM_STATUS's `end`)."""

    NONE = 0  # no program since the device started
    RUNNING = 1  # still running
    DONE = 2  # its segments ran out
    WINDOW = 3  # the hinge was about to leave its window [low, high]
    STALL = 4  # |duty| above the stall duty and the counts did not move for the stall time
    TIMEOUT = 5  # its timeout came before the segments' end
    HOST_QUIET = 6  # no frame from the host for the watchdog's period
    STATE = 7  # the device left IDLE (targets, ESTOP, a fault)


class ProgramRun(NamedTuple):
    """One program's run on one hinge, a sample per firmware tick from its first tick (time 0) to its last.

    time_s: s from the program's start (tick index / loop rate); duty: the applied signed duty per sample
    (after the core's I2t derating, -1..1, 1 = the drive cap's voltage); counts: the hinge's encoder counts
    per sample (int64); battery_mV: the pack voltage the device read at the end (None: not sensed); end:
    ProgramEnd's name in lower case ("done", "window", "stall", "timeout", "host_quiet", "state");
    samples_lost: ticks whose sample never reached the host (their times are missing from time_s); coasting:
    per sample, whether the hinge coasted from it (its duty 0, its windings open; None: an empty run's).
    """

    hinge: int
    time_s: np.ndarray
    duty: np.ndarray
    counts: np.ndarray
    battery_mV: float | None
    end: str
    samples_lost: int = 0
    coasting: np.ndarray | None = None


def end_name(code: int) -> str:
    """The end reason's name in lower case ("window"), or the number for one this host does not know."""
    return ProgramEnd(code).name.lower() if code in ProgramEnd._value2member_map_ else str(code)
