"""`vrscroll mirror TARGET.json --serial PORT`: gate a target on the twin, send it, watch the device follow
(twin.hil.mirror_run)."""

from __future__ import annotations

from twin.commands.options import add_device_option, add_mount, add_rerun, add_serial, add_tolerance_deg, opened, within
from twin.hil.device_gains import device_session
from twin.hil.mirror_run import mirror_on_device, mirror_targets


def add_arguments(p) -> None:
    p.add_argument("target", nargs="?", help='JSON file with {"angles_deg": [one per hinge]}')
    p.add_argument("--angles", help="hinge targets in degrees, comma-separated, instead of TARGET.json")
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


def run(args) -> int:
    profile, spec = opened(args)
    targets = mirror_targets(spec, args.target, args.angles)
    spec, result, lines = mirror_on_device(device_session(args.serial, spec, args.log), profile, targets,
                                           args.tolerance_deg, args.settle_limit_s, args.override, args.telemetry_hz,
                                           args.log, lambda line: print(line, flush=True))
    print("\n".join(lines))
    if args.rerun:
        from viz.rerun_log import RerunRecording, add_move

        with RerunRecording(args.rerun, spec) as rec:
            add_move(rec, 0.0, result.telemetry, result.report.prediction)
        print(f"rerun recording {args.rerun} (device and twin, {result.elapsed:.2f} s)")
    return 0 if result.ok else 3
