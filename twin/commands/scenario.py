"""`vrscroll scenario FILE`: write the calibration scenario (TOML) for the gains the device has and how it is held,
each move gated on every corner of the plants the device may be (the profile's calibrated intervals, else the
spread about the spec), to record with `vrscroll hil` and fit with `vrscroll calibrate`
(docs/tuning-hil-calibration.md)."""

from __future__ import annotations

from twin.commands.options import add_device_option, add_mount, add_serial, opened, within
from twin.device.variation import corners, prior_ranges
from twin.errors import UserError
from twin.formats.gains import read_gains
from twin.formats.scenario import write_scenario
from twin.hil.calibration_scenario import calibration_scenario
from twin.hil.device_gains import device_gains, link_errors
from twin.link.serial_link import Link


def add_arguments(p) -> None:
    p.add_argument("scenario", metavar="FILE", help="the scenario file to write (TOML)")
    add_serial(p, required=False, what="read the gains from this device")
    p.add_argument("--gains", metavar="FILE", help="a gains file instead of the device's (default: the profile's)")
    p.add_argument("--seed", type=int, default=0, help="which angles (default %(default)s)")
    p.add_argument("--cycles", type=within(1, 100, whole=True), default=2,
                   help="cycles of a large move and a slow ramp out and back (default %(default)s)")
    add_device_option(p)
    add_mount(p)


def run(args) -> int:
    profile, spec = opened(args)
    if args.gains and args.serial:
        raise UserError("give --gains FILE or --serial PORT, not both")
    if args.gains:
        gains = read_gains(args.gains, spec.n_hinges).hinges
    elif args.serial:
        with link_errors(), Link(args.serial, hinges=spec.n_hinges) as link:
            gains = device_gains(link, spec.n_hinges)
    else:
        gains = profile.gains
    ranges = profile.ranges(prior_ranges(spec))
    plants = corners(spec, ranges, profile.hinges)
    print(f"gating every move on {len(plants)} plants (nominal and the corners of {ranges.what}), "
          f"mount: {profile.mount}", flush=True)

    try:
        scenario = calibration_scenario(spec, gains, seed=args.seed, cycles=args.cycles,
                                        name=f"calibration-{args.seed}", mount=profile.mount, plants=plants,
                                        progress=lambda line: print("  " + line, flush=True))
    except ValueError as exc:
        raise UserError(str(exc)) from None
    write_scenario(args.scenario, scenario)
    print(f"calibration scenario written to {args.scenario}: {len(scenario.times)} steps, {scenario.duration:.2f} s "
          f"(timed for the gains of {args.gains or args.serial or profile.gains_from}, held {profile.mount}); record "
          f"it with `vrscroll hil {args.scenario} --serial PORT`")
    return 0
