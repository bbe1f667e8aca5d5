"""`vrscroll zero --serial PORT`: confirm the device's flat pose as its zero, after every start of the device.

Its encoders count from wherever the motors stood when it started (a power-on, a brown-out, a reset):
until a person confirms that the flaps lie flat, the device refuses every target (NACK ZERO_UNCONFIRMED)
and the host's commands refuse to move it. This command shows where the flaps are by the old zero,
then makes the present counts zero."""

from __future__ import annotations

import numpy as np

from controllers.encoder import angle_from_counts
from twin.commands.options import add_device_option, add_serial, opened
from twin.errors import UserError
from twin.formats.profile import profile_line
from twin.hil.device_gains import device_session, link_errors
from twin.link import protocol as P


def add_arguments(p) -> None:
    add_serial(p, required=True)
    p.add_argument("--log", help="session log, JSON lines")
    add_device_option(p)


def run(args) -> int:
    profile, spec = opened(args, say=False)  # said after the device answers, above what it said
    with link_errors(), device_session(args.serial, spec, args.log) as (link, spec):
        before = link.get_state()
        if before.state == P.State.FAULT and before.faults == P.Fault.WATCHDOG:
            link.clear_fault()  # the last session's hold ran out: nothing went wrong
            before = link.get_state()
        if before.state in (P.State.ACTIVE, P.State.HOLDING):
            raise UserError(
                f"the device is {P.enum_name(P.State, before.state)}: it holds the last session's targets (a "
                f"`mirror`, bring-up's first move) for {spec.host_away_hold:g} s after that session's last "
                f"frame; the zero is confirmed in IDLE only. Run `vrscroll zero --serial {args.serial}` again "
                f"after that (it clears the hold's end itself), or let go now with `vrscroll status --serial "
                f"{args.serial} --estop --clear-fault` (the flaps then rest where they are)")
        if before.state != P.State.IDLE:
            raise UserError(f"the device is {P.enum_name(P.State, before.state)} ("
                            f"{P.enum_name(P.Fault, before.faults) if before.faults else 'no fault'}): the zero "
                            f"is confirmed in IDLE only (`vrscroll status --serial {args.serial} --clear-fault` "
                            "once the cause is gone)")
        link.confirm_zero()
        after = link.get_state()
    print(profile_line(profile))
    was = np.degrees(angle_from_counts(spec, before.counts))
    print(f"started  {P.enum_name(P.ResetReason, link.info.reset_reason)}")
    print("was      " + " ".join(f"{a:7.1f}" for a in was) + "  deg by the zero before")
    print("counts   " + " ".join(f"{c:7d}" for c in after.counts))
    print("zero confirmed: the flat pose is 0 deg on every hinge; the device takes targets now")
    return 0
