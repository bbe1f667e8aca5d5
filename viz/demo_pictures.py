"""`vrscroll demo`'s pictures of its morph (twin.evaluation.demo_morph): the device where the twin ended on the
target, the step response per hinge, and where asked a Rerun recording and the morph played beside the target."""

from __future__ import annotations

import numpy as np

from twin.device.kinematics import flap_frames
from twin.evaluation.demo_morph import DemoMorph
from viz.render import target_view
from viz.scene import render_approximation
from viz.traces import step_figure
from viz.viewer import show_angles


def demo_pictures(spec, demo: DemoMorph, name: str, mesh, start: list, pose: np.ndarray, png: str, plot: str,
                  rerun: str | None = None, view_out: str | None = None, slowmo: float | None = None,
                  say=print) -> dict:
    """Write the demo's pictures (png: the device on the target; plot: the step response, where the morph ran;
    rerun: a Rerun recording; view_out: the morph played, None: not, slowmo times slower than real time (None:
    viz.viewer.slowmo_for)) and say where each went; the --json document's entries for them ({"png",
    "step_png"})."""
    approx, outcome = demo.approx, demo.outcome
    trace, end, end_angles = outcome.gate.prediction, outcome.end, outcome.reached
    frames = flap_frames(spec, end_angles, approx.root_pose, approx.widths)
    start_frames = flap_frames(spec, np.zeros(spec.n_hinges), pose, approx.widths)
    notes = [f"start (outlined): {', '.join(f'{v:g}' for v in start)} (x y z mm, roll pitch yaw deg)",
             "approximation: " + " ".join(f"{a:.1f}" for a in np.degrees(approx.angles)) + " deg",
             "twin ended at:  " + " ".join(f"{a:.1f}" for a in np.degrees(end_angles)) + " deg"]
    render_approximation(spec, mesh, frames, approx.widths, png, notes=notes, start_frames=start_frames,
                         title=f"{name}, {approx.variant}: twin after the morph, MSD {end.msd * 1e3:.2f} mm, "
                               f"HD {end.hd * 1e3:.2f} mm", failed=demo.failed)
    say(f"[5/5] picture: {png}")
    if trace is not None:
        step_figure(plot, f"demo: {name} morph on the twin", spec, trace, outcome.report.settle_time)
        say(f"      step response: {plot}")
        if rerun:
            from viz.rerun_log import log_move

            say("      " + log_move(rerun, spec, trace, mesh, approx.root_pose, approx.widths))
    if view_out:
        target = target_view(spec, mesh, approx.root_pose, end_angles, approx.widths)
        if trace is None:  # the gate refused the move before simulating it: the device stays flat (shown for 1 s)
            t, angles, slowmo = np.array([0.0, 1.0]), np.tile(end_angles, (2, 1)), 1.0
        else:
            t, angles = trace.time, trace.true_angle
        say("      " + show_angles(spec, t, angles, view_out, target=target, failed=demo.failed, slowmo=slowmo))
    return {"png": png, "step_png": plot if trace is not None else None}
