"""`vrscroll view RUN`: a HIL run's device and twin side by side in MuJoCo's viewer, replayed from its traces."""

from __future__ import annotations

from twin.commands.options import add_device_option, profile_line, profile_of
from twin.errors import UserError
from twin.formats.run import read_run
from viz.viewer import display_missing, view_run


def add_arguments(p) -> None:
    p.add_argument("run", metavar="RUN", help="HIL run folder (vrscroll hil --out)")
    add_device_option(p)


def run(args) -> int:
    profile = profile_of(args)
    recorded = read_run(args.run, profile.spec, incomplete=True)
    missing = display_missing()
    if missing:
        raise UserError(missing)
    print(profile_line(profile))
    print(view_run(recorded, profile.spec))
    return 0
