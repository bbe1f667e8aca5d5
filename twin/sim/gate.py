"""The gate: nothing reaches the hardware that the twin has not simulated and found safe.

`check_move(spec, start, targets, gains)` runs the move on the twin from the
device's present hinge angles with the device's gains and checks:

- range:     every target inside the hinge range (deg);
- collision: no flap-on-flap contact anywhere along the simulated trajectory
             (trace angles replayed through mj_forward, every `collision_step` s; the
             same contact as twin.device.flap_collision finds without MuJoCo);
- settle:    every hinge settles (|error| <= settle_band counts for settle_hold s)
             within `settle_limit` s;
- peak current: the largest winding current, A, within the motor driver's peak rating
             (spec [power] driver_peak_current; not the stall current: braking or
             reversing at speed draws more, back-EMF adding to the supply);
- hold current: the mean current over the last `settle_hold` s (what the device
             draws holding the pose indefinitely) within its continuous rating.

The report lists every check with its value and limit; `enforce(report, override)`
raises GateRefused naming the failed checks unless overridden (the caller logs it).
"""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np

from controllers.pid import PidGains
from twin.device.flap_collision import CONTACT_DEPTH
from twin.sim.simulation import Trace, Twin
from twin.device.spec import DeviceSpec


@dataclasses.dataclass(frozen=True)
class Check:
    name: str
    passed: bool
    value: float
    limit: float
    unit: str
    detail: str = ""
    warning: bool = False  # over its limit, but reported rather than refused

    def line(self) -> str:
        mark = "FAIL" if not self.passed else "WARN" if self.warning else "ok  "
        return f"{mark} {self.name:<13} {self.value:10.3f} {self.unit:<4} limit {self.limit:.3f} {self.unit}" + (
            f"  ({self.detail})" if self.detail else "")


@dataclasses.dataclass
class GateReport:
    """Every check of one move, and the twin's predicted trace (None when the range check failed)."""

    start: np.ndarray  # rad
    targets: np.ndarray  # rad
    checks: list[Check]
    prediction: Trace | None
    overridden: bool = False

    @property
    def passed(self) -> bool:
        return all(c.passed for c in self.checks)

    @property
    def failed(self) -> list[Check]:
        return [c for c in self.checks if not c.passed]

    def text(self) -> str:
        head = (f"gate: targets {', '.join(f'{math.degrees(a):.1f}' for a in self.targets)} deg from "
                f"{', '.join(f'{math.degrees(a):.1f}' for a in self.start)} deg")
        return "\n".join([head] + ["  " + c.line() for c in self.checks])

    def refusal(self) -> str:
        return "gate refused the move: " + "; ".join(
            f"{c.name} {c.value:.3f} {c.unit} over limit {c.limit:.3f} {c.unit}" + (f" ({c.detail})" if c.detail else "")
            for c in self.failed)

    def to_dict(self) -> dict:
        return {"passed": self.passed, "overridden": self.overridden,
                "start_deg": np.degrees(self.start).round(3).tolist(),
                "targets_deg": np.degrees(self.targets).round(3).tolist(),
                "checks": [{**dataclasses.asdict(c), "value": c.value if math.isfinite(c.value) else None}
                           for c in self.checks]}


class GateRefused(RuntimeError):
    def __init__(self, report: GateReport):
        self.report = report
        super().__init__(report.refusal())


def flap_contacts(model: mujoco.MjModel, data: mujoco.MjData, hinge_qadr, angles,
                  min_depth: float = CONTACT_DEPTH) -> list[tuple[str, str, float]]:
    """Flap-on-flap contacts at hinge angles (rad): (flap, flap, penetration m) deeper than min_depth."""
    data.qpos[hinge_qadr] = angles
    mujoco.mj_forward(model, data)
    out = []
    for c in data.contact[:data.ncon]:
        a, b = model.geom(c.geom1).name, model.geom(c.geom2).name
        if a.endswith("_collision") and b.endswith("_collision") and -c.dist > min_depth:
            out.append((a.removesuffix("_collision"), b.removesuffix("_collision"), float(-c.dist)))
    return out


def check_move(spec: DeviceSpec, start, targets, gains=None, settle_limit: float = 2.0,
               collision_step: float = 0.005, peak_current_limit: float | None = None,
               hold_current_limit: float | None = None, twin: Twin | None = None) -> GateReport:
    """Simulate start -> targets (rad) on the twin with the device's gains (one PidGains or one per hinge)."""
    start = np.asarray(start, float)
    targets = np.asarray(targets, float)
    lim = math.degrees(spec.hinge_limit)
    checks = []
    worst = int(np.argmax(np.abs(targets))) if targets.size else 0
    ok_shape = targets.shape == (spec.n_hinges,) and np.all(np.isfinite(targets))
    peak = float(np.degrees(np.abs(targets[worst]))) if ok_shape else float("inf")
    checks.append(Check("range", ok_shape and peak <= lim + 1e-9, peak, lim, "deg",
                        f"hinge {worst}" if ok_shape else f"expected {spec.n_hinges} finite targets"))
    if not checks[0].passed:
        return GateReport(start, targets, checks, None)

    if twin is None:
        twin = Twin(spec, gains if isinstance(gains, PidGains) or gains is None else list(gains))
    else:
        twin.set_gains(PidGains.from_spec(spec) if gains is None else gains)
    twin.reset(np.clip(start, -spec.hinge_limit, spec.hinge_limit))
    trace = twin.move_to(targets, max_time=settle_limit, stop_when_settled=True)
    settle_ticks = int(round(spec.settle_hold / spec.firmware_dt))
    hold = twin.hold(spec.settle_hold)  # keep simulating: the hold current is what the device draws at rest

    # collision along the trajectory (and at rest)
    m, d = twin.model, mujoco.MjData(twin.model)
    mujoco.mj_resetDataKeyframe(m, d, m.key("flat").id)
    every = max(1, int(round(collision_step / spec.firmware_dt)))
    rows = list(range(0, len(trace.time), every)) + [len(trace.time) - 1]
    hit, deepest = None, 0.0
    for i in rows:
        contacts = flap_contacts(m, d, twin.hinges.qadr, trace.angle[i])
        if contacts:
            a, b, depth = max(contacts, key=lambda c: c[2])
            if depth > deepest:
                deepest = depth
                hit = f"{a} and {b} at t={trace.time[i] - trace.time[0]:.3f} s"
    checks.append(Check("collision", hit is None, deepest * 1000, 0.0, "mm",
                        hit or "no flap-on-flap contact"))

    # settle: the twin stops early once every hinge has stayed in the band for settle_hold
    err = np.abs(trace.target_counts[-settle_ticks:] - trace.counts[-settle_ticks:]).max(axis=0)
    settled = len(trace.time) < int(round(settle_limit / spec.firmware_dt)) or bool(np.all(err <= spec.settle_band))
    t_settle = trace.duration if settled else float("inf")
    worst = int(np.argmax(err))
    checks.append(Check("settle", settled, t_settle, settle_limit, "s",
                        "all hinges" if settled else f"hinge {worst} still {int(err[worst])} counts off"))

    peak_lim = peak_current_limit or spec.driver_peak_current
    cur = np.abs(trace.current)
    k = int(np.unravel_index(np.argmax(cur), cur.shape)[1]) if cur.size else 0
    peak_i = float(cur.max()) if cur.size else 0.0
    checks.append(Check("peak_current", peak_i <= peak_lim, peak_i, peak_lim, "A", f"hinge {k}"))

    hold_lim = hold_current_limit or spec.continuous_current
    held = np.abs(hold.current).mean(axis=0)
    k = int(np.argmax(held))
    checks.append(Check("hold_current", float(held[k]) <= hold_lim, float(held[k]), hold_lim, "A", f"hinge {k}"))
    return GateReport(start, targets, checks, trace)


def redirection_check(summary: dict, strict: bool = False) -> Check:
    """The perception thresholds as a gate check, from `twin.morphpatch.redirection.threshold_summary`'s dict.

    The share of the touch surface whose pen redirection is within the thresholds must be 1;
    below that it is a warning, or with `strict` a failure.
    """
    share = summary["share_within"]
    over = share < 1.0
    detail = (f"largest {summary['largest_offset_mm']:.1f} mm, {summary['largest_rotation_deg']:.1f} deg; "
              f"thresholds {summary['position_threshold_mm']:g} mm, {summary['rotation_threshold_deg']:g} deg")
    return Check("redirection", not (over and strict), share * 100, 100.0, "%", detail, warning=over and not strict)


def enforce(report: GateReport, override: bool = False) -> GateReport:
    """The report if it passed, or if `override` (marked overridden); GateRefused otherwise."""
    if report.passed:
        return report
    if override:
        report.overridden = True
        return report
    raise GateRefused(report)
