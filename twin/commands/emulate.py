"""`vrscroll emulate`: a device emulator on a pseudo-terminal (twin/link/emulator.py, served by
twin/link/pty_device.py); prints the pty's path and runs until SIGINT/SIGTERM."""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import signal

from twin.device.mount import DEFAULT_MOUNT, MOUNTS
from twin.device.spec import DeviceSpec, load_spec
from twin.link.emulator import Emulator, EmulatorOptions, drawn_options
from twin.link.faults import FaultOptions, Miswiring
from twin.link.pty_device import open_pty, serve
from twin.paths import replacing
from twin.sim.plant import PlantRanges, as_twin

RANGED = {  # PlantRanges field (its option is --field-name) -> what it is
    "speed_scale": "no-load speed x, i.e. motor constant / x",
    "friction_scale": "gear Coulomb and static friction x",
    "damping_scale": "gear viscous damping x",
    "armature_scale": "rotor inertia (armature) x",
    "backlash_deg": "backlash between gearbox output and flap, deg",
    "latency_ms": "command latency, ms",
    "hinge_scale": "each hinge's own x on speed, friction, damping and armature, about the above",
    "cogging_pct": "each motor's cogging, %% of its stall torque (its phase against the encoder drawn too)",
    "ripple_pct": "each gearbox's friction ripple with its final gear's mesh, %% of its Coulomb friction",
    "winding_c": "each winding's temperature at power-on, deg C (it warms as it works)",
    "backdrive_scale": "the gearboxes' back-driven efficiency x (a load turning the motor; at most 1 in all)",
}


def _flag(field: str) -> str:
    return "--" + field.replace("_", "-")


def add_arguments(p: argparse.ArgumentParser) -> None:
    ranges = PlantRanges()
    p.add_argument("--log", help="JSON-lines log of every command received, and of the plant drawn (appended)")
    p.add_argument("--serial-file", help="also write the pty path (the device's --serial) to this file")
    for field, what in RANGED.items():
        lo, hi = getattr(ranges, field)
        p.add_argument(_flag(field), metavar="X or LOW,HIGH",
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


def _range(flag: str, text: str | None, default: tuple[float, float]) -> tuple[float, float]:
    """A fixed value "X" or a range "LOW,HIGH"; ValueError naming the option."""
    if text is None:
        return default
    try:
        parts = [float(x) for x in text.split(",")]
    except ValueError:
        raise ValueError(f"{flag} {text}: expected a number or LOW,HIGH") from None
    if len(parts) not in (1, 2):
        raise ValueError(f"{flag} {text}: expected a number or LOW,HIGH")
    return (parts[0], parts[-1])


MAX_PACK_V = 20.0  # V: beyond any pack the DRV8833 (10.8 V max) could be run from


def options_from_args(args, spec: DeviceSpec) -> EmulatorOptions:
    """The emulator's options from the command line; ValueError naming the option that is wrong."""
    if args.jam_hinge is not None and not 0 <= args.jam_hinge < spec.n_hinges:
        raise ValueError(f"--jam-hinge {args.jam_hinge}: no such hinge")
    if not 0.0 <= args.encoder_miss <= 1.0:
        raise ValueError(f"--encoder-miss {args.encoder_miss}: a probability, 0 to 1")
    if not 0.0 <= args.corrupt <= 1.0:
        raise ValueError(f"--corrupt {args.corrupt}: a probability, 0 to 1")
    if args.pack_voltage_v is not None and not 0 < args.pack_voltage_v <= MAX_PACK_V:
        raise ValueError(f"--pack-voltage-v {args.pack_voltage_v}: a pack's voltage, above 0 and at most {MAX_PACK_V} V")
    if args.watchdog_ms is not None and not 0 <= args.watchdog_ms <= 65535:
        raise ValueError(f"--watchdog-ms {args.watchdog_ms}: 0 (off) to 65535 ms, what the firmware's config holds")
    for flag, value in (("--jam-after-s", args.jam_after_s), ("--drop-after-s", args.drop_after_s)):
        if value is not None and not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{flag} {value}: a time in s, finite and not negative")
    if args.host_away_hold_ms is not None and not 0 <= args.host_away_hold_ms <= 65535:
        raise ValueError(f"--host-away-hold-ms {args.host_away_hold_ms}: 0 to 65535 ms, what the firmware's config holds")
    for flag, value in (("--watchdog-ms", args.watchdog_ms), ("--host-away-hold-ms", args.host_away_hold_ms)):
        if args.sketch and value is not None:
            raise ValueError(f"{flag}: the sketch's is the spec's, compiled into its header; "
                             "it applies to the C core alone (without --sketch)")
    if args.seed < 0:
        raise ValueError(f"--seed {args.seed}: not negative")
    default = PlantRanges()
    if args.ideal:
        twin = as_twin(spec)
        default = PlantRanges(speed_scale=(1, 1), friction_scale=(1, 1), damping_scale=(1, 1),
                              armature_scale=(1, 1), backlash_deg=(twin.backlash_deg,) * 2, latency_ms=(0, 0),
                              backdrive_scale=(1, 1))
    given = {field: _range(_flag(field), getattr(args, field), getattr(default, field)) for field in RANGED}
    try:
        ranges = PlantRanges(**given)
    except ValueError as exc:
        field, reason = str(exc).split(": ", 1)
        raise ValueError(f"{_flag(field)}: {reason}") from None
    faults = FaultOptions(jam_hinge=args.jam_hinge, jam_after=args.jam_after_s, drop_after=args.drop_after_s,
                          corrupt=args.corrupt, wiring=tuple(args.wiring_fault))
    Miswiring.parse(faults.wiring, spec.n_hinges)  # refused here, naming the fault
    opt = drawn_options(ranges, faults, args.seed, args.watchdog_ms, args.encoder_miss, args.pack_voltage_v,
                        args.sketch, args.zeroed, spec.n_hinges)
    return dataclasses.replace(opt, host_away_hold_ms=args.host_away_hold_ms,
                               plant=dataclasses.replace(opt.plant, mount=args.mount,
                                                         hinges=() if args.ideal else opt.plant.hinges,
                                                         warming=not args.no_warming))


def run(args) -> int:
    """Open a pty, print its path, emulate the device until SIGINT/SIGTERM."""
    spec = load_spec()
    opt = options_from_args(args, spec)
    master, slave, path = open_pty()
    emu = Emulator(spec, opt, log_path=args.log)
    stop = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.append(True))
    if args.serial_file:
        with replacing(args.serial_file) as tmp, open(tmp, "w") as f:
            f.write(path + "\n")
    print(path, flush=True)
    try:
        overruns = serve(emu, master, lambda: bool(stop))
        emu.close(overruns=overruns)
    finally:
        os.close(master)
        os.close(slave)
    return 0
