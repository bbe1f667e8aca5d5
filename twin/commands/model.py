"""`vrscroll model`: write the device MJCF from the spec, or check the committed one is current."""

from __future__ import annotations

from twin.cli import UserError
from twin.device.mjcf import MJCF_PATH, mjcf, write_mjcf


def add_arguments(p) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--write", action="store_true", help=f"regenerate {MJCF_PATH.name} from the spec")
    g.add_argument("--check", action="store_true", help="fail if the committed MJCF differs from the spec")


def run(args) -> int:
    if args.write:
        print(f"wrote {write_mjcf()}")
    elif args.check:
        if MJCF_PATH.read_text() != mjcf():
            raise UserError(f"{MJCF_PATH} is out of date with the spec; run `vrscroll model --write`")
        print(f"{MJCF_PATH} matches the spec")
    else:
        print(MJCF_PATH)
        print(f"open it with: python -m mujoco.viewer --mjcf {MJCF_PATH}")
    return 0
