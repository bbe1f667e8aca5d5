"""Holding: what the device does when its drive is cut, measured by a release under gravity and fitted.

At an e-stop (ESTOP; and after a fault) the firmware gives every hinge zero duty in slow decay: each
winding is shorted, so a flap that gravity turns drives its gearbox backwards and the motor brakes it with
its back-EMF current. How fast a loaded hinge then sags is set by the gravity torque, the gearbox's
friction (calibrated from HIL runs: twin.hil.calibration) and how much of the load's power the gearbox
passes to the motor when back-driven, `backdrive_efficiency` (twin.sim.drive: the braking torque felt at
the output is the motor's / backdrive_efficiency). The spec's 0.5 is an assumption; with it the twin's
hinges 2 and 3, which carry three flaps each, sag about 29 deg in 0.4 s from flat.

A release (`record_release`): the device is brought to POSE (gated, twin.hil.mirror) and left to rest,
then e-stopped; its telemetry is recorded for RELEASE_S, then the e-stop is cleared. On the twin
(`twin_release`): the same pose at the device's encoder angles, the firmware e-stopped, RELEASE_S played.

The fit (`fit_backdrive`): backdrive_efficiency, one value for every gearbox, minimising the sum of
squares of device - twin encoder angle (deg) over every frame and hinge of every release, searched in
log within BOUNDS (scipy's bounded scalar search). Its 95 % interval is where that sum stays within
3.84 sigma^2 tau of its least: a profile likelihood, sigma^2 the residual's mean square (at least the
encoder's quantisation, a count^2 / 12), tau its autocorrelation time in frames
(twin.hil.calibration.autocorrelation_time: frames that move together count once), never narrower
than the search's resolution; an end of BOUNDS inside it is left open. Then widened by how far each
other parameter would move the fit from either end of what is known of it (a calibration's
intervals; the spec's spread for an uncalibrated device): the braking torque goes with the motor
constant squared, so an unidentified no-load speed leaves the efficiency unidentified too.
Identifiable as in calibration: the interval within x(1 -+ MAX_HALFWIDTH). Angles in deg where they
are reported, SI otherwise.

`measure_holding` is `vrscroll holding`'s whole job: the releases, the fit, the profile with the fitted value
and its record (written where it has a name), and what the twin then says a braked and an unpowered device do.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
from scipy.optimize import brentq, minimize_scalar

from controllers.encoder import angle_from_counts
from twin.device.spec import DeviceSpec
from twin.device.variation import prior_ranges, scaled
from twin.formats.profile import updated, write_profile
from twin.hil.calibration import MAX_HALFWIDTH, Estimate, autocorrelation_time
from twin.hil.mirror import DeviceNotReady, mirror, wait_for_rest
from twin.link import protocol as P
from twin.records.profile import Holding, Profile
from twin.records.ranges import Ranges
from twin.sim.twin import Twin

RELEASE_S = 0.4  # s recorded after the e-stop: hinges 2-3 sag ~29 deg on the spec's twin, well within the hinge range
POSE = 0.0  # rad, every hinge: flat, where the gravity torque on the hinges beside the root flap is largest
BOUNDS = (0.05, 1.0)  # backdrive_efficiency's range searched: from nearly self-locking to lossless
CHI2_95 = 3.84  # chi-square quantile, one degree of freedom, 95 %
SEARCH_TOL = 0.005  # log: the search's resolution, the least half-width of an interval
TELEMETRY_HZ = 500
PREDICT_S = (1.0, 5.0)  # s after the drive is cut: what the twin reports, braked
UNPOWERED_S = (0.1, 0.5)  # s after a pack is pulled: what the twin reports, the windings open


@dataclasses.dataclass
class Release:
    """One release recorded on the device: frame times (s from the first e-stopped frame) and encoder
    angles (deg, mid-count, (frames, n)); start: the encoder angles (rad) at rest just before."""

    t: np.ndarray
    angle_deg: np.ndarray
    start: np.ndarray

    def to_json(self) -> dict:
        return {"t_s": self.t.round(4).tolist(), "angle_deg": self.angle_deg.round(4).tolist(),
                "start_deg": np.degrees(self.start).round(4).tolist()}


def _encoder_deg(spec: DeviceSpec, counts) -> np.ndarray:
    return np.degrees(angle_from_counts(spec, np.asarray(counts, float) + 0.5))


def record_release(link, spec: DeviceSpec, duration: float = RELEASE_S, tolerance_deg: float = 5.0,
                   hinges=None) -> Release:
    """Bring the device to POSE (gated on the twin, hinges: each hinge's own plant), let it rest, e-stop it and
    record its telemetry for `duration` s, then clear the e-stop (the device IDLE, where it sagged to).
    DeviceNotReady if it cannot reach the pose."""
    n = spec.n_hinges
    res = mirror(link, spec, np.full(n, POSE), tolerance_deg=tolerance_deg, hinges=hinges)
    if not res.ok:
        raise DeviceNotReady(f"the device did not reach the release pose: {res.message}")
    state = wait_for_rest(link, spec)
    link.set_telemetry_rate(TELEMETRY_HZ)
    link.drain_telemetry()
    rows = []
    try:
        link.estop()
        deadline = time.monotonic() + duration + 2.0
        while time.monotonic() < deadline:
            item = link.telemetry(timeout=0.2)
            if item is None:
                continue
            fr = item[1]
            if fr.state != P.State.ESTOP:
                continue
            rows.append((fr.time_us, fr.counts))
            if (rows[-1][0] - rows[0][0]) % 2 ** 32 >= duration * 1e6:
                break
    finally:
        link.clear_fault()
    if len(rows) < 10:
        raise DeviceNotReady(f"{len(rows)} telemetry frames after the e-stop (at least 10 needed): "
                             "is the device streaming telemetry?")
    t = np.array([((us - rows[0][0]) % 2 ** 32) * 1e-6 for us, _ in rows])
    return Release(t, _encoder_deg(spec, [c for _, c in rows]), angle_from_counts(spec, np.asarray(state.counts) + 0.5))


def twin_release(plant: DeviceSpec, release: Release, spec: DeviceSpec | None = None, hinges=None) -> np.ndarray:
    """The twin's encoder angles (deg, at the release's frame times) after an e-stop at the release's start.
    plant: the physics (hinges: each hinge's own, Twin's); spec: the device's encoder (default the plant's)."""
    spec = spec or plant
    twin = Twin(plant, hinges=hinges)
    twin.reset(np.clip(release.start, -spec.hinge_limit, spec.hinge_limit))
    twin.firmware.estop()
    trace = twin.hold(float(release.t[-1]) + 2 * plant.firmware_dt)
    rows = np.minimum(np.round(release.t / plant.firmware_dt).astype(int), len(trace.counts) - 1)
    return _encoder_deg(spec, trace.counts[rows])


@dataclasses.dataclass
class HoldingFit:
    estimate: Estimate  # backdrive_efficiency
    sag_deg: dict  # per hinge, the angle change over the release (deg, mean over releases): device, twin before, after
    autocorrelation_frames: float
    replays: int


def with_values(plant: DeviceSpec, hinges, values: dict):
    """The plant (and each hinge's own spec) with the fields in values (SI; a hinge's own value scaled alike)."""
    scales = {f: v / getattr(plant, f) for f, v in values.items()}  # a field that moves another moves it too
    return scaled(plant, scales), [scaled(h, scales) for h in hinges] if hinges else None


def fit_backdrive(releases: list[Release], plant: DeviceSpec, hinges=None, ranges: Ranges | None = None) -> HoldingFit:
    """backdrive_efficiency from releases (module docstring), about the plant's value (its prior). ranges:
    what is known of the other parameters (a calibration's intervals, SI): the interval is widened by how far
    each would move the fit from either end of its shared range."""
    count = [0]

    def residual(x: float, p: DeviceSpec, h) -> list[np.ndarray]:
        count[0] += 1
        p, h = with_values(p, h, {"backdrive_efficiency": math.exp(x)})
        return [r.angle_deg - twin_release(p, r, plant, h) for r in releases]

    def cost(x: float, p: DeviceSpec = plant, h=hinges) -> float:
        return float(sum(np.sum(b ** 2) for b in residual(x, p, h)))

    lo, hi = math.log(BOUNDS[0]), math.log(BOUNDS[1])

    def best(p: DeviceSpec, h) -> tuple[float, float]:
        found = minimize_scalar(cost, bounds=(lo, hi), args=(p, h), method="bounded", options={"xatol": SEARCH_TOL})
        return float(found.x), float(found.fun)

    x, least = best(plant, hinges)
    blocks = residual(x, plant, hinges)
    tau = autocorrelation_time(blocks)
    quantum = math.degrees(plant.rad_per_count) ** 2 / 12  # deg^2: no fit is closer than the encoder's resolution
    rise = CHI2_95 * max(least / sum(b.size for b in blocks), quantum) * tau

    def edge(end: float) -> float:
        if cost(end) - least <= rise:
            return end  # the bound itself inside the interval: left open
        return brentq(lambda v: cost(v) - least - rise, min(x, end), max(x, end), xtol=SEARCH_TOL)

    down, up = min(edge(lo) - x, -SEARCH_TOL), max(edge(hi) - x, SEARCH_TOL)  # log, the fit's own interval
    moved = []
    others = {f: ends for f, ends in (ranges.shared if ranges else {}).items()
              if f != "backdrive_efficiency"}
    for f, ends in others.items():  # each other parameter at either end of its range, the fit again
        shifts = [best(*with_values(plant, hinges, {f: v}))[0] - x for v in ends]
        down, up = down + min(0.0, *shifts), up + max(0.0, *shifts)
        moved.append(f"{f} x{math.exp(min(shifts)):.2f} .. x{math.exp(max(shifts)):.2f}")
    value = math.exp(x)
    low, high = max(BOUNDS[0], value * math.exp(down)), min(BOUNDS[1], value * math.exp(up))
    identifiable = low > BOUNDS[0] and high < BOUNDS[1] and max(value / low, high / value) <= 1 + MAX_HALFWIDTH
    note = (f"from {len(releases)} release(s) of {releases[0].t[-1]:.2f} s; 95 % interval x{low / value:.3f} .. "
            f"x{high / value:.3f}" + (f", widened by the other parameters' ranges ({'; '.join(moved)})" if moved else "")
            + ("" if identifiable else f": not identifiable (wider than x(1 -+ {MAX_HALFWIDTH:g}) or open at a bound)"))
    estimate = Estimate(value, plant.backdrive_efficiency, low, high, identifiable, note)
    before = [twin_release(plant, r, plant, hinges) for r in releases]
    fitted, own = with_values(plant, hinges, {"backdrive_efficiency": value})
    after = [twin_release(fitted, r, plant, own) for r in releases]

    def sag(traces) -> list[float]:
        return np.mean([tr[-1] - tr[0] for tr in traces], axis=0).round(3).tolist()

    sags = {"device": sag([r.angle_deg for r in releases]), "twin_before": sag(before), "twin_after": sag(after)}
    return HoldingFit(estimate, sags, tau, count[0])


def sag_after_cut(plant: DeviceSpec, duration: float, hinges=None, braked: bool = True) -> np.ndarray:
    """What the twin says the device does when its drive is cut at rest at POSE: each hinge's angle (deg)
    after `duration` s. braked: an e-stop (every winding braked, as the firmware does); else unpowered (a pack
    pulled: the windings open, nothing but friction and the gearboxes holding the flaps)."""
    twin = Twin(plant, hinges=hinges)
    twin.reset(np.full(plant.n_hinges, POSE))
    twin.firmware.estop()
    return np.degrees((twin.hold(duration) if braked else twin.unpowered(duration)).true_angle[-1])


@dataclasses.dataclass(frozen=True)
class HoldingMeasured:
    """What `measure_holding` found: the releases, the fit, and the twin's prediction with the fitted value."""

    releases: list[Release]
    fit: HoldingFit
    ranges: Ranges  # what was known of the other parameters (a calibration's intervals, or the spec's spread)
    profile: Profile  # the profile with the fitted value and its Holding record
    written: str | None  # the profile's folder where it was kept (a named profile), else None
    braked: dict[str, list[float]]  # s after the drive is cut (PREDICT_S) -> each hinge's angle, deg
    unpowered: dict[str, list[float]]  # s after a pack is pulled (UNPOWERED_S) -> each hinge's angle, deg

    def to_json(self) -> dict:
        e = self.fit.estimate
        return {"device_profile": self.profile.label, "written": self.written, "backdrive_efficiency": e.to_json(),
                "autocorrelation_frames": round(self.fit.autocorrelation_frames, 1), "replays": self.fit.replays,
                "sag_deg": self.fit.sag_deg, "braked_from_flat_deg": self.braked,
                "unpowered_from_flat_deg": self.unpowered, "releases": [r.to_json() for r in self.releases]}

    def lines(self, spec: DeviceSpec, release_s: float) -> list[str]:
        """What was found, in words (deg; release_s: each release's s): the fitted value, the sag of the device
        and the twin before and after the fit, the twin braked and unpowered after its drive is cut, where kept."""
        e, fit = self.fit.estimate, self.fit
        lines = [f"backdrive_efficiency {e.value:.3f} (prior {e.prior:.3f}; 95 % interval {e.low:.3f} .. "
                 f"{e.high:.3f}; {'identifiable' if e.identifiable else 'NOT identifiable'}), {fit.replays} twin "
                 f"releases:\n  {e.note}"
                 + ("" if self.ranges.calibrated else "\n  (an uncalibrated profile: the other parameters' ranges "
                                                     "are the spec's spread; `vrscroll calibrate` first narrows them)"),
                 f"sag over {release_s:g} s per hinge, deg (mean of the releases):"]
        lines += [f"  {label:<12}" + " ".join(f"{d:7.2f}" for d in fit.sag_deg[key])
                  for label, key in (("device", "device"), ("twin before", "twin_before"), ("twin after", "twin_after"))]
        lines.append("the twin, braked with its drive cut at flat (root flap held level), hinge angles, deg:")
        lines += [f"  after {s} s: " + " ".join(f"{a:7.1f}" for a in angles) for s, angles in self.braked.items()]
        held = [k for k, a in enumerate(self.braked[f"{PREDICT_S[0]:g}"]) if abs(a) < 1.0]
        lines += [f"holds within 1 deg for {PREDICT_S[0]:g} s: hinges {held or 'none'}; the others sag towards their "
                  f"limits (+-{math.degrees(spec.hinge_limit):g} deg) or until a flap rests on something",
                  "the twin, its pack pulled at flat (no power: the windings open and carry no current, so only the "
                  "gearboxes' friction holds; the efficiency fitted above does not act), hinge angles, deg:"]
        lines += [f"  after {s} s: " + " ".join(f"{a:7.1f}" for a in angles) for s, angles in self.unpowered.items()]
        lines.append(f"kept in device profile {self.profile.name} ({self.written})" if self.written else
                     "not kept: no device profile (--device NAME keeps it)")
        return lines


def measure_holding(link, spec: DeviceSpec, profile: Profile, count: int, duration: float = RELEASE_S,
                    tolerance_deg: float = 5.0, progress=None) -> HoldingMeasured:
    """`count` releases of `duration` s on the device (record_release; progress(k, release) after each), the
    back-driven efficiency fitted about the profile's plant with what is known of the others, the profile with
    it (written where the profile has a name), and the twin's sag after a cut, braked and unpowered."""
    releases = []
    for k in range(count):
        releases.append(record_release(link, spec, duration, tolerance_deg, profile.hinges))
        if progress:
            progress(k, releases[-1])
    ranges = profile.ranges(prior_ranges(spec))
    fit = fit_backdrive(releases, spec, profile.hinges, ranges)
    e = fit.estimate
    fitted, hinges = with_values(spec, profile.hinges, {"backdrive_efficiency": e.value})
    profile = updated(profile, {"backdrive_efficiency": e.value},
                      f"measured by `vrscroll holding` from {count} release(s) on {link.url}",
                      holding=Holding(link.url, count, {"backdrive_efficiency": e}))
    written = str(write_profile(profile, by="vrscroll holding")) if profile.name else None
    braked = {f"{s:g}": sag_after_cut(fitted, s, hinges).round(2).tolist() for s in PREDICT_S}
    unpowered = {f"{s:g}": sag_after_cut(fitted, s, hinges, braked=False).round(2).tolist() for s in UNPOWERED_S}
    return HoldingMeasured(releases, fit, ranges, profile, written, braked, unpowered)
