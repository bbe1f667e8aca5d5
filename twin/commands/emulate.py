"""`vrscroll emulate`: a device emulator on a pseudo-terminal (twin/link/emulator.py, served by
twin/link/pty_device.py); prints the pty's path and runs until SIGINT/SIGTERM (twin.link.emulator_run)."""

from __future__ import annotations

import argparse

from twin.device.mount import DEFAULT_MOUNT, MOUNTS
from twin.device.spec import load_spec
from twin.link.emulator_run import RANGED, emulate_on_pty, option_flag, options_from_args
from twin.sim.plant import PlantRanges


def add_arguments(p: argparse.ArgumentParser) -> None:
    ranges = PlantRanges()
    p.add_argument("--log", help="JSON-lines log of every command received, and of the plant drawn (appended)")
    p.add_argument("--serial-file", help="also write the pty path (the device's --serial) to this file")
    for field, what in RANGED.items():
        lo, hi = getattr(ranges, field)
        p.add_argument(option_flag(field), metavar="X or LOW,HIGH",
                       help=f"{what}: fixed, or drawn uniformly from the seed (default {lo:g},{hi:g})")
    p.add_argument("--encoder-miss", type=float, default=0.0,
                   help="probability that the encoder's counter misses an edge; missed edges accumulate (default 0)")
    p.add_argument("--pack-voltage-v", type=float,
                   help="the 2S pack's open-circuit voltage, V (default: the spec's supply_voltage)")
    p.add_argument("--watchdog-ms", type=int, help="watchdog timeout, ms (default: the spec's, 0: off)")
    p.add_argument("--host-away-hold-ms", type=int,
                   help="how long the targets are held after the watchdog fires, before the release, ms "
                        "(default: the spec's host_away_hold)")
    p.add_argument("--jam-hinge", type=int, help="this hinge jams ...")
    p.add_argument("--jam-after-s", type=float, default=0.0, help="... this many s after the first target (default 0)")
    p.add_argument("--drop-after-s", type=float, help="the link goes dead after this many s of device time")
    p.add_argument("--wiring-fault", action="append", default=[], metavar="FAULT:HINGE[,HINGE]",
                   help="a wiring mistake between the board and its motors (repeatable): motor-reversed:K, "
                        "encoder-reversed:K, encoder-dead:K, channel-dead:K (its B channel open), crossed:J,K (the "
                        "encoder cables of J and K swapped), bridges-crossed:J,K (their motors on each other's bridges), "
                        "input-open:K,N (bridge K's IN1 or IN2 open, pulled up)")
    p.add_argument("--corrupt", type=float, default=0.0,
                   help="probability per frame sent of a flipped byte and of inserted garbage (default 0)")
    p.add_argument("--seed", type=int, default=0, help="random seed: the plant drawn, missed edges, corruption")
    p.add_argument("--sketch", action="store_true",
                   help="run the whole ESP32-S3 sketch on stand-ins for its peripherals (encoders decoded from "
                        "quadrature edges, MCPWM through the H-bridges, USB CDC buffers), not the C core alone "
                        "(docs/firmware.md, 'The sketch in the loop'); needs a C++ compiler")
    held = p.add_mutually_exclusive_group()
    held.add_argument("--mount", choices=MOUNTS, default=DEFAULT_MOUNT,
                      help="how the device is held, its plant the twin's model of that mount (docs/device.md "
                           "\"Mounts\"): hanging from its root flap (the flaps beside the root sag under gravity "
                           "while nothing drives them), flat on a table (its flaps cannot fold below it), or on a "
                           "stand on its edge (gravity loads no hinge) (default %(default)s)")
    held.add_argument("--lying-flat", dest="mount", action="store_const", const="flat",
                      help="the same as --mount flat (bring-up's zero and the identification are done lying flat)")
    p.add_argument("--zeroed", action="store_true",
                   help="start with the zero confirmed, as if `vrscroll zero` had run at power-on while the flaps lay "
                        "flat (by default, as a real device, it refuses to move until confirmed)")
    p.add_argument("--no-warming", action="store_true",
                   help="every winding at the spec's resistance (25 deg C) throughout, as the twin's, instead of "
                        "starting at --winding-c and warming as it works (--winding-c is then not used)")
    p.add_argument("--ideal", action="store_true",
                   help="the twin's own plant: nothing drawn, no latency (the other options still apply)")


def run(args) -> int:
    """Open a pty, print its path, emulate the device until SIGINT/SIGTERM."""
    spec = load_spec()
    emulate_on_pty(spec, options_from_args(args, spec), args.log, args.serial_file,
                   lambda line: print(line, flush=True))
    return 0
