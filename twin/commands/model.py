"""`vrscroll model`: write the device MJCF, its scene and the firmware's protocol header from the spec,
or check the committed ones are current."""

from __future__ import annotations

from twin.device.mjcf import MJCF_PATH, SCENE_PATH, generated_files, write_mjcf
from twin.errors import UserError
from twin.link.firmware_header import HEADER_PATH, header, write_header


def add_arguments(p) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--write", action="store_true",
                   help=f"regenerate {MJCF_PATH.name} (the device), {SCENE_PATH.name} (device, floor, light) "
                        f"and {HEADER_PATH.name} (the firmware's protocol header) from the spec")
    g.add_argument("--check", action="store_true",
                   help="fail if the committed MJCF files or firmware header differ from the spec")


def run(args) -> int:
    if args.write:
        for path in write_mjcf():
            print(f"wrote {path}")
        print(f"wrote {write_header()}")
    elif args.check:
        for path, text in {**generated_files(), HEADER_PATH: header()}.items():
            if not path.is_file() or path.read_text() != text:
                raise UserError(f"{path} is out of date with the spec; run `vrscroll model --write`")
            print(f"{path} matches the spec")
    else:
        print(MJCF_PATH)
        print(f"open it with: python -m mujoco.viewer --mjcf {MJCF_PATH}")
    return 0
