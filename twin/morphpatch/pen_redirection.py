"""`vrscroll redirect`'s work: an approximation's target, the pen redirection field over it with the share of the
touch surface it keeps within the perception thresholds, and a pen file's samples redirected (deg, mm in the
summary and its lines)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from twin.errors import UserError
from twin.formats.pen import write_redirected
from twin.formats.target import read_approximation
from twin.morphpatch.fields import build_fields
from twin.morphpatch.redirection import build_field, redirect, threshold_summary, within_samples
from twin.morphpatch.shapes import load_mesh, load_shape, shape_names


def approximation_target(path: str, spec, shape: str | None = None, mesh: str | None = None):
    """(approximation, target name, mesh) from an approximation file and the target given instead (a shape or a
    mesh file; None: the one the file names). UserError where neither names one."""
    approx = read_approximation(path, spec)
    name = shape or mesh or approx.target
    if not name:
        raise UserError(f"{path} names no target: give --shape or --mesh")
    return approx, name, load_shape(name) if name in shape_names() else load_mesh(name)


def field_summary(spec, approx, name: str, mesh, sigma_mm: float, padding_mm: float, say=print):
    """(the redirection field over the approximation's pose on its target, its summary as JSON): the share of
    the touch surface within the thresholds, said in a line. say(line): progress and the outcome."""
    say(f"fields of {name} (cached after the first run) ...")
    field = build_field(spec, approx.root_pose, approx.angles, approx.widths, mesh, build_fields(mesh),
                        sigma=sigma_mm / 1e3, padding=padding_mm / 1e3)
    summary = {"target": name, "sigma_mm": sigma_mm, "padding_mm": padding_mm,
               "build_time_ms": round(field.build_time * 1e3, 1), **threshold_summary(field)}
    say(f"redirection field built in {summary['build_time_ms']:.0f} ms: {summary['share_within']:.1%} of the "
        f"touch surface within {summary['position_threshold_mm']:g} mm / {summary['rotation_threshold_deg']:g} deg "
        f"(largest {summary['largest_offset_mm']:.1f} mm, {summary['largest_rotation_deg']:.1f} deg; "
        f"no target along the normal on {summary['no_target_share']:.1%})")
    return field, summary


def redirect_pens(field, pens, pens_path: str, out: str | None, say=print) -> dict:
    """The pen samples (a PenSamples record, read from pens_path) redirected through the field and written to
    `out` (None: PENS_redirected.csv beside them); the summary's entries for them, said in a line."""
    result = redirect(field, pens.position, pens.orientation, pens.device_pose)
    within = within_samples(result)
    path = Path(out) if out else Path(pens_path).with_name(Path(pens_path).stem + "_redirected.csv")
    write_redirected(path, pens, result, within)
    say(f"{len(pens.position)} pen samples redirected, {within.mean():.1%} within the thresholds "
        f"(largest {result.offset.max() * 1e3:.1f} mm, {np.degrees(result.angle.max()):.1f} deg): {path}")
    return {"samples": len(pens.position), "samples_within": int(within.sum()), "out": str(path)}
