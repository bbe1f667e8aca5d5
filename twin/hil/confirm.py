"""Tuned gains confirmed on the device (`vrscroll tune --serial`): pushed all or nothing, one step from flat on
the device and the same step on the twin from where the device started, each hinge's settle time and overshoot
side by side."""

from __future__ import annotations

import math

import numpy as np

from controllers.encoder import target_counts
from twin.device.mount import DEFAULT_MOUNT
from twin.device.spec import DeviceSpec
from twin.errors import UserError
from twin.formats.move_report import move_rows
from twin.hil.device_gains import push_gains
from twin.hil.mirror import DeviceNotReady, device_step
from twin.link.serial_link import LinkError
from twin.sim.gate import GateRefused
from twin.sim.replay import twin_at_start
from twin.sim.response import move_report, step_metrics


def confirm_step(link, spec: DeviceSpec, gains, targets, duration: float, pushed, hinges=None,
                 mount: str = DEFAULT_MOUNT) -> tuple[list[dict], str]:
    """Bring the device to flat with the gains it holds, push the tuned gains there
    (twin.hil.device_gains.push_gains) and call pushed() once the device holds them, then step every hinge from
    flat to targets (rad) on the device (twin.hil.mirror.device_step) and on the twin from where the device
    started, with the integral it held (duration s; hinges: each hinge's own plant; mount: how the device is
    held). The tuner checked its limits on this step from flat, not on the move to flat from wherever the device
    stood (after `calibrate --serial` the flaps stand up to 84 deg, and the tuned gains' braking at the end of a
    fall from there drew 2.45 A in the gate's twin on seed 4242, over the driver's 2 A: refused). Returns (per hinge
    {"hinge", "device_settle_s", "device_overshoot_deg", "twin_settle_s", "twin_overshoot_deg"}, the device
    step's message). GateRefused, DeviceNotReady, LinkError as mirror's; nothing pushed where the move to flat
    was refused."""
    def push() -> None:
        push_gains(link, gains, spec.n_hinges)
        pushed()

    t, deg, start, res = device_step(link, spec, targets, mount=mount, hinges=hinges, at_flat=push)
    twin = twin_at_start(spec, gains, start, hinges=hinges, mount=mount)  # where the device is, with its integral
    pred = move_rows(move_report(spec, twin.move_to(targets, max_time=duration, stop_when_settled=False)))
    band = math.degrees(spec.settle_band * spec.rad_per_count)
    tgt = np.degrees(target_counts(spec, targets) * spec.rad_per_count)
    rows = []
    for k in range(spec.n_hinges):
        m = step_metrics(t, deg[:, k], float(tgt[k]), band, hold=spec.settle_hold) if len(t) > 1 else None
        rows.append({"hinge": k, "device_settle_s": round(m.settle_time, 4) if m else float("nan"),
                     "device_overshoot_deg": round(m.overshoot, 3) if m else float("nan"),
                     "twin_settle_s": pred[k]["settle_time_s"], "twin_overshoot_deg": pred[k]["overshoot_deg"]})
    return rows, res.message


def confirmed(session, gains, step: float, duration: float, pushed, hinges=None, mount: str = DEFAULT_MOUNT,
              log: str = "") -> tuple[list[dict], list[str]]:
    """confirm_step on the device `session` opens (a context manager giving (link, spec)), every hinge stepping
    to `step` (rad): (its rows, them in words). UserError (one line) for a refusal, a device not ready or the
    link (naming the session log)."""
    held = []  # once the device holds the tuned gains

    def hold() -> None:
        pushed()
        held.append(True)

    try:
        with session as (link, spec):
            rows, message = confirm_step(link, spec, gains, np.full(spec.n_hinges, step), duration, hold, hinges,
                                         mount)
    except (GateRefused, DeviceNotReady) as exc:
        raise UserError(f"{exc} (" + ("the tuned gains are on the device and in its profile" if held else
                                      "nothing pushed: the device holds the gains it had") + ")") from None
    except LinkError as exc:
        raise UserError(f"link: {exc} (session log: {log})") from None
    lines = [f"device at {link.url}: {message}",
             f"{'hinge':>5} {'device settle s':>15} {'twin settle s':>13} {'device over deg':>15} {'twin over deg':>13}"]
    lines += [f"{r['hinge']:>5} {r['device_settle_s']:>15.3f} {r['twin_settle_s']:>13.3f} "
              f"{r['device_overshoot_deg']:>15.3f} {r['twin_overshoot_deg']:>13.3f}" for r in rows]
    return rows, lines
