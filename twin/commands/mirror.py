"""`vrscroll mirror TARGET.json --serial PORT`: gate a target on the twin, send it, watch the device follow."""

from __future__ import annotations

import math

import numpy as np

from twin.checks import cell, hinge_angles
from twin.commands.options import (
    add_device_option,
    add_mount,
    add_rerun,
    add_serial,
    add_tolerance_deg,
    device_session,
    link_errors,
    opened,
    within,
)
from twin.errors import UserError
from twin.formats.target import read_target
from twin.hil.mirror import DeviceNotReady, mirror
from twin.sim.gate import GateRefused


def add_arguments(p) -> None:
    p.add_argument("target", nargs="?", help='JSON file with {"angles_deg": [one per hinge]}')
    p.add_argument("--angles", help="hinge targets in degrees, comma-separated, instead of TARGET.json "
                   "(write --angles=-30,0,... when the first is negative)")
    add_serial(p, required=True)
    add_tolerance_deg(p)
    p.add_argument("--settle-limit-s", type=within(0.1, 60, "s"), default=2.0, help="s the move may take (default %(default)s)")
    p.add_argument("--telemetry-hz", type=within(1, 1000, "Hz", whole=True), default=500, help="telemetry rate (default %(default)s)")
    p.add_argument("--log", default="vrscroll-session.jsonl", help="session log, JSON lines (default %(default)s)")
    add_rerun(p)
    p.add_argument("--override", action="store_true",
                   help="send even when the gate fails a check (logged); the device's own limits still apply")
    add_device_option(p)
    add_mount(p)


HALF_TURN = math.pi  # rad: no hinge target given with --angles may be further from flat than this


def read_targets(args, spec) -> np.ndarray:
    """Targets in rad from --angles or the target JSON; UserError for anything malformed.

    A target file is read by twin.formats.target (angles within the hinge range). --angles must
    be finite numbers within half a turn: whether they are within the hinge range is the gate's
    check, which --override may override (the device's own limit still holds)."""
    if (args.target is None) == (args.angles is None):
        raise UserError("give either TARGET.json or --angles")
    n = spec.n_hinges
    if args.angles is None:
        return read_target(args.target, spec)
    try:
        given = [cell(v, f"--angles[{i}]") for i, v in enumerate(args.angles.split(","))]
        return hinge_angles(given, n, HALF_TURN, "--angles", "half a turn")
    except ValueError as exc:
        raise UserError(f"{exc} (expected {n} numbers in degrees, comma-separated)") from None


def run(args) -> int:
    profile, spec = opened(args)
    targets = read_targets(args, spec)
    last = [0.0]

    def show(t, device, predicted):
        if t - last[0] >= 0.1:
            last[0] = t
            dev = np.abs(device - predicted)
            print(f"t={t:6.3f} s  device " + " ".join(f"{a:7.1f}" for a in device)
                  + f"  deg   largest deviation {dev.max():4.1f} deg (hinge {int(dev.argmax())})", flush=True)

    try:
        with link_errors(f" (session log: {args.log})"), device_session(args, spec) as (link, spec):
            if args.override:
                print("gate override requested: a failed check will be logged and the move sent anyway")
            result = mirror(link, spec, targets, tolerance_deg=args.tolerance_deg, settle_limit=args.settle_limit_s,
                            override=args.override, telemetry_hz=args.telemetry_hz, on_frame=show,
                            hinges=profile.hinges, mount=profile.mount)
    except GateRefused as exc:
        print(exc.report.text())
        raise UserError(f"{exc} (nothing was sent; --override to send anyway)") from None
    except DeviceNotReady as exc:
        raise UserError(str(exc)) from None
    print(result.report.text())
    print(("mirror: " if result.ok else "mirror: STOPPED: ") + result.message)
    print("final   " + " ".join(f"{a:7.1f}" for a in result.final_deg) + "  deg")
    if args.rerun:
        from viz.rerun_log import RerunRecording, add_move

        with RerunRecording(args.rerun, spec) as rec:
            add_move(rec, 0.0, result.telemetry, result.report.prediction)
        print(f"rerun recording {args.rerun} (device and twin, {result.elapsed:.2f} s)")
    return 0 if result.ok else 3
