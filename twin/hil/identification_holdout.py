"""The held-out run of `calibrate --serial`: after the identification experiments, a short closed-loop scenario
that no fit sees (twin.hil.calibration_scenario's, one cycle, lying flat, gated), recorded on the device as `hil`
records its runs; after the fits, per hinge the RMSE of the twin against it with the prior values and with the
identified ones, the floor the encoder and the link set, and what neither explains (deg;
docs/tuning-hil-calibration.md, "Identification": the held-out run).

The run also brings the flaps down from where the experiments left them (up to 84 deg): its move to the start is
to flat, gated with the gains the device holds.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from twin.device.spec import DeviceSpec
from twin.formats.run import read_run
from twin.hil.calibration import compared_lines, compared_rows, floor_deg, trace_rmse
from twin.hil.calibration_scenario import calibration_scenario
from twin.hil.device_gains import device_gains
from twin.hil.record import Diverged, run_hil
from twin.link.serial_link import LinkError
from twin.records.profile import Profile
from twin.sim.gate import GateRefused

HOLDOUT_FOLDER = "identification-holdout"  # the held-out run's folder in the device profile's (a `hil` run)
SEED = 36  # the held-out scenario's draw (any one: no fit sees it)
CYCLES = 1  # of calibration_scenario's: a move out and a ramp about it, 3.7 s of scenario on the device
KEYS = ("rmse_prior_deg", "rmse_identified_deg")  # the report's per-hinge RMSE with the prior and identified values
TOLERANCE_DEG = 30.0  # the run is e-stopped where the device parts from the prior twin by more (hil's tolerance)


def record_holdout(link, spec: DeviceSpec, out: Path, profile: str) -> tuple[object | None, str]:
    """Record the held-out run into folder `out` with the gains the device holds, lying flat: (the Run, "") or,
    where it could not be recorded (the gate refused it, the device parted from the prior twin by more than
    TOLERANCE_DEG), (None, why in words): the identification stands without it."""
    gains = device_gains(link, spec.n_hinges)
    try:
        scenario = calibration_scenario(spec, gains, seed=SEED, cycles=CYCLES, name="identification held-out",
                                        mount="flat")
        run_hil(link, spec, scenario, out, tolerance_deg=TOLERANCE_DEG, profile=profile, mount="flat")
    except (GateRefused, ValueError) as exc:
        return None, f"the gate refused it: {exc}"
    except Diverged as exc:
        return None, f"the device parted from the twin: {exc}"
    except (LinkError, RuntimeError) as exc:
        return None, str(exc)
    return read_run(out, spec), ""


def holdout_report(run, prior: Profile, fitted: Profile, spec: DeviceSpec) -> dict:
    """The held-out run against the twin with the prior profile's values and the identified one's (each hinge's
    own where it has them): per hinge {"hinge", "rmse_prior_deg", "rmse_identified_deg", "floor_deg",
    "unexplained_deg"}, and over every hinge "overall_before_deg" / "overall_after_deg" (RMS) and "floor_deg"."""
    before = trace_rmse(run, prior.spec, spec, prior.hinges)
    after = trace_rmse(run, fitted.spec, spec, fitted.hinges)
    floor = floor_deg(run, spec)
    rms = (lambda x: round(float(np.sqrt(np.mean(np.asarray(x) ** 2))), 4))
    return {"hinges": compared_rows(before, after, floor, KEYS),
            "overall_before_deg": rms(before), "overall_after_deg": rms(after), "floor_deg": rms(floor)}


def holdout_lines(doc: dict) -> list[str]:
    """The held-out report (holdout_report's, or {"not_recorded": why}) in words."""
    if "not_recorded" in doc:
        return [f"held-out run: not recorded ({doc['not_recorded']}); the identification stands without it"]
    lines = [f"held-out run ({doc['run']}), deg: RMSE with the prior -> with the identified values; floor; "
             f"unexplained (overall {doc['overall_before_deg']:.3f} -> {doc['overall_after_deg']:.3f}, "
             f"floor {doc['floor_deg']:.3f})"]
    return lines + compared_lines(doc["hinges"], KEYS)
