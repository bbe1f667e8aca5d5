"""The --device option of every command that simulates, gates or talks to hardware: which device
profile it uses (twin.formats.profile), remembered as the default for the commands that follow."""

from __future__ import annotations

from twin.device.profile import set_default
from twin.formats.profile import Profile, select_profile


def add_device_option(p) -> None:
    p.add_argument("--device", metavar="NAME",
                   help="device profile to use, and to remember as the default (`vrscroll device list`); "
                        "default: the one selected last, else the spec's defaults")


def profile_of(args) -> Profile:
    """The profile args.device names (then remembered as the default), or the selected one, or the spec's
    defaults. ValueError (one line) for a profile that is not there or is damaged."""
    profile = select_profile(args.device)
    if args.device:
        set_default(args.device)
    return profile


def profile_line(profile: Profile) -> str:
    """The line every report starts with."""
    where = f" ({profile.folder})" if profile.folder else " (models/vrscroll/spec.toml)"
    return f"device profile: {profile.label}{where}"
