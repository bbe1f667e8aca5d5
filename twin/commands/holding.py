"""`vrscroll holding --serial PORT`: what the device does when its drive is cut. Releases from flat under
gravity (e-stopped: each winding shorted, the flaps braked by their motors' back-EMF), the gearboxes'
back-driven efficiency fitted to them, kept in the device profile, and what the twin then says a braked
device does in the seconds after its drive is cut, and an unpowered one (a pack pulled: the windings open)
(twin.hil.holding; docs/tuning-hil-calibration.md)."""

from __future__ import annotations

import math

from twin.commands.options import (
    add_device_option,
    add_json,
    add_mount,
    add_serial,
    add_tolerance_deg,
    device_session,
    json_to_stdout,
    link_errors,
    opened,
    within,
    write_json,
)
from twin.errors import UserError
from twin.hil.holding import PREDICT_S, RELEASE_S, measure_holding
from twin.hil.mirror import DeviceNotReady
from twin.sim.gate import GateRefused


def add_arguments(p) -> None:
    add_serial(p, required=True)
    p.add_argument("--releases", type=within(1, 10, whole=True), default=2,
                   help="releases to record and fit (default %(default)s)")
    p.add_argument("--release-s", type=within(0.1, 2.0, "s"), default=RELEASE_S,
                   help="s recorded after each e-stop (default %(default)s; longer sags further, up to the hinge "
                        "range)")
    add_tolerance_deg(p)
    p.add_argument("--log", help="session log, JSON lines")
    add_json(p, "the releases, the fit and the prediction")
    add_device_option(p)
    add_mount(p)


def run(args) -> int:
    profile, spec = opened(args)
    if profile.mount != "hanging":  # lying flat the table holds the flaps up; on a stand gravity loads no hinge
        raise UserError(f"holding releases the flaps under gravity, which the {profile.mount} mount takes away: hang "
                        "the device from its root flap and give --mount hanging (docs/device.md, \"Mounts\")")
    quiet = json_to_stdout(args)

    def progress(k, release):
        if not quiet:
            print(f"release {k + 1}/{args.releases}: {len(release.t)} frames, sag per hinge "
                  + " ".join(f"{d:.1f}" for d in release.angle_deg[-1] - release.angle_deg[0]) + " deg", flush=True)

    try:
        with link_errors(), device_session(args, spec) as (link, spec):
            got = measure_holding(link, spec, profile, args.releases, args.release_s, args.tolerance_deg, progress)
    except (GateRefused, DeviceNotReady) as exc:
        raise UserError(str(exc)) from None
    write_json(args.json, got.to_json())
    if quiet:
        return 0
    e, fit = got.fit.estimate, got.fit
    print(f"backdrive_efficiency {e.value:.3f} (prior {e.prior:.3f}; 95 % interval {e.low:.3f} .. {e.high:.3f}; "
          f"{'identifiable' if e.identifiable else 'NOT identifiable'}), {fit.replays} twin releases:\n  {e.note}"
          + ("" if got.ranges.calibrated else "\n  (an uncalibrated profile: the other parameters' ranges are the "
                                              "spec's spread; `vrscroll calibrate` first narrows them)"))
    print(f"sag over {args.release_s:g} s per hinge, deg (mean of the releases):")
    for label, key in (("device", "device"), ("twin before", "twin_before"), ("twin after", "twin_after")):
        print(f"  {label:<12}" + " ".join(f"{d:7.2f}" for d in fit.sag_deg[key]))
    print("the twin, braked with its drive cut at flat (root flap held level), hinge angles, deg:")
    for s, angles in got.braked.items():
        print(f"  after {s} s: " + " ".join(f"{a:7.1f}" for a in angles))
    held = [k for k, a in enumerate(got.braked[f"{PREDICT_S[0]:g}"]) if abs(a) < 1.0]
    print(f"holds within 1 deg for {PREDICT_S[0]:g} s: hinges {held or 'none'}; the others sag towards their "
          f"limits (+-{math.degrees(spec.hinge_limit):g} deg) or until a flap rests on something")
    print("the twin, its pack pulled at flat (no power: the windings open and carry no current, so only the "
          "gearboxes' friction holds; the efficiency fitted above does not act), hinge angles, deg:")
    for s, angles in got.unpowered.items():
        print(f"  after {s} s: " + " ".join(f"{a:7.1f}" for a in angles))
    print(f"kept in device profile {profile.name} ({got.written})" if got.written else
          "not kept: no device profile (--device NAME keeps it)")
    return 0
