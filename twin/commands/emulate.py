"""`vrscroll emulate`: a device emulator on a pseudo-terminal (twin/link/emulator.py, served by
twin/link/pty_device.py); prints the pty's path and runs until SIGINT/SIGTERM."""

from __future__ import annotations

import argparse
import os
import signal

from twin.device.spec import load_spec
from twin.link.emulator import Emulator, EmulatorOptions
from twin.link.faults import FaultOptions
from twin.link.plant import IDEAL, PlantOptions
from twin.link.pty_device import open_pty, serve


def add_arguments(p: argparse.ArgumentParser) -> None:
    pl, f = PlantOptions(), FaultOptions()
    p.add_argument("--log", help="JSON-lines log of every command received (appended)")
    p.add_argument("--port-file", help="also write the pty path to this file")
    p.add_argument("--friction-scale", type=float, default=pl.friction_scale,
                   help="gear friction x (default %(default)s)")
    p.add_argument("--damping-scale", type=float, default=pl.damping_scale, help="gear damping x (default %(default)s)")
    p.add_argument("--speed-scale", type=float, default=pl.speed_scale,
                   help="no-load speed x, i.e. motor constant / x (default %(default)s)")
    p.add_argument("--armature-scale", type=float, default=pl.armature_scale,
                   help="rotor inertia (armature) x (default %(default)s)")
    p.add_argument("--backlash-deg", type=float, default=pl.backlash_deg, help="backlash, deg (default %(default)s)")
    p.add_argument("--encoder-noise", type=float, default=pl.encoder_noise,
                   help="probability per read of a count off by one (default %(default)s)")
    p.add_argument("--latency-ms", type=float, default=f.latency_ms, help="command latency, ms (default %(default)s)")
    p.add_argument("--watchdog-ms", type=int, help="watchdog timeout, ms (default: the spec's, 0: off)")
    p.add_argument("--jam-hinge", type=int, help="this hinge jams ...")
    p.add_argument("--jam-after", type=float, default=0.0, help="... this many s after the first target (default 0)")
    p.add_argument("--drop-after", type=float, help="the link goes dead after this many s of device time")
    p.add_argument("--corrupt", type=float, default=0.0,
                   help="probability per frame sent of a flipped byte and of inserted garbage (default 0)")
    p.add_argument("--seed", type=int, default=0, help="random seed for noise and corruption")
    p.add_argument("--ideal", action="store_true",
                   help="plant identical to the twin: no perturbation, backlash, noise or latency")


def options_from_args(args, n_hinges: int) -> EmulatorOptions:
    """The emulator's options from the command line; ValueError naming the option that is wrong."""
    if args.jam_hinge is not None and not 0 <= args.jam_hinge < n_hinges:
        raise ValueError(f"--jam-hinge {args.jam_hinge}: no such hinge")
    plant = IDEAL if args.ideal else PlantOptions(
        friction_scale=args.friction_scale, damping_scale=args.damping_scale, speed_scale=args.speed_scale,
        armature_scale=args.armature_scale, backlash_deg=args.backlash_deg, encoder_noise=args.encoder_noise)
    faults = FaultOptions(latency_ms=0.0 if args.ideal else args.latency_ms, jam_hinge=args.jam_hinge,
                          jam_after=args.jam_after, drop_after=args.drop_after, corrupt=args.corrupt)
    return EmulatorOptions(plant=plant, faults=faults, watchdog_ms=args.watchdog_ms, seed=args.seed)


def run(args) -> int:
    """Open a pty, print its path, emulate the device until SIGINT/SIGTERM."""
    spec = load_spec()
    opt = options_from_args(args, spec.n_hinges)
    master, slave, path = open_pty()
    emu = Emulator(spec, opt, log_path=args.log)
    stop = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.append(True))
    if args.port_file:
        with open(args.port_file + ".part", "w") as f:
            f.write(path + "\n")
        os.replace(args.port_file + ".part", args.port_file)
    print(path, flush=True)
    try:
        overruns = serve(emu, master, lambda: bool(stop))
        emu.close(overruns=overruns)
    finally:
        os.close(master)
        os.close(slave)
    return 0
