"""`vrscroll device`: list, show, select or create device profiles (docs/tuning-hil-calibration.md,
"Device profiles"; the folder: docs/formats.md "Device profile")."""

from __future__ import annotations

import math

from twin.commands.options import add_mount, select_profile
from twin.device.profile import default_name, profile_names, profiles_dir, set_default
from twin.device.spec import SPEC_PATH, spec_sources
from twin.device.spec_toml import shown, shown_range, spec_units
from twin.formats.profile import create_profile
from twin.records.profile import NO_PROFILE


def add_arguments(p) -> None:
    p.add_argument("action", choices=("list", "show", "select", "create"), nargs="?", default="list",
                   help="list the profiles (default); show one (default: the selected); select one for the "
                        "commands that follow (`select none`: the spec's defaults); create one from the spec's "
                        "defaults")
    p.add_argument("name", nargs="?", help="the profile's name")
    add_mount(p)


def run(args) -> int:
    if args.mount and args.action != "create":
        raise ValueError(f"--mount is for `vrscroll device create`; give it to a command that runs the device "
                         f"(simulate, hil, mirror, ...: it records it in the profile), not to `device {args.action}`")
    if args.action == "list":
        chosen = default_name()
        names = profile_names()
        print(f"device profiles in {profiles_dir()}:" + ("" if names else " none"))
        for n in names:
            print(("* " if n == chosen else "  ") + n)
        print(f"selected: {chosen or NO_PROFILE}")
        return 0
    if args.action in ("select", "create") and not args.name:
        raise ValueError(f"vrscroll device {args.action} NAME: give the profile's name")
    if args.action == "select":
        name = None if args.name == "none" else args.name
        if name:
            select_profile(name)  # there, and readable
        set_default(name)
        print(f"selected: {name or NO_PROFILE}")
        return 0
    if args.action == "create":
        print(f"created {create_profile(args.name, args.mount)} (the spec's defaults, mount: {args.mount or 'hanging'};"
              f" `vrscroll calibrate RUN --device {args.name}` calibrates it)")
        return 0
    profile = select_profile(args.name)
    print(f"device profile: {profile.label}" + (f" ({profile.folder})" if profile.folder else ""))
    print(f"mount: {profile.mount}")
    print(f"gains: {profile.gains_from}")
    for k, g in enumerate(profile.gains):
        print(f"  hinge {k}: kp {g.kp:g} ki {g.ki:g} kd {g.kd:g}")
    sources = profile.sources
    units = spec_units(SPEC_PATH)  # each value in the unit the spec file gives it in
    if profile.calibration:
        print("calibration from " + ", ".join(profile.calibration.runs) + ":")
        for p, e in profile.calibration.parameters.items():
            u = units.get(p, "")
            print(f"  {p:<14} {shown(e.value, u, '.6g')}  (prior {shown(e.prior, u, '.6g')}; interval "
                  f"{shown_range(e.low, e.high, u, '.6g')}; "
                  f"{'identifiable' if e.identifiable else 'NOT identifiable'}): {e.note}")
        for k, row in enumerate(profile.calibration.hinges or []):
            print(f"  hinge {k}'s own, x the shared value (95 % interval): " + "; ".join(
                f"{p} x{e.value / e.prior:.3f} (x{e.low / e.prior:.2f} .. x{e.high / e.prior:.2f}"
                f"{', identifiable' if e.identifiable else ''})" for p, e in row.items()))
    else:
        print("not calibrated")
    for p, e in (profile.holding.parameters if profile.holding else {}).items():
        u = units.get(p, "")
        print(f"holding (vrscroll holding, {profile.holding.releases} release(s) on {profile.holding.port}): "
              f"{p} {shown(e.value, u, '.3g')} (prior {shown(e.prior, u, '.3g')}; interval "
              f"{shown_range(e.low, e.high, u, '.3g')}; {'identifiable' if e.identifiable else 'NOT identifiable'})")
    defaults = spec_sources()
    changed = [f for f, s in sources.items() if s != defaults.get(f)]
    print("spec values not the spec's defaults: " + (", ".join(
        f"{f} = {shown(getattr(profile.spec, f), units.get(f, ''), '.6g')} ({sources[f]})" for f in changed)
        if changed else "none"))
    print(f"hinge limit {math.degrees(profile.spec.hinge_limit):g} deg, {profile.spec.n_hinges} hinges")
    return 0
