"""`vrscroll play`: synthetic VR sessions over the evaluation shapes, played against the live service.

With `--url` it plays against a running `vrscroll serve`. Without it, it starts its own:
an emulated device (`vrscroll emulate`'s emulator on a pseudo-terminal) and `vrscroll serve
--serial` on it, on a free loopback port (`--no-device`: the service morphs the twin alone).
The sessions are described in twin/live/player.py and docs/live.md. Exit status 0 when
every shape locked, morphed and had every pen sample redirected; 1 otherwise.
"""

from __future__ import annotations

import asyncio
import contextlib
import tempfile
from pathlib import Path

from websockets.exceptions import WebSocketException

from twin.commands.options import add_json, comma_list, within, write_json
from twin.device.spec import load_spec
from twin.errors import UserError
from twin.link.emulator_process import EmulatorProcess
from twin.live.player import all_played, play, session_line
from twin.live.process import ServiceProcess
from twin.morphpatch.approximation import VARIANTS
from twin.morphpatch.shapes import shape_names


def add_arguments(p) -> None:
    p.add_argument("--url", help="a running service (ws://host:port); default: start an emulator and a service")
    p.add_argument("--token", help="the service's token, if it needs one")
    p.add_argument("--no-device", action="store_true", help="without --url: the service morphs the twin alone")
    p.add_argument("--variant", choices=VARIANTS, default="full", help="without --url: approximation variant")
    p.add_argument("--shapes", type=comma_list(shape_names()), default=shape_names(), metavar="S1,S2,...",
                   help="comma-separated shapes (default all eight evaluation shapes)")
    p.add_argument("--attempts", type=within(1, 100, whole=True), default=4, help="approaches per shape until one morphs (default 4)")
    p.add_argument("--seed", type=int, default=0, help="seed of the starts after each shape's own (default 0)")
    add_json(p, "every session's record")


def _play(args, spec, shapes) -> list[dict]:
    """Start the emulator and the service unless --url, then play every shape; the records."""
    with contextlib.ExitStack() as stack:
        url = args.url
        if url is None:
            tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="vrscroll-play-")))
            serve_args = ["--variant", args.variant]
            if not args.no_device:
                emulator = stack.enter_context(EmulatorProcess(tmp / "emulator.jsonl", "--zeroed"))
                serve_args += ["--serial", emulator.port, "--log", str(tmp / "session.jsonl")]
                print(f"emulator on {emulator.port}", flush=True)
            service = stack.enter_context(ServiceProcess(*serve_args, stderr_path=tmp / "serve.stderr"))
            url = service.url
            print(service.banner.strip(), flush=True)
        return asyncio.run(play(url, spec, shapes, args.token, args.attempts, args.seed,
                                on_record=lambda r: print(session_line(r), flush=True)))


def run(args) -> int:
    shapes = args.shapes  # checked by --shapes' own type
    try:
        records = _play(args, load_spec(), shapes)
    except (RuntimeError, OSError, WebSocketException) as exc:  # LiveError, a process that did not start, a bad URL
        raise UserError(str(exc)) from None
    write_json(args.json, records)
    ok = all_played(records)
    print(f"{sum(r['morphed'] for r in records)}/{len(records)} shapes morphed; "
          + ("every pen sample redirected" if ok else "NOT every shape morphed with every pen sample redirected"))
    return 0 if ok else 1
