"""`vrscroll mirror`'s move, whole: the targets from a target file or the command line's degrees, the move gated,
sent and watched on the device (twin.hil.mirror.mirror) with each way it can be refused as one line, and the
outcome in words."""

from __future__ import annotations

import math

import numpy as np

from twin.checks import cell, hinge_angles
from twin.errors import UserError
from twin.formats.target import read_target
from twin.hil.mirror import DeviceNotReady, mirror
from twin.link.serial_link import LinkError
from twin.records.profile import Profile
from twin.sim.gate import GateRefused

HALF_TURN = math.pi  # rad: no hinge target given with --angles may be further from flat than this
SHOWN_EVERY_S = 0.1  # s between the progress lines of the device following


def mirror_targets(spec, target: str | None, angles: str | None) -> np.ndarray:
    """Targets in rad from a target file or `angles` (deg, comma-separated); UserError for anything malformed.

    A target file is read by twin.formats.target (angles within the hinge range). The angles must be finite
    numbers within half a turn: whether they are within the hinge range is the gate's check, which --override
    may override (the device's own limit still holds)."""
    if (target is None) == (angles is None):
        raise UserError("give either TARGET.json or --angles")
    n = spec.n_hinges
    if angles is None:
        return read_target(target, spec)
    try:
        given = [cell(v, f"--angles[{i}]") for i, v in enumerate(angles.split(","))]
        return hinge_angles(given, n, HALF_TURN, "--angles", "half a turn")
    except ValueError as exc:
        raise UserError(f"{exc} (expected {n} numbers in degrees, comma-separated)") from None


def mirror_on_device(session, profile: Profile, targets, tolerance_deg: float, settle_limit: float, override: bool,
                     telemetry_hz: int, log: str, say=print):
    """Gate the move to targets (rad) on the twin, send it to the device `session` opens (a context manager giving
    (link, spec)) and watch it follow, say(line) every SHOWN_EVERY_S; (spec with the device's configuration,
    mirror's result, the outcome in lines). UserError (one line) where the gate refused (its report said first),
    the device was not ready or the link failed (naming the session log)."""
    last = [0.0]

    def show(t, device, predicted):
        if t - last[0] >= SHOWN_EVERY_S:
            last[0] = t
            dev = np.abs(device - predicted)
            say(f"t={t:6.3f} s  device " + " ".join(f"{a:7.1f}" for a in device)
                + f"  deg   largest deviation {dev.max():4.1f} deg (hinge {int(dev.argmax())})")

    try:
        with session as (link, spec):
            if override:
                say("gate override requested: a failed check will be logged and the move sent anyway")
            result = mirror(link, spec, targets, tolerance_deg=tolerance_deg, settle_limit=settle_limit,
                            override=override, telemetry_hz=telemetry_hz, on_frame=show, hinges=profile.hinges,
                            mount=profile.mount)
    except LinkError as exc:
        raise UserError(f"link: {exc} (session log: {log})") from None
    except GateRefused as exc:
        say(exc.report.text())
        raise UserError(f"{exc} (nothing was sent; --override to send anyway)") from None
    except DeviceNotReady as exc:
        raise UserError(str(exc)) from None
    return spec, result, [result.report.text(), ("mirror: " if result.ok else "mirror: STOPPED: ") + result.message,
                          "final   " + " ".join(f"{a:7.1f}" for a in result.final_deg) + "  deg"]
