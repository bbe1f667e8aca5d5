"""`vrscroll view RUN`: a HIL run's device and twin side by side, replayed from its traces: in MuJoCo's viewer
where there is a display, else (or with --out) as a video and a contact sheet rendered off-screen; --rerun
writes a Rerun recording of it."""

from __future__ import annotations

from pathlib import Path

from twin.commands.options import add_device_option, add_rerun, opened, output_file
from twin.formats.profile import profile_line
from twin.formats.run import read_run
from viz.viewer import show_run


def add_arguments(p) -> None:
    p.add_argument("run", metavar="RUN", help="HIL run folder (vrscroll hil --out)")
    p.add_argument("--out", metavar="STEM", type=output_file,
                   help="write STEM.mp4 and STEM.png instead of opening the viewer (without a display: RUN/view)")
    add_rerun(p)
    add_device_option(p)


def run(args) -> int:
    profile, spec = opened(args, say=False)  # said once the run reads
    recorded = read_run(args.run, spec, incomplete=True)
    print(profile_line(profile))
    if args.rerun:
        from viz.rerun_log import log_run

        print(log_run(args.rerun, spec, recorded))
    if args.rerun and not args.out:
        return 0
    print(show_run(recorded, spec, args.out or Path(args.run) / "view", files=bool(args.out),
                   say=lambda line: print(line, flush=True)))
    return 0
