"""`vrscroll status --serial PORT`: the device's firmware version, state, faults and hinge angles (twin.hil.device_status)."""

from __future__ import annotations

from twin.commands.options import add_device_option, add_serial, comma_list, opened, within
from twin.formats.profile import profile_line
from twin.hil.device_gains import device_session, link_errors
from twin.hil.device_status import device_status, watch


def add_arguments(p) -> None:
    add_serial(p, required=True)
    p.add_argument("--clear-fault", action="store_true", help="clear an ESTOP or FAULT first")
    p.add_argument("--estop", action="store_true", help="e-stop the device first")
    p.add_argument("--disable-hinges", type=comma_list(), metavar="K1,K2,...",
                   help="disable these hinges on the device (kept with its wiring, across power cycles and "
                        "CLEAR_FAULT): braked, never driven, their targets and pulses refused; the device IDLE "
                        "(with --clear-fault from a fault)")
    p.add_argument("--enable-hinges", type=comma_list(), metavar="K1,K2,...",
                   help="enable these hinges again (once the dead wire is mended; bring-up does it for a hinge it "
                        "finds healthy)")
    p.add_argument("--log", help="session log, JSON lines")
    p.add_argument("--watch", type=within(0, 86400, "s"), nargs="?", const=0.0, metavar="SECONDS",
                   help="then a live readout of the hinge angles, 5 lines a second, for SECONDS (none or 0: until "
                        "Ctrl-C): for the bring-up steps where you bend a flap by hand")
    add_device_option(p)


def run(args) -> int:
    profile, spec = opened(args, say=False)  # said with what the device says
    with link_errors(), device_session(args.serial, spec, args.log) as (link, spec):
        lines = device_status(link, spec, profile, args.estop, args.clear_fault, args.disable_hinges,
                              args.enable_hinges)
        print("\n".join([profile_line(profile), *lines]), flush=True)
        if args.watch is not None:
            watch(link, spec, args.watch, lambda line: print(line, flush=True))
    return 0
