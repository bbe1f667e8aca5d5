"""The emulator as `vrscroll emulate` runs it: its options from the command line's values (each range of the
plant it draws, its faults, its mount), and the emulator served on a pseudo-terminal until a stop signal
(twin/link/emulator.py, served by twin/link/pty_device.py)."""

from __future__ import annotations

import dataclasses
import math
import os
import signal

from twin.device.spec import DeviceSpec
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


def option_flag(field: str) -> str:
    """The option of a RANGED field (--field-name)."""
    return "--" + field.replace("_", "-")


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
    """The emulator's options from the command line's values (args: `vrscroll emulate`'s parsed options);
    ValueError naming the option that is wrong."""
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
    given = {field: _range(option_flag(field), getattr(args, field), getattr(default, field)) for field in RANGED}
    try:
        ranges = PlantRanges(**given)
    except ValueError as exc:
        field, reason = str(exc).split(": ", 1)
        raise ValueError(f"{option_flag(field)}: {reason}") from None
    faults = FaultOptions(jam_hinge=args.jam_hinge, jam_after=args.jam_after_s, drop_after=args.drop_after_s,
                          corrupt=args.corrupt, wiring=tuple(args.wiring_fault))
    Miswiring.parse(faults.wiring, spec.n_hinges)  # refused here, naming the fault
    opt = drawn_options(ranges, faults, args.seed, args.watchdog_ms, args.encoder_miss, args.pack_voltage_v,
                        args.sketch, args.zeroed, spec.n_hinges)
    return dataclasses.replace(opt, host_away_hold_ms=args.host_away_hold_ms,
                               plant=dataclasses.replace(opt.plant, mount=args.mount,
                                                         hinges=() if args.ideal else opt.plant.hinges,
                                                         warming=not args.no_warming))


def emulate_on_pty(spec: DeviceSpec, opt: EmulatorOptions, log: str | None = None, serial_file: str | None = None,
                   say=print) -> None:
    """Open a pty, say its path (and write it to serial_file), emulate the device on it until SIGINT/SIGTERM."""
    master, slave, path = open_pty()
    emu = Emulator(spec, opt, log_path=log)
    stop = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.append(True))
    if serial_file:
        with replacing(serial_file) as tmp, open(tmp, "w") as f:
            f.write(path + "\n")
    say(path)
    try:
        overruns = serve(emu, master, lambda: bool(stop))
        emu.close(overruns=overruns)
    finally:
        os.close(master)
        os.close(slave)
