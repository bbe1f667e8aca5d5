"""`vrscroll hil`'s run, whole: the run folder (a run already there is a measurement that cannot be taken again),
the scenario recorded on the device and the twin (twin.hil.record.run_hil) with each way it can end as one line,
and the two traces compared per hinge (twin.hil.compare)."""

from __future__ import annotations

import datetime
from pathlib import Path

from twin.errors import UserError
from twin.formats.run import read_run, recorded_status
from twin.formats.scenario import Scenario
from twin.hil.compare import compare
from twin.hil.mirror import DeviceNotReady
from twin.hil.record import Diverged, GainsRestored, run_hil
from twin.link.serial_link import LinkError, NackError
from twin.records.profile import Profile
from twin.sim.gate import GateRefused


def run_folder(scenario: Scenario, out: str | None, overwrite: bool) -> Path:
    """The run folder (default hil-<scenario>-<time>); UserError where it holds a run already, unless overwrite."""
    folder = Path(out or f"hil-{scenario.name}-{datetime.datetime.now():%Y%m%d-%H%M%S}")
    status = recorded_status(folder)
    if status and not overwrite:  # a run is a measurement that cannot be taken again
        raise UserError(f"{folder} holds a run already (run.json, status {status!r}): give another --out, or "
                        "--overwrite to record over it")
    return folder


def record_hil(session, profile: Profile, scenario: Scenario, scenario_path: str, out: Path, gains, gains_from: str,
               log: str, telemetry_hz: int, tolerance_deg: float, say=print) -> tuple:
    """Record the scenario on the device `session` opens (a context manager giving (link, spec)) and on the twin
    into `out` (made; removed again where nothing was recorded), with gains (PidGains per hinge, from
    `gains_from` in words; None: the device's own); (the spec with the device's configuration, the run, compare's
    rows per hinge). say(line): progress
    and the gate's report where it refused. UserError (one line) for each way a run ends early, naming what was
    kept."""
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    last = [0.0]

    def progress(t):
        if t - last[0] >= 0.5:
            last[0] = t
            say(f"t={t:6.2f} s of {scenario.duration:.2f} s")

    try:
        with session as (link, spec):
            run_hil(link, spec, scenario, out, telemetry_hz=telemetry_hz, scenario_path=scenario_path,
                    on_progress=progress, gains=gains, tolerance_deg=tolerance_deg, profile=profile.label,
                    hinges=profile.hinges, mount=profile.mount)
    except GainsRestored as exc:
        say(exc.report.text())
        raise UserError(f"refused by the gate: {exc} (the gains of {gains_from} were sent, then the device's "
                        "previous gains sent back; no target was sent)") from None
    except GateRefused as exc:
        say(exc.report.text())
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
    finally:
        if created and not any(out.iterdir()):  # nothing recorded (a port that would not open): no empty folder
            out.rmdir()
    run = read_run(out, spec)
    return spec, run, compare(spec, run.device, run.twin, [t for t, _ in run.changes])
