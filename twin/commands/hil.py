"""`vrscroll hil SCENARIO --serial PORT`: one scenario on the device and on the twin, compared (docs/tuning-hil-calibration.md)."""

from __future__ import annotations

import datetime
import sys
from pathlib import Path

from twin.commands.options import (
    add_device_option,
    add_mount,
    add_rerun,
    add_serial,
    add_tolerance_deg,
    device_session,
    opened,
    within,
)
from twin.errors import UserError
from twin.formats.gains import read_gains
from twin.formats.run import read_run, recorded_status
from twin.formats.scenario import read_scenario
from twin.hil.compare import compare, metrics_text, not_followed
from twin.hil.mirror import DeviceNotReady
from twin.hil.record import Diverged, GainsRestored, run_hil
from twin.link.serial_link import LinkError, NackError
from twin.sim.gate import GateRefused
from viz.hil_report import write_report


def add_arguments(p) -> None:
    p.add_argument("scenario", help="scenario file, TOML or JSON (docs/tuning-hil-calibration.md)")
    add_serial(p, required=True)
    p.add_argument("--out", help="run folder (default hil-<scenario>-<time>); one that holds a run is refused "
                   "unless --overwrite")
    p.add_argument("--overwrite", action="store_true", help="record over the run already in --out (it is lost)")
    p.add_argument("--telemetry-hz", type=within(1, 1000, "Hz", whole=True), default=500, help="telemetry rate (default %(default)s)")
    p.add_argument("--gains", help="gains file (vrscroll tune --out) to push to the device before the run "
                   "(default: the device profile's gains, if it holds any)")
    p.add_argument("--log", help="session log, JSON lines (default <out>/session.jsonl)")
    add_tolerance_deg(p)
    add_rerun(p)
    add_device_option(p)
    add_mount(p)


def run(args) -> int:
    profile, spec = opened(args)
    scenario = read_scenario(args.scenario, spec)
    gains = read_gains(args.gains, spec.n_hinges).hinges if args.gains else \
        profile.gains if profile.gains_from != "spec" else None
    out = Path(args.out or f"hil-{scenario.name}-{datetime.datetime.now():%Y%m%d-%H%M%S}")
    status = recorded_status(out)
    if status and not args.overwrite:  # a run is a measurement that cannot be taken again
        raise UserError(f"{out} holds a run already (run.json, status {status!r}): give another --out, or "
                        "--overwrite to record over it")
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        return _record(args, profile, spec, scenario, gains, out)
    finally:
        if created and not any(out.iterdir()):  # nothing recorded (a port that would not open): no empty folder
            out.rmdir()


def _record(args, profile, spec, scenario, gains, out: Path) -> int:
    log = args.log or str(out / "session.jsonl")
    last = [0.0]

    def progress(t):
        if t - last[0] >= 0.5:
            last[0] = t
            print(f"t={t:6.2f} s of {scenario.duration:.2f} s", flush=True)

    try:
        with device_session(args, spec, log) as (link, spec):
            run_hil(link, spec, scenario, out, telemetry_hz=args.telemetry_hz, scenario_path=args.scenario,
                    on_progress=progress, gains=gains, tolerance_deg=args.tolerance_deg, profile=profile.label,
                    hinges=profile.hinges, mount=profile.mount)
    except GainsRestored as exc:
        print(exc.report.text())
        raise UserError(f"refused by the gate: {exc} (the gains of {args.gains or profile.gains_from} were sent, "
                        "then the device's "
                        "previous gains sent back; no target was sent)") from None
    except GateRefused as exc:
        print(exc.report.text())
        raise UserError(f"scenario refused by the gate: {exc} (nothing was sent)") from None
    except NackError as exc:
        raise UserError(f"{exc}; the hinges already changed got their previous gains back, no target was sent") \
            from None
    except DeviceNotReady as exc:
        raise UserError(str(exc)) from None
    except Diverged as exc:
        raise UserError(f"stopped: {exc} (the run up to there is kept in {out}, marked stopped; `vrscroll view "
                        f"{out}` shows it)") from None
    except LinkError as exc:
        raise UserError(f"link: {exc} (session log: {log}; traces so far in {out})") from None
    except RuntimeError as exc:
        raise UserError(f"{exc} (traces so far in {out})") from None
    run_ = read_run(out, spec)
    rows = compare(spec, run_.device, run_.twin, [t for t, _ in run_.changes])
    report = write_report(spec, out, rows)
    print(metrics_text(rows))
    print(f"report: {report} (each column defined there)")
    warning = not_followed(rows)
    if warning:
        print(f"vrscroll hil: warning: {warning}", file=sys.stderr)
    if args.rerun:
        from viz.rerun_log import log_run

        print(log_run(args.rerun, spec, run_))
    return 0
