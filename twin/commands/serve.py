"""`vrscroll serve`: the live service for VR applications (docs/live.md).

On the loopback address by default. `--device` picks the device profile whose twin approximates,
gates and (without a device) morphs. `--serial` attaches the device (a serial port, or the
emulator's pty); without it a lock morphs the twin alone. `--shape`/`--mesh` gives the
first target (a client may send another). Serving beyond loopback needs `--allow-remote`
and a token (`--token`, or the VRSCROLL_TOKEN environment variable) that every client presents. The service: twin.live.serving.
"""

from __future__ import annotations

import os
import secrets

from twin.commands.interrupts import stop_signals_call
from twin.commands.options import add_device_option, add_mount, add_rerun, add_serial, add_target, add_tolerance_deg
from twin.errors import UserError
from twin.formats.profile import chosen_profile, profile_line
from twin.live.messages import DEFAULT_LISTEN_PORT
from twin.live.service import LOOPBACK
from twin.live.serving import live_service, serve_until_stopped
from twin.morphpatch.approximation import VARIANTS
from twin.morphpatch.shapes import shape_names


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
    profile = chosen_profile(args.device, args.mount)
    print(profile_line(profile), flush=True)
    token = args.token
    if args.allow_remote and not token and args.host not in LOOPBACK:
        token = secrets.token_urlsafe(24)
        print(f"token (give it to every client): {token}", flush=True)
    service = live_service(profile, args.serial, args.log, args.tolerance_deg, args.host, args.listen, token,
                           args.allow_remote, args.variant, args.shape, args.mesh)
    recording = None
    if args.rerun:
        from viz.rerun_log import morph_recording

        recording = morph_recording(args.rerun, profile.spec, service.morpher)
    try:
        serve_until_stopped(service, stop_signals_call, lambda line: print(line, flush=True))
    finally:
        if recording is not None:
            recording.close()
            print(f"vrscroll serve: rerun recording {args.rerun} (every morph on the service's clock)", flush=True)
    return 0
