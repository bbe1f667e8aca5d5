"""`vrscroll holding --serial PORT`: what the device does when its drive is cut. Releases from flat under
gravity (e-stopped: each winding shorted, the flaps braked by their motors' back-EMF), the gearboxes'
back-driven efficiency fitted to them, kept in the device profile, and what the twin then says a braked
device does in the seconds after its drive is cut, and an unpowered one (a pack pulled: the windings open)
(twin.hil.holding; docs/tuning-hil-calibration.md)."""

from __future__ import annotations

from twin.commands.options import (add_device_option, add_json, add_mount, add_serial, add_tolerance_deg,
                                   json_to_stdout, opened, within, write_json)
from twin.errors import UserError
from twin.hil.device_gains import device_session, link_errors
from twin.hil.holding import RELEASE_S, measure_holding
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
        with link_errors(), device_session(args.serial, spec, args.log) as (link, spec):
            got = measure_holding(link, spec, profile, args.releases, args.release_s, args.tolerance_deg, progress)
    except (GateRefused, DeviceNotReady) as exc:
        raise UserError(str(exc)) from None
    write_json(args.json, got.to_json())
    if not quiet:
        print("\n".join(got.lines(spec, args.release_s)))
    return 0
