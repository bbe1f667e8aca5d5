"""`vrscroll redirect`: the pen redirection field of an approximation, and redirected pen samples.

Input: an approximation result (`vrscroll approximate --json FILE`); its target is the
shape or mesh named in it unless --shape/--mesh say otherwise. Prints how much of the
device's touch surface the redirection keeps within the perception thresholds
(models/perception/perception.toml). With a pen file (CSV, one sample per row:
x_mm,y_mm,z_mm,qw,qx,qy,qz, optional device_x_mm..device_qz and any other columns),
writes the redirected samples beside it (or to --out). --strict exits 1 when any part of
the surface is over a threshold (the samples are still written).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from twin.commands.options import add_json, add_target, output_file, within, write_json
from twin.device.spec import load_spec
from twin.errors import UserError
from twin.formats.pen import read_pen_samples, write_redirected
from twin.formats.target import read_approximation
from twin.morphpatch.fields import build_fields
from twin.morphpatch.redirection import PADDING, SIGMA, build_field, redirect, threshold_summary, within_samples
from twin.morphpatch.shapes import load_mesh, load_shape, shape_names
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


def _load(args, spec):
    """(approximation, target name, mesh) from APPROX.json and --shape/--mesh."""
    approx = read_approximation(args.approximation, spec)
    name = args.shape or args.mesh or approx.target
    if not name:
        raise UserError(f"{args.approximation} names no target: give --shape or --mesh")
    mesh = load_shape(name) if name in shape_names() else load_mesh(name)
    return approx, name, mesh


def run(args) -> int:
    spec = load_spec()
    approx, name, mesh = _load(args, spec)
    pens = read_pen_samples(args.pens) if args.pens else None  # bad files fail before the long part
    print(f"fields of {name} (cached after the first run) ...", flush=True)
    fields = build_fields(mesh)
    field = build_field(spec, approx.root_pose, approx.angles, approx.widths, mesh, fields,
                        sigma=args.sigma_mm / 1e3, padding=args.padding_mm / 1e3)
    summary = {"target": name, "sigma_mm": args.sigma_mm, "padding_mm": args.padding_mm,
               "build_time_ms": round(field.build_time * 1e3, 1), **threshold_summary(field)}
    print(f"redirection field built in {summary['build_time_ms']:.0f} ms: {summary['share_within']:.1%} of the "
          f"touch surface within {summary['position_threshold_mm']:g} mm / {summary['rotation_threshold_deg']:g} deg "
          f"(largest {summary['largest_offset_mm']:.1f} mm, {summary['largest_rotation_deg']:.1f} deg; "
          f"no target along the normal on {summary['no_target_share']:.1%})")
    if pens:
        result = redirect(field, pens.position, pens.orientation, pens.device_pose)
        within = within_samples(result)
        out = Path(args.out) if args.out else Path(args.pens).with_name(Path(args.pens).stem + "_redirected.csv")
        write_redirected(out, pens, result, within)
        summary.update({"samples": len(pens.position), "samples_within": int(within.sum()), "out": str(out)})
        print(f"{len(pens.position)} pen samples redirected, {within.mean():.1%} within the thresholds "
              f"(largest {result.offset.max() * 1e3:.1f} mm, {np.degrees(result.angle.max()):.1f} deg): {out}")
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
