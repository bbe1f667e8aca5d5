"""`vrscroll`: the command line. Each command lives in its own module with
`add_arguments(parser)` and `run(args) -> int`; this file only wires them up.

Errors the user can fix (bad target, bad mesh, bad port) are printed as one
line on stderr with exit status 2, never as a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import select
import sys

from twin import gl_problem
from twin.commands.interrupts import interrupt_on_stop_signals
from twin.commands.options import HelpFormatter, join_negative_values, refuse_renamed
from twin.errors import UserError

# command name -> (module, one-line help)
COMMANDS = {
    "demo": ("twin.commands.demo", "approximate a shape, validate and simulate the morph on the twin, write a picture"),
    "simulate": ("twin.commands.simulate", "move the twin's hinges to targets and report the step response"),
    "model": ("twin.commands.model", "write or check the device MJCF generated from the spec"),
    "approximate": ("twin.commands.approximate", "approximate a target shape or mesh from a start pose; prints JSON"),
    "cbs": ("twin.commands.cbs", "collision-based simulation baseline in MuJoCo; prints JSON like approximate"),
    "evaluate": ("twin.commands.evaluate", "the paper's Table 1: CBS, no_hcevf, full and ours (refined), same starts"),
    "sweep": ("twin.commands.sweep", "design sweeps: designs x shapes x starts x methods x plants, locally or on Ray"),
    "emulate": ("twin.commands.emulate", "run a device emulator on a pseudo-terminal (prints its port)"),
    "mirror": ("twin.commands.mirror", "gate a target on the twin, send it to the device, watch it follow"),
    "status": ("twin.commands.status", "the device's firmware version, state, faults and hinge angles"),
    "bringup": ("twin.commands.bringup", "bring up a new board: pulse each motor, check its encoder, name and "
                                         "correct wiring mistakes, confirm the zero, a first gated move"),
    "zero": ("twin.commands.zero", "confirm the device's flat pose as its zero (after every start it refuses to move until then)"),
    "tune": ("twin.commands.tune", "tune PID gains per hinge on the twin (robust to tolerances); --serial confirms"),
    "hil": ("twin.commands.hil", "play a scenario on the device and the twin; traces, metrics, plots, report"),
    "scenario": ("twin.commands.scenario", "write the calibration scenario for the device's gains, to record with hil"),
    "calibrate": ("twin.commands.calibrate", "fit the twin's motor and gearbox parameters to recorded HIL runs, or (--serial) to the device's own experiments"),
    "holding": ("twin.commands.holding", "what the device does when its drive is cut: releases under gravity, the "
                                         "gearboxes' back-driven efficiency fitted, the twin's prediction"),
    "redirect": ("twin.commands.redirect", "pen redirection field of an approximation; redirect pen samples (CSV)"),
    "psychometric": ("twin.commands.psychometric", "psychometric fit of redirection trials: CDT and DT with CIs, plot"),
    "serve": ("twin.commands.serve", "the live service for VR applications: pose in, approximation out, lock, pen"),
    "play": ("twin.commands.play", "play synthetic VR sessions over the evaluation shapes against the live service"),
    "device": ("twin.commands.device", "list, show, select or create device profiles (calibrated spec and gains)"),
    "view": ("twin.commands.view", "replay a HIL run's device and twin side by side: MuJoCo's viewer, or a video "
                                   "and a contact sheet without a display"),
    "cache": ("twin.commands.cache", "show what the cache folder holds (fields, firmware builds), or clear it"),
    "compare": ("twin.commands.compare", "HIL runs of one scenario side by side: per hinge RMSE, settle, overshoot, plot"),
}


def _stdout_gone() -> bool:
    """Whether standard output is a pipe whose reader has closed it (poll reports an error on its write end)."""
    poll = select.poll()
    poll.register(sys.stdout.fileno(), select.POLLOUT)
    return any(events & select.POLLERR for _, events in poll.poll(0))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="vrscroll", description="VRScroll physics twin and MorphPatch tools.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    argv = sys.argv[1:] if argv is None else list(argv)
    chosen = next((a for a in argv if not a.startswith("-")), None)
    problem = gl_problem() if chosen in COMMANDS else None  # every command imports MuJoCo, which would fail first
    if problem:
        print(f"vrscroll {chosen}: error: {problem}", file=sys.stderr)
        return 2
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text, formatter_class=HelpFormatter)
        p.set_defaults(_module=module)
        if name == chosen:  # only the command being run is imported: fast start, and one broken command breaks only itself
            importlib.import_module(module).add_arguments(p)
            refuse_renamed(p)
            argv = join_negative_values(p, argv)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a usage error (2, already printed): the status, as for any command
        return exc.code
    interrupt_on_stop_signals()  # SIGTERM, SIGHUP, SIGQUIT as Ctrl-C: a session with the device e-stops it
    try:
        return importlib.import_module(args._module).run(args) or 0
    except BrokenPipeError as exc:  # the reader went away (`vrscroll status | head`): end quietly, as a shell tool does
        if not _stdout_gone():  # another pipe (a socket the command used): an error like any other
            _say(f"vrscroll {args.command}: error: {exc}")
            return 2
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error when Python flushes it
        return 141  # 128 + SIGPIPE, what the shell reports for a command that a closed pipe ended
    except (UserError, ValueError, FileNotFoundError, OSError) as exc:
        _say(f"vrscroll {args.command}: error: {exc}")
        return 2
    except KeyboardInterrupt:
        _say(f"vrscroll {args.command}: interrupted")
        return 130


def _say(line: str) -> None:
    """A line on stderr, if there is still one to write to (a closed terminal is why some commands end)."""
    try:
        print(line, file=sys.stderr)
    except OSError:
        pass


if __name__ == "__main__":
    sys.exit(main())
