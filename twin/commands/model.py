"""`vrscroll model`: write the device MJCF and its scene from the spec, or check the committed ones are current."""

from __future__ import annotations

from twin.cli import UserError
from twin.device.mjcf import MJCF_PATH, SCENE_PATH, generated_files, write_mjcf


def add_arguments(p) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--write", action="store_true",
                   help=f"regenerate {MJCF_PATH.name} (the device) and {SCENE_PATH.name} (device, floor, light) from the spec")
    g.add_argument("--check", action="store_true", help="fail if the committed MJCF files differ from the spec")


def run(args) -> int:
    if args.write:
        for path in write_mjcf():
            print(f"wrote {path}")
    elif args.check:
        for path, text in generated_files().items():
            if not path.is_file() or path.read_text() != text:
                raise UserError(f"{path} is out of date with the spec; run `vrscroll model --write`")
            print(f"{path} matches the spec")
    else:
        print(MJCF_PATH)
        print(f"open it with: python -m mujoco.viewer --mjcf {SCENE_PATH}")
    return 0
