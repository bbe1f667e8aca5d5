"""Off-screen pyvista pictures of the device on a target.

Rendering is off-screen (pyvista.OFF_SCREEN); without a display VTK uses its EGL
window (twin/__init__.py sets VTK_DEFAULT_OPENGL_WINDOW), so no X warning is printed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyvista as pv
import trimesh

from twin.device.spec import DeviceSpec
from twin.morphpatch.redirection import within_flags
from twin.morphpatch.sampling import METRIC_SPACING, grid_layout, world_points
from twin.morphpatch.surface_metrics import INSIDE_TOLERANCE, point_distances
from twin.perception.thresholds import load_thresholds

pv.OFF_SCREEN = True


def _nice_ceiling(x: float) -> float:
    """The smallest of 1, 2 or 5 x 10^k at or above x (> 0)."""
    k = 10.0 ** np.floor(np.log10(x))
    return float(next(m * k for m in (1, 2, 5, 10) if m * k >= x - 1e-12))


def render_approximation(spec: DeviceSpec, mesh: trimesh.Trimesh, frames: np.ndarray, widths,
                         path: str | Path, title: str = "", notes=(), start_frames: np.ndarray | None = None,
                         window_size=(1200, 900), failed: str | None = None) -> Path:
    """Write a PNG of the target (grey) and the device's flaps coloured by signed distance to it (mm; below 0,
    red, inside the target; blue above it), the colour scale symmetric about 0 and running to the largest
    distance (rounded up to 1, 2 or 5 x 10^k, at least 0.5 mm) so the fit's own spread is seen, and where the
    flaps lie inside the target, how much and how deep, noted; `notes` (lines of text, e.g. hinge angles)
    lower left; where start_frames are given, the device where it started, as a black outline; where `failed`
    is given (what refused the pose, e.g. the gate's failed checks), FAILED and it in red, upper right.

    frames, start_frames: world flap frames (n_flaps, 4, 4), e.g. `twin.morphpatch.approximation.frames`; widths: m.
    """
    plotter = pv.Plotter(off_screen=True, window_size=window_size)
    plotter.add_mesh(pv.wrap(mesh), color="lightgrey", opacity=0.35, smooth_shading=True)
    grids = []
    for i, width in enumerate(widths):
        layout = grid_layout(spec, METRIC_SPACING, width)
        nu = len(np.unique(layout.u))
        points = world_points(frames, widths, layout, [i])[0]
        grid = pv.StructuredGrid(*(points[:, d].reshape(nu, -1, 1) for d in range(3)))
        # the grid's points run in Fortran order (u fastest); the layout's in C order (y fastest)
        grid["distance_mm"] = (point_distances(mesh, points) * 1e3).reshape(nu, -1).ravel(order="F")
        grids.append(grid)
        if start_frames is not None:
            start = world_points(start_frames, widths, layout, [i])[0]
            outline = pv.StructuredGrid(*(start[:, d].reshape(nu, -1, 1) for d in range(3))).extract_feature_edges()
            plotter.add_mesh(outline, color="black", line_width=2)
    distances = np.concatenate([g["distance_mm"] for g in grids])
    top = _nice_ceiling(max(0.5, float(np.abs(distances).max())))
    for i, grid in enumerate(grids):
        plotter.add_mesh(grid, scalars="distance_mm", cmap="RdBu", clim=(-top, top), show_edges=False,
                         scalar_bar_args={"title": "signed distance to target, mm (< 0: inside)"} if i == 0 else None,
                         show_scalar_bar=i == 0)
    inside = distances < -INSIDE_TOLERANCE * 1e3
    notes = [f"inside the target: {inside.mean():.0%} of the touch surface, up to {-distances.min():.1f} mm deep"
             if inside.any() else "inside the target: none of the touch surface", *notes]
    if title:
        plotter.add_text(title, font_size=10)
    if notes:
        plotter.add_text("\n".join(notes), position="lower_left", font_size=8)
    if failed:
        plotter.add_text(f"FAILED: {failed}", position="upper_right", font_size=14, color="red")
    plotter.camera_position = "iso"
    plotter.reset_camera()
    path = Path(path)
    plotter.screenshot(str(path))
    plotter.close()
    return path


def render_redirection(mesh: trimesh.Trimesh, field, path: str | Path, thresholds=None, title: str = "",
                       window_size=(1600, 800)) -> Path:
    """Write a PNG of the redirection over the device: |offset| (mm) left, rotation (deg) right.

    field: a `twin.morphpatch.redirection.RedirectionField`. Colours run from 0 to the perception
    threshold; nodes beyond it (or where no target was found) are red. The target is grey.
    """
    thresholds = thresholds or load_thresholds()
    points, _ = field.surface()
    dev = field.on_device
    rows, cols = np.flatnonzero(dev.any(axis=1)), np.flatnonzero(dev.any(axis=0))
    sub = np.ix_(rows, cols)
    grid = pv.StructuredGrid(*(points[sub][..., d][..., None] for d in range(3)))
    found = field.hit[sub]
    panels = (("offset_mm", field.offset_size()[sub] * 1e3, thresholds.position * 1e3, "positional offset, mm"),
              ("rotation_deg", np.degrees(field.rotation_angle()[sub]), np.degrees(thresholds.rotation),
               "rotational offset, deg"))
    plotter = pv.Plotter(off_screen=True, shape=(1, 2), window_size=window_size)
    for k, (name, values, limit, label) in enumerate(panels):
        plotter.subplot(0, k)
        plotter.add_mesh(pv.wrap(mesh), color="lightgrey", opacity=0.3, smooth_shading=True)
        grid[name] = np.where(found, values, np.inf).ravel(order="F")  # the grid's points run u fastest
        plotter.add_mesh(grid.copy(), scalars=name, cmap="viridis", clim=(0.0, limit), above_color="red",
                         scalar_bar_args={"title": f"{label} (red: over {limit:.4g})"})
        share = within_flags(field, thresholds)[sub].mean()
        plotter.add_text(f"{label}: {share:.1%} of the surface within both thresholds" if k == 0 else label,
                         font_size=9)
        plotter.camera_position = "iso"
        plotter.reset_camera()
    if title:
        plotter.subplot(0, 0)
        plotter.add_text(title, position="lower_left", font_size=9)
    path = Path(path)
    plotter.screenshot(str(path))
    plotter.close()
    return path
