"""`vrscroll model`: write the device MJCF, its scene and the firmware's generated headers from the spec,
or check the committed ones are current."""

from __future__ import annotations

from twin.device.mjcf import MJCF_PATH, SCENE_PATH, generated_files, write_mjcf
from twin.errors import UserError
from twin.link.firmware_header import HEADER_PATH, LAYOUT_PATH, generated_headers, write_headers


def add_arguments(p) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--write", action="store_true",
                   help=f"regenerate {MJCF_PATH.name} (the device), {SCENE_PATH.name} (device, floor, light) "
                        f"and {HEADER_PATH.name}, {LAYOUT_PATH.name} (the firmware's protocol header, its struct layout "
                        f"checks) from the spec and the host's mirrors")
    g.add_argument("--check", action="store_true",
                   help="fail if the committed MJCF files or firmware headers differ from the spec")


def run(args) -> int:
    if args.write:
        for path in write_mjcf():
            print(f"wrote {path}")
        for path in write_headers():
            print(f"wrote {path}")
    elif args.check:
        for path, text in {**generated_files(), **generated_headers()}.items():
            if not path.is_file() or path.read_text() != text:
                raise UserError(f"{path} is out of date with the spec; run `vrscroll model --write`")
            print(f"{path} matches the spec")
    else:
        print(MJCF_PATH)
        print(f"open it with: python -m mujoco.viewer --mjcf {MJCF_PATH}")
    return 0
