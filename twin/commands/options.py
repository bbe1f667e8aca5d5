"""The options the commands share, declared once so that every command speaks one dialect:

- `--serial PORT`: the device's serial port (or a pyserial URL); `--listen PORT` is only ever a network port;
- `--json FILE`: write the command's result as JSON to FILE, `-` for standard output (then instead of the
  human-readable report);
- units in option names (`--tolerance-deg`, `--tolerance-pct`, `--sigma-mm`); lists are comma-separated
  (`--shapes cube,cylinder`, `--angles 0,10,...`);
- `--device NAME`: the device profile, remembered as the default; `--mount hanging|flat|stand`: how the device is
  held, recorded in that profile (the twin is held the same way);
- `--shape S | --mesh FILE` and `--start X,Y,Z,ROLL,PITCH,YAW`: the target and the anchor's start.

What the options open lives below the commands, where tests and other layers reach it too: the profile
(twin.formats.profile.chosen_profile, its line profile_line), its twin (twin.sim.twin.profile_twin), the device
(twin.hil.device_gains.device_session, a link failure as one line with link_errors); `opened` here reads --device
and --mount and prints the profile's line.

An old spelling (`--port`, `--tolerance`, `--json` without a file) is refused with a message naming the new.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

from twin.device.mount import MOUNTS
from twin.formats.profile import chosen_profile, profile_line
from twin.paths import replacing

# old spelling -> new, refused wherever the new one is an option of the command
RENAMED = {"--port": "--serial", "--tolerance": "--tolerance-pct", "--max-time": "--max-time-s",
           "--duration": "--duration-s", "--settle-limit": "--settle-limit-s", "--jam-after": "--jam-after-s",
           "--drop-after": "--drop-after-s", "--pack-voltage": "--pack-voltage-v"}  # old spelling -> the new


class _Renamed(argparse.Action):
    """An old spelling: a usage error naming the new one."""

    def __init__(self, option_strings, dest, new: str, **kw):
        super().__init__(option_strings, dest, nargs="?", help=argparse.SUPPRESS, **kw)
        self.new = new

    def __call__(self, parser, namespace, values, option_string=None):
        parser.error(f"{option_string} is now {self.new} (see `vrscroll {parser.prog.split()[-1]} --help`)")


def refuse_renamed(p: argparse.ArgumentParser) -> None:
    """Add each old spelling whose new one `p` has, as an option that refuses itself naming the new."""
    have = set(p._option_string_actions)
    for old, new in RENAMED.items():
        if new in have and old not in have:
            add_refused(p, old, new)


def add_refused(p, old: str, new: str) -> None:
    """An option `old` that is refused with a message naming `new` (an option, or a command)."""
    p.add_argument(old, action=_Renamed, new=new, dest=f"_refused{old}")


def within(low: float, high: float, unit: str = "", whole: bool = False):
    """An argparse type: a finite number (a whole one when `whole`) from low to high, in `unit`; anything else
    (NaN, 1e9 s, a negative count) is a usage error naming the range."""
    def parse(text: str):
        try:
            value = int(text) if whole else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a {'whole ' if whole else ''}number") from None
        if not (math.isfinite(value) and low <= value <= high):
            raise argparse.ArgumentTypeError(f"{text} is not within {low:g} to {high:g}{' ' + unit if unit else ''}")
        return value
    return parse


def output_file(text: str) -> str:
    """An argparse type for a file the command writes: not a folder (a picture "written" into a folder once
    wrote nothing), in a folder that exists; `-` passes (standard output, where an option takes it)."""
    path = Path(text)
    if text != "-" and path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder: give a file name in it")
    if text != "-" and not path.resolve().parent.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: the folder {path.parent} does not exist")
    return text


class _JsonFile(argparse.Action):
    """--json FILE; a bare --json (the old flag) is refused naming `--json -`."""

    def __call__(self, parser, namespace, values, option_string=None):
        if values is None:
            parser.error("--json now takes a file: --json FILE writes it there, --json - prints it on standard output")
        setattr(namespace, self.dest, values)


class HelpFormatter(argparse.HelpFormatter):
    """argparse's help, with --json shown as it is taken (FILE, not an optional [FILE]: a bare --json is refused)."""

    def _format_args(self, action, default_metavar):
        if isinstance(action, _JsonFile):
            return action.metavar
        return super()._format_args(action, default_metavar)


_NEGATIVE_LIST = re.compile(r"-\d[\d.]*(,-?\d[\d.]*)*")


def join_negative_values(parser, argv: list[str]) -> list[str]:
    """argv with an option that takes a value and is followed by a negative number or list (`--from -10,0,5`)
    joined into one word (`--from=-10,0,5`): argparse would read `-10,0,5` as an unknown option."""
    out = []
    for word in argv:
        action = parser._option_string_actions.get(out[-1]) if out else None  # argparse has no public lookup
        if action is not None and action.nargs is None and _NEGATIVE_LIST.fullmatch(word):
            out[-1] = f"{out[-1]}={word}"
        else:
            out.append(word)
    return out


def add_json(p, what: str) -> None:
    """--json FILE|-: `what` (e.g. "the report") as JSON."""
    p.add_argument("--json", metavar="FILE", nargs="?", action=_JsonFile, type=output_file,
                   help=f"write {what} as JSON to FILE; - prints it on standard output instead of the report")


MAX_THREADS = 256  # MuJoCo thread-pool threads a command may ask for


def add_threads(p) -> None:
    """--threads N: the batch twin's threads on MuJoCo's thread pool (0: every core)."""
    p.add_argument("--threads", type=within(0, MAX_THREADS, whole=True), default=0,
                   help="simulation threads (default: all cores)")


def add_slowmo(p, min_played_s: float) -> None:
    """--slowmo FACTOR: `--view`'s move played (or its video) FACTOR times slower than real time; by default one
    shorter than min_played_s (viz.viewer.MIN_PLAYED_S) is slowed to last that long."""
    p.add_argument("--slowmo", metavar="FACTOR", type=within(1, 1000),
                   help=f"with --view: play the move FACTOR times slower than real time (default: a move shorter "
                        f"than {min_played_s:g} s slowed to last that long; 1: real time)")


def add_rerun(p) -> None:
    """--rerun FILE.rrd: a Rerun recording of what the command ran (viz.rerun_log; the `rerun` extra)."""
    p.add_argument("--rerun", metavar="FILE.rrd", type=output_file,
                   help="also write a Rerun recording (3-D device and, per hinge, target, twin, device, difference, "
                        "duty, current on one timeline); open it with `rerun FILE.rrd` (pip install '.[rerun]')")


def json_to_stdout(args) -> bool:
    """Whether the JSON replaces the human-readable report on standard output (--json -)."""
    return getattr(args, "json", None) == "-"


def _json_safe(value):
    """value with every NaN or infinite float as None (JSON's null: not defined, e.g. a move that did not
    settle); JSON has no NaN, and json.dumps would write one anyway."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def write_json(dest: str | None, doc) -> None:
    """The result as JSON to `dest` (a file, or - for standard output; NaN and infinities as null); nothing
    when dest is None."""
    if dest is None:
        return
    text = json.dumps(_json_safe(doc), indent=2, allow_nan=False) + "\n"
    if dest == "-":
        sys.stdout.write(text)
    else:
        with replacing(dest) as tmp:
            Path(tmp).write_text(text)


def add_serial(p, required: bool, what: str = "the device") -> None:
    p.add_argument("--serial", metavar="PORT", required=required,
                   help=f"{what}: a serial port (/dev/tty*, the pty `vrscroll emulate` prints) or a pyserial URL")


def add_tolerance_deg(p, default: float = 5.0) -> None:
    p.add_argument("--tolerance-deg", type=within(0.1, 180, "deg"), default=default, metavar="DEG",
                   help="e-stop when a hinge parts from the twin's prediction by more than this, deg "
                        "(default %(default)s)")


def comma_list(choices=None):
    """An argparse type: a comma-separated list, each item one of `choices` when given."""
    def parse(text: str) -> list[str]:
        items = [t.strip() for t in text.split(",") if t.strip()]
        if not items:
            raise argparse.ArgumentTypeError("expected a comma-separated list")
        bad = [t for t in items if choices is not None and t not in choices]
        if bad:
            raise argparse.ArgumentTypeError(f"{bad[0]!r} is not one of {', '.join(choices)}")
        return items
    return parse


def add_target(p, shapes, required: bool, role: str = "the target", start: bool = True) -> None:
    """--shape S | --mesh FILE (and --start): `role` says what the target is for this command."""
    target = p.add_mutually_exclusive_group(required=required)
    target.add_argument("--shape", choices=shapes, help=f"{role}: one of the evaluation shapes")
    target.add_argument("--mesh", metavar="FILE",
                        help=f"{role}: a watertight mesh file in metres (STL, OBJ, PLY, GLB, ...)")
    if start:
        p.add_argument("--start", metavar="X,Y,Z,ROLL,PITCH,YAW",
                       help="the anchor's start in the target's frame: x, y, z in mm, then roll, pitch, yaw in deg "
                            "(R = Rz(yaw) Ry(pitch) Rx(roll), fixed axes; the device's -z points at the target); default: the shape's start, or 40 mm out from the side of a mesh ours fits best, over its middle (docs/approximation.md, \"Starts\")")


def add_device_option(p) -> None:
    p.add_argument("--device", metavar="NAME",
                   help="device profile to use, and to remember as the default (`vrscroll device list`); "
                        "default: the one selected last, else the spec's defaults")


def add_mount(p) -> None:
    """--mount hanging|flat|stand: how the device is held (twin.device.mount), recorded in the profile."""
    p.add_argument("--mount", choices=MOUNTS,
                   help="how the device is held: hanging from its root flap, flat on a table, or on a stand "
                        "(docs/device.md \"Mounts\"); recorded in the device profile, so later commands hold the "
                        "twin the same way (default: the profile's, else hanging)")


def opened(args, say: bool = True):
    """A command's opening: (the profile --device and --mount choose (twin.formats.profile.chosen_profile), its
    spec), the profile's line printed first, unless the JSON takes standard output (--json -) or say is False (a
    command that prints it later). ValueError (one line) for a profile that is not there or is damaged."""
    profile = chosen_profile(args.device, getattr(args, "mount", None))
    if say and not json_to_stdout(args):
        print(profile_line(profile), flush=True)
    return profile, profile.spec
