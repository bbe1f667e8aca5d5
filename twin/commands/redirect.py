"""`vrscroll redirect`: the pen redirection field of an approximation, and redirected pen samples.

Input: an approximation result (`vrscroll approximate --json FILE`); its target is the
shape or mesh named in it unless --shape/--mesh say otherwise. Prints how much of the
device's touch surface the redirection keeps within the perception thresholds
(models/perception/perception.toml). With a pen file (CSV, one sample per row:
x_mm,y_mm,z_mm,qw,qx,qy,qz, optional device_x_mm..device_qz and any other columns),
writes the redirected samples beside it (or to --out). --strict exits 1 when any part of
the surface is over a threshold (the samples are still written). The work: twin.morphpatch.pen_redirection.
"""

from __future__ import annotations

from twin.commands.options import add_json, add_target, output_file, within, write_json
from twin.device.spec import load_spec
from twin.formats.pen import read_pen_samples
from twin.morphpatch.pen_redirection import approximation_target, field_summary, redirect_pens
from twin.morphpatch.redirection import PADDING, SIGMA
from twin.morphpatch.shapes import shape_names
from viz.scene import render_redirection


def add_arguments(p) -> None:
    p.add_argument("approximation", metavar="APPROX.json", help="an approximation result (vrscroll approximate --json)")
    p.add_argument("pens", metavar="PENS.csv", nargs="?", help="pen samples to redirect (see docs/redirection-perception.md)")
    add_target(p, shape_names(), required=False, role="the target (default: the one APPROX.json names)", start=False)
    p.add_argument("--out", metavar="FILE", type=output_file, help="redirected samples (default PENS_redirected.csv)")
    p.add_argument("--sigma-mm", type=within(0, 100, "mm"), default=SIGMA * 1e3, help=f"Gaussian blur, mm (default {SIGMA * 1e3:g})")
    p.add_argument("--padding-mm", type=within(0, 200, "mm"), default=PADDING * 1e3,
                   help=f"field beyond the device's edges, mm (default {PADDING * 1e3:g})")
    p.add_argument("--png", metavar="FILE", type=output_file, help="picture of the offsets over the device")
    add_json(p, "the summary")
    p.add_argument("--strict", action="store_true", help="exit 1 if any of the surface is over a threshold")


def run(args) -> int:
    spec = load_spec()
    approx, name, mesh = approximation_target(args.approximation, spec, args.shape, args.mesh)
    pens = read_pen_samples(args.pens) if args.pens else None  # bad files fail before the long part
    say = (lambda line: print(line, flush=True))
    field, summary = field_summary(spec, approx, name, mesh, args.sigma_mm, args.padding_mm, say)
    if pens:
        summary.update(redirect_pens(field, pens, args.pens, args.out, say))
    if args.png:
        render_redirection(mesh, field, args.png, title=f"{name}: pen redirection, blur {args.sigma_mm:g} mm")
        summary["png"] = args.png
        print(f"picture: {args.png}")
    write_json(args.json, summary)
    over = summary["share_within"] < 1.0
    if over:
        print(f"warning: {1 - summary['share_within']:.1%} of the touch surface is redirected beyond the perception "
              "thresholds" + ("" if args.strict else " (--strict makes this an error)"))
    return 1 if over and args.strict else 0
