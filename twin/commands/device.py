"""`vrscroll device`: list, show, select or create device profiles (docs/tuning-hil-calibration.md,
"Device profiles"; the folder: docs/formats.md "Device profile")."""

from __future__ import annotations

from twin.commands.options import add_mount
from twin.device.profile import default_name, profile_names, profiles_dir, set_default
from twin.formats.profile import create_profile, profile_lines, select_profile
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
    print("\n".join(profile_lines(select_profile(args.name))))
    return 0
