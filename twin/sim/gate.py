"""The gate: nothing reaches the hardware that the twin has not simulated and found safe.

`check_move(spec, start, targets, gains)` runs the move on the twin from the
device's present hinge angles with the device's gains; `check_scenario(spec,
scenario, gains)` runs a timed scenario as one run, as it will be played (each
target at its time, whatever the hinges are doing then: a reversal while a hinge
still runs draws what the two steps from rest do not). Both check:

- range:     every target inside the hinge range (deg);
- table:     lying flat (mount "flat"), no target puts a flap below the table (mm; the hinge that takes
             its flap there named): the twin's table would stop it, and a device driven into a table
             levers itself off it at full duty;
- lying_flat: lying flat, the move's start (the device's present angles) puts no flap more than
             NOT_FLAT_DEPTH below the table (mm; the flap named): a device that says it lies flat but whose
             flaps hang below its table is held otherwise (hanging, its flaps sagged), and the twin, which
             cannot start inside its table, would predict nothing of it (check_move only: a scenario's start
             is a plan, gated as a target by the move there);
- collision: no flap-on-flap contact anywhere along the simulated trajectory
             (trace angles replayed through mj_forward, every `collision_step` s; the
             same contact as twin.device.flap_collision finds without MuJoCo);
- settle:    the move's settle time (twin.sim.response.settle_time: every hinge within
             settle_band counts, staying there settle_hold s) is at most `settle_limit` s;
- peak current: the largest winding current, A, within the motor driver's peak rating
             (spec [power] driver_peak_current; not the stall current: braking or
             reversing at speed draws more, back-EMF adding to the supply), naming the
             hinge and the moment;
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
from twin.device.kinematics import flap_frames
from twin.device.mount import DEFAULT_MOUNT, table_height
from twin.device.spec import DeviceSpec
from twin.formats.scenario import Scenario
from twin.records.trace import Trace, joined
from twin.sim.replay import replay_targets
from twin.sim.response import move_settle_time
from twin.sim.twin import Twin


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

    @property
    def settle_time(self) -> float:
        """The predicted move's settle time, s (twin.sim.response.settle_time); NaN where it did not settle
        within the limit or was not simulated."""
        c = next((c for c in self.checks if c.name == "settle"), None)
        return c.value if c is not None and c.passed else math.nan

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
               hold_current_limit: float | None = None, twin: Twin | None = None, integral=None,
               mount: str = DEFAULT_MOUNT) -> GateReport:
    """Simulate start -> targets (rad) on the twin with the device's gains (one PidGains or one per hinge),
    from the PID integral the device holds (duty per hinge, its STATE's; default none). mount: how the device
    is held (twin.device.mount.MOUNTS; a given twin's own wins)."""
    start = np.asarray(start, float)
    targets = np.asarray(targets, float)
    mount = twin.mount if twin is not None else mount
    checks = _target_checks(spec, [targets], mount)
    checks += _start_checks(spec, start, mount) if all(c.passed for c in checks) else []
    if not all(c.passed for c in checks):
        return GateReport(start, targets, checks, None)
    twin = _twin_at(spec, start, gains, twin, integral, mount)
    trace = twin.move_to(targets, max_time=settle_limit, stop_when_settled=True)
    moved = _heat(twin)
    hold = twin.hold(spec.settle_hold)  # keep simulating: the hold current is what the device draws at rest

    checks.append(_collision_check(spec, twin, trace, collision_step))
    checks.append(_settle_check(spec, trace, 0, settle_limit, ""))
    checks += _current_checks(spec, trace, hold, peak_current_limit, hold_current_limit)
    checks.append(_thermal_check(moved, _heat(twin)))
    return GateReport(start, targets, checks, trace)


def check_scenario(spec: DeviceSpec, scenario: Scenario, gains=None, settle_limit: float = 2.0,
                   collision_step: float = 0.005, peak_current_limit: float | None = None,
                   hold_current_limit: float | None = None, twin: Twin | None = None,
                   mount: str = DEFAULT_MOUNT) -> GateReport:
    """Simulate a whole scenario on the twin as one run, as it will be played, and check it whole (mount: as
    check_move's).

    From the scenario's start, each target takes effect at its time; the run lasts the scenario's
    duration, or until settle_limit s after the last target if that is later. The settle check is the last
    target's (earlier ones may be left on purpose before they settle); the currents are the whole run's,
    the peak named with its hinge and moment (s from the first target).
    """
    start = np.asarray(scenario.start, float)
    last = np.asarray(scenario.targets[-1], float)
    mount = twin.mount if twin is not None else mount
    checks = _target_checks(spec, scenario.targets, mount)
    if not all(c.passed for c in checks):
        return GateReport(start, last, checks, None)
    twin = _twin_at(spec, start, gains, twin, mount=mount)
    dt = spec.firmware_dt
    end = int(round(max(scenario.duration, scenario.times[-1] + settle_limit) / dt))
    trace = joined([tr for _, tr in replay_targets(twin, list(zip(scenario.times, scenario.targets)), 0, end)])
    moved = _heat(twin)
    hold = twin.hold(spec.settle_hold)

    checks.append(_collision_check(spec, twin, trace, collision_step))
    checks.append(_settle_check(spec, trace, int(round(scenario.times[-1] / dt)), settle_limit, "the last target"))
    checks += _current_checks(spec, trace, hold, peak_current_limit, hold_current_limit)
    checks.append(_thermal_check(moved, _heat(twin)))
    return GateReport(start, last, checks, trace)


def _range_check(spec: DeviceSpec, steps) -> Check:
    """Every target inside the hinge range: the farthest one, with its hinge (and step, if more than one)."""
    lim = math.degrees(spec.hinge_limit)
    steps = [np.asarray(t, float) for t in steps]
    if not all(t.shape == (spec.n_hinges,) and np.all(np.isfinite(t)) for t in steps):
        return Check("range", False, float("inf"), lim, "deg", f"expected {spec.n_hinges} finite targets")
    far = np.abs(np.degrees(np.array(steps)))
    i, k = np.unravel_index(int(np.argmax(far)), far.shape)
    detail = f"hinge {k}" + (f", step {i}" if len(steps) > 1 else "")
    return Check("range", float(far[i, k]) <= lim + 1e-9, float(far[i, k]), lim, "deg", detail)


def _target_checks(spec: DeviceSpec, steps, mount: str) -> list[Check]:
    """The checks on the targets alone, before anything is simulated: the range, and the table lying flat."""
    checks = [_range_check(spec, steps)]
    if mount == "flat" and checks[0].passed:
        checks.append(_table_check(spec, steps))
    return checks


# m: the deepest a flap of a device lying flat may read below its table at rest. A flap resting on the table
# reads a little under it through each hinge's count (0.3 deg) and backlash (up to 0.5 deg): -1 deg on every
# hinge puts the outermost flap 2.7 mm under, -3 deg 8.2 mm; a device hanging from its root flap sags tens of
# degrees within a second (hinges 2-3 to -58 and -65 deg in 2 s on the emulator: flap 0 66 mm under).
NOT_FLAT_DEPTH = 0.010


def _start_checks(spec: DeviceSpec, start: np.ndarray, mount: str) -> list[Check]:
    """Lying flat: the start (the device's present angles) puts no flap more than NOT_FLAT_DEPTH below the
    table, the deepest flap named (else the device is not lying flat)."""
    if mount != "flat":
        return []
    depth = below_table(spec, start)
    j = int(np.argmax(depth))
    ok = bool(depth[j] <= NOT_FLAT_DEPTH)
    detail = "no flap below the table at the start" if ok else (
        f"flap {j} lies {depth[j] * 1000:.1f} mm below the table at the start: the device is not lying flat as its "
        "mount says; hanging? (docs/device.md, \"Mounts\")")
    return [Check("lying_flat", ok, float(depth[j]) * 1000, NOT_FLAT_DEPTH * 1000, "mm", detail)]


def below_table(spec: DeviceSpec, angles) -> np.ndarray:
    """Per flap, how far its lowest corner lies below the table of a device lying flat, m (0 where above), at
    hinge angles (rad): each flap's box (its touch surface, the thickness behind it) from the kinematics."""
    frames = flap_frames(spec, angles)
    half = (spec.flap_pitch - spec.flap_gap) / 2
    corners = np.array([[x, 0.0, z, 1.0] for x in (-half, half) for z in (0.0, -spec.thickness)])
    lowest = (frames @ corners.T)[:, 2, :].min(axis=1)
    return np.maximum(0.0, table_height(spec) - lowest)


def _table_check(spec: DeviceSpec, steps) -> Check:
    """Lying flat: no target puts a flap below the table (CONTACT_DEPTH allowed). The value is the deepest
    flap's depth; the detail names, in the first step that goes under, the hinge nearest the root that takes
    its flap under (the chain beyond follows it) and its step, if more than one."""
    depth = np.array([below_table(spec, t) for t in steps])
    deepest = float(depth.max())
    if deepest <= CONTACT_DEPTH:
        return Check("table", True, deepest * 1000, CONTACT_DEPTH * 1000, "mm", "no flap below the table")
    r = spec.root_flap
    i = int(np.flatnonzero(depth.max(axis=1) > CONTACT_DEPTH)[0])
    under = np.flatnonzero(depth[i] > CONTACT_DEPTH)
    j = int(under[np.argmin(np.abs(under - r))])
    hinge = j if j < r else j - 1
    detail = f"hinge {hinge} takes flap {j} {depth[i, j] * 1000:.1f} mm below the table" + (
        f" at step {i}" if len(steps) > 1 else "")
    return Check("table", False, deepest * 1000, CONTACT_DEPTH * 1000, "mm", detail)


def _twin_at(spec: DeviceSpec, start, gains, twin: Twin | None, integral=None, mount: str = DEFAULT_MOUNT) -> Twin:
    """A twin (the given one, or a new one held as `mount`) with the device's gains, holding the start angles
    (rad) with the PID integral given (duty per hinge; default none)."""
    if twin is None:
        twin = Twin(spec, gains if isinstance(gains, PidGains) or gains is None else list(gains), mount=mount)
    else:
        twin.set_gains(PidGains.from_spec(spec) if gains is None else gains)
    twin.reset(np.clip(start, -spec.hinge_limit, spec.hinge_limit), integral)
    return twin


def _collision_check(spec: DeviceSpec, twin: Twin, trace: Trace, collision_step: float) -> Check:
    """Flap-on-flap contact along the trajectory (every collision_step s, and at its end)."""
    m, d = twin.model, mujoco.MjData(twin.model)
    mujoco.mj_resetDataKeyframe(m, d, m.key("flat").id)
    every = max(1, int(round(collision_step / spec.firmware_dt)))
    rows = list(range(0, len(trace.time), every)) + [len(trace.time) - 1]
    hit, deepest = None, 0.0
    for i in rows:
        contacts = flap_contacts(m, d, twin.hinges.qadr, trace.true_angle[i])
        if contacts:
            a, b, depth = max(contacts, key=lambda c: c[2])
            if depth > deepest:
                deepest = depth
                hit = f"{a} and {b} at t={trace.time[i] - trace.time[0]:.3f} s"
    return Check("collision", hit is None, deepest * 1000, 0.0, "mm", hit or "no flap-on-flap contact")


def _settle_check(spec: DeviceSpec, trace: Trace, first: int, settle_limit: float, scope: str) -> Check:
    """The move's settle time (response.move_settle_time) from row `first` on, against settle_limit s; scope
    names the target checked in the detail ("" for the one move)."""
    t_settle = move_settle_time(spec, trace.time[first:], trace.counts[first:], trace.target_counts[first:])
    if math.isfinite(t_settle) and t_settle <= settle_limit:
        return Check("settle", True, t_settle, settle_limit, "s", f"{scope}, all hinges" if scope else "all hinges")
    err = np.abs(trace.target_counts[-1] - trace.counts[-1])
    worst = int(np.argmax(err))
    return Check("settle", False, math.inf, settle_limit, "s",
                 (f"{scope}: " if scope else "") + f"hinge {worst} still {int(err[worst])} counts off at the end")


def current_limits(spec: DeviceSpec, peak_current_limit: float | None = None,
                   hold_current_limit: float | None = None) -> tuple[float, float]:
    """The gate's current limits, A: (peak winding current, mean current while holding), the given ones or
    the driver's peak rating and the motor's continuous rating. The tuner keeps its candidates within them."""
    return peak_current_limit or spec.driver_peak_current, hold_current_limit or spec.continuous_current


def _current_checks(spec: DeviceSpec, trace: Trace, hold: Trace, peak_current_limit, hold_current_limit) -> list:
    """The peak winding current over the run (hinge and moment) and the mean over the hold after it."""
    peak_lim, hold_lim = current_limits(spec, peak_current_limit, hold_current_limit)
    cur = np.abs(trace.current)
    i, k = np.unravel_index(int(np.argmax(cur)), cur.shape) if cur.size else (0, 0)
    peak_i = float(cur[i, k]) if cur.size else 0.0
    when = float(trace.time[i] - trace.time[0]) if cur.size else 0.0
    out = [Check("peak_current", peak_i <= peak_lim, peak_i, peak_lim, "A", f"hinge {k} at t={when:.3f} s")]
    held = np.abs(hold.current).mean(axis=0)
    k = int(np.argmax(held))
    out.append(Check("hold_current", float(held[k]) <= hold_lim, float(held[k]), hold_lim, "A", f"hinge {k}"))
    return out


def _heat(twin: Twin) -> tuple[np.ndarray, int]:
    """The twin's firmware's I2t estimate per hinge (share of its budget) and its derated hinges' bits."""
    return twin.firmware.heat, twin.firmware.derated


def _thermal_check(*readings) -> Check:
    """The firmware's I2t protection as the twin's run met it (from cold): the largest estimate, as a share of
    the budget, after the move and after the hold; at 100 % the device derates the hinge to its continuous
    current, and the move is not what was asked."""
    share = np.max([h for h, _ in readings], axis=0)
    derated = any(d for _, d in readings)
    k = int(np.argmax(share))
    return Check("i2t", not derated and float(share[k]) < 1.0, float(share[k]) * 100, 100.0, "%",
                 f"hinge {k}" + (": derated to its continuous current" if derated else " (from cold)"))


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
