"""`vrscroll bringup --serial PORT`: bring a new board up, step by step, with the device on the bench.

Firmware and configuration read back (a set-up fault named); for each hinge a short low-duty pulse of its
motor each way (twin.hil.bringup), the encoder that answers, its direction and counts per pulse; wiring
mistakes named (motor leads or encoder A/B swapped, encoder cables crossed, motors on each other's bridges, a
dead encoder) and the correction
stored on the device (kept across power cycles, reported in HELLO) and in the device profile; the flat pose
confirmed as zero; then a first gated move of every hinge and back."""

from __future__ import annotations

from twin.commands.options import (
    add_device_option,
    add_serial,
    add_tolerance_deg,
)
from twin.errors import UserError
from twin.formats.profile import chosen_profile, profile_line, write_profile_wiring
from twin.hil.bringup import bring_up, first_move, hand_by_prompt
from twin.hil.device_gains import device_session
from twin.link.serial_link import LinkError
from twin.sim.gate import GateRefused


def add_arguments(p) -> None:
    add_serial(p, required=True)
    p.add_argument("--hand", action="store_true",
                   help="ask you to bend each flap by hand, so that a reversed encoder is told from a reversed "
                        "motor and crossed encoder cables from motors on each other's bridges (without it, lying "
                        "flat, the way that lifts the flap tells the first; the second is named, nothing stored)")
    p.add_argument("--no-move", action="store_true", help="stop after the zero: no first gated move")
    add_tolerance_deg(p)
    p.add_argument("--log", help="session log, JSON lines")
    add_device_option(p)


def run(args) -> int:
    profile = chosen_profile(args.device)
    spec = profile.spec
    print(profile_line(profile))
    try:
        with device_session(args.serial, spec, args.log) as (link, spec):
            checks = bring_up(link, spec, hand_by_prompt(link) if args.hand else None)
            wiring = link.get_wiring()
            found = [c.note for c in checks if c.note]
            print("wiring   " + ("as built: nothing to correct" if not found else
                                 f"corrected on the device: encoder inputs {list(wiring.encoder)}, "
                                 f"flags {list(wiring.flags)}, bridges {list(wiring.bridge)}"))
            kept = "kept on the device (its flash, across power cycles, HELLO's wiring_set)"
            if profile.folder:
                print(f"         {kept} and in {write_profile_wiring(profile.name, wiring, found)}")
            else:
                print(f"         {kept} only: no device profile is selected, so no copy here (`--device NAME` "
                      "keeps one in the profile's wiring.json)")
            if args.hand:
                input("lay every flap flat for the zero; press Enter ")
            link.confirm_zero()
            print("zero     confirmed: the pose now is 0 deg on every hinge" +
                  ("" if args.hand else " (the device must lie flat now: `vrscroll zero` again if it did not)"))
            if args.no_move:
                return 0
            first_move(link, spec, args.tolerance_deg)
    except GateRefused as exc:
        raise UserError(str(exc)) from None
    except LinkError as exc:
        raise UserError(str(exc)) from None
    print("bring-up done: the device takes targets")
    return 0
