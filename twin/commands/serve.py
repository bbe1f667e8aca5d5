"""`vrscroll serve`: the live service for VR applications (docs/live.md).

On the loopback address by default. `--device` picks the device profile whose twin approximates,
gates and (without a device) morphs. `--serial` attaches the device (a serial port, or the
emulator's pty); without it a lock morphs the twin alone. `--shape`/`--mesh` gives the
first target (a client may send another). Serving beyond loopback needs `--allow-remote`
and a token (`--token`, or the VRSCROLL_TOKEN environment variable) that every client presents.
"""

from __future__ import annotations

import asyncio
import os
import secrets
import threading
import time

from twin.commands.interrupts import stop_signals_call
from twin.commands.options import (
    add_device_option,
    add_mount,
    add_rerun,
    add_serial,
    add_target,
    add_tolerance_deg,
    profile_line,
    profile_of,
)
from twin.errors import UserError
from twin.link.serial_link import LinkError
from twin.live.messages import DEFAULT_LISTEN_PORT
from twin.live.morph import DeviceMorpher, TwinMorpher
from twin.live.service import LOOPBACK, LiveService, ServiceConfig
from twin.morphpatch.approximation import VARIANTS
from twin.morphpatch.shapes import load_mesh, shape_names


def add_arguments(p) -> None:
    add_serial(p, required=False, what="the device (without it a lock morphs the twin alone)")
    add_target(p, shape_names(), required=False, role="the first target", start=False)
    p.add_argument("--variant", choices=VARIANTS, default="full", help="approximation variant (default full)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default the loopback 127.0.0.1)")
    p.add_argument("--listen", type=int, default=DEFAULT_LISTEN_PORT,
                   help="TCP (control) and UDP (pose, pen) port number; 0 picks a free one (default %(default)s)")
    p.add_argument("--allow-remote", action="store_true", help="allow --host beyond loopback (needs a token)")
    p.add_argument("--token", default=os.environ.get("VRSCROLL_TOKEN"),
                   help="token every client must present (default $VRSCROLL_TOKEN; generated and printed when "
                   "--allow-remote is given without one)")
    p.add_argument("--log", default="vrscroll-live.jsonl", help="serial session log with --serial (default %(default)s)")
    add_rerun(p)
    add_device_option(p)
    add_mount(p)
    add_tolerance_deg(p)


def run(args) -> int:
    if not 0 <= args.listen <= 65535:
        raise UserError(f"--listen {args.listen}: a port number, 0 (any free one) to 65535")
    profile = profile_of(args)
    spec = profile.spec
    print(profile_line(profile), flush=True)
    token = args.token
    if args.allow_remote and not token and args.host not in LOOPBACK:
        token = secrets.token_urlsafe(24)
        print(f"token (give it to every client): {token}", flush=True)
    mesh = None
    if args.mesh:
        loaded = load_mesh(args.mesh)
        mesh = (loaded.vertices, loaded.faces)
    morpher = (DeviceMorpher(spec, args.serial, args.log, args.tolerance_deg, hinges=profile.hinges,
                             mount=profile.mount) if args.serial
               else TwinMorpher(spec, profile.gains, hinges=profile.hinges, mount=profile.mount))
    config = ServiceConfig(spec, morpher, host=args.host, listen=args.listen, token=token,
                           allow_remote=args.allow_remote, variant=args.variant, shape=args.shape, mesh=mesh,
                           profile=profile.label)
    service = LiveService(config)
    recording = _recording(args, spec, morpher)

    host = f"[{args.host}]" if ":" in args.host else args.host  # an IPv6 address in a URL

    def ready(port):
        print(f"vrscroll serve: listening on ws://{host}:{port} (control) and udp {host}:{port} "
              f"(pose, pen); device: {morpher.name}; target: {service.target['name'] if service.target else 'none'}; "
              f"variant {args.variant}" + ("; token required" if token else ""), flush=True)

    async def main():
        stop_signals_call(asyncio.get_running_loop(), service.stop)  # its device e-stopped as the service ends
        await service.run(ready)

    try:
        asyncio.run(main())
    except LinkError as exc:
        raise UserError(f"device: {exc}") from None
    except OSError as exc:
        raise UserError(f"cannot serve on {args.host}:{args.listen}: {exc}") from None
    finally:
        if recording is not None:
            recording.close()
            print(f"vrscroll serve: rerun recording {args.rerun} (every morph on the service's clock)", flush=True)
    return 0


def _recording(args, spec, morpher):
    """With --rerun, a recording every morph is added to, at its time since the service started (s)."""
    if not args.rerun:
        return None
    from viz.rerun_log import RerunRecording, add_move

    recording = RerunRecording(args.rerun, spec)
    started = time.monotonic()
    lock = threading.Lock()  # morphs run in a worker thread

    def on_move(telemetry, prediction):
        with lock:
            add_move(recording, time.monotonic() - started, telemetry, prediction)

    morpher.on_move = on_move
    return recording
