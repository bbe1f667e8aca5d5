"""MuJoCo's viewer for the twin: a HIL run's device and twin overlaid (`vrscroll view RUN`: the device
solid, the twin translucent, both replayed from the run's traces), and a twin's move played in real
time (`--view` on `vrscroll simulate` and `vrscroll demo`).

The window needs a display; without one (or when asked for files) `show_move` and `show_run` write a video
and a contact sheet rendered off-screen (viz.render) instead, and say where.
"""

from __future__ import annotations

import os
import sys
import time

import mujoco
import mujoco.viewer
import numpy as np

from twin.device.mjcf import mjcf
from twin.device.spec import DeviceSpec
from twin.errors import UserError
from twin.formats.run import Run
from viz.render import TargetView, add_target, device_mjspec, hinge_qadr, offscreen_missing, resample, write_views

TWIN_ALPHA = 0.3  # opacity of the twin's flaps beside the device's
TWIN_PREFIX = "twin/"
FRAME_PERIOD = 1.0 / 60.0  # s between viewer updates
MIN_PLAYED_S = 2.0  # a twin's move shorter than this is played slowed down to last this long (`slowmo_for`)


def display_missing() -> str | None:
    """None where a window can open; else the one-line reason it cannot."""
    if sys.platform == "darwin" or os.name == "nt" or os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return None
    return "no display (neither DISPLAY nor WAYLAND_DISPLAY is set): MuJoCo's viewer needs one; nothing was shown"


def pair_model(spec: DeviceSpec) -> mujoco.MjModel:
    """Two devices in one model, in the same place: the device's (joints hinge0..) and the twin's
    (joints twin/hinge0.., every geom translucent)."""
    device, twin = device_mjspec(spec), device_mjspec(spec)
    device.attach(twin, prefix=TWIN_PREFIX, frame=device.worldbody.add_frame())
    for g in device.geoms:
        if g.name.startswith(TWIN_PREFIX) or g.parent.name.startswith(TWIN_PREFIX):
            g.material = ""
            g.rgba = [0.3, 0.6, 1.0, TWIN_ALPHA]
    return device.compile()


def run_frames(run: Run, spec: DeviceSpec) -> tuple[np.ndarray, np.ndarray]:
    """(t s, qpos rows (frames, 2n) rad: the device's hinges then the twin's) of a recorded run
    (twin.formats.run.read_run), at the device's frame times: the device's encoder angles mid-count, the
    twin's true angles interpolated to those times."""
    dev, tw = run.device, run.twin
    if tw is None or not len(tw.time):
        raise ValueError(f"{run.dir}: no twin.csv to replay beside the device")
    t = dev.time
    device = dev.angle + 0.5 * spec.rad_per_count
    flap = tw.true_angle if tw.true_angle is not None else tw.angle
    twin = resample(tw.time, flap, t)
    return t, np.concatenate([device, twin], axis=1)


def slowmo_for(duration: float, slowmo: float | None = None) -> float:
    """How many times slower than real time a move of `duration` s is played: `slowmo` where given, else as slow
    as makes it last MIN_PLAYED_S, never faster than real time (a 0.27 s morph made a 9-frame video)."""
    if slowmo is not None:
        return slowmo
    return max(1.0, MIN_PLAYED_S / duration) if duration > 0 else 1.0


def play(model: mujoco.MjModel, qadr: np.ndarray, t: np.ndarray, rows: np.ndarray, title: str,
         failed: str | None = None, slowmo: float = 1.0) -> str:
    """Show rows (frames, m) of hinge angles at their times t (s), slowmo times slower than real time, each row
    at the qpos addresses qadr (r, m), then hold the last until the window is closed; where `failed` says what
    refused the move, "FAILED: ..." over the view. A one-line message for where no window can open."""
    missing = display_missing()
    if missing:
        return missing
    data = mujoco.MjData(model)
    with mujoco.viewer.launch_passive(model, data) as viewer:
        if failed:
            viewer.set_texts((mujoco.mjtFontScale.mjFONTSCALE_200, mujoco.mjtGridPos.mjGRID_TOPLEFT, "FAILED", failed))
        start = time.monotonic()
        while viewer.is_running():
            i = min(int(np.searchsorted(t, (time.monotonic() - start) / slowmo)), len(t) - 1)
            data.qpos[qadr] = rows[i][None]
            mujoco.mj_forward(model, data)
            viewer.sync()
            time.sleep(FRAME_PERIOD)
    return f"viewer closed ({title}, {t[-1] - t[0]:.2f} s played)"


def view_run(run: Run, spec: DeviceSpec) -> str:
    """A recorded HIL run replayed: the device solid, the twin translucent."""
    model = pair_model(spec)
    t, rows = run_frames(run, spec)
    n = spec.n_hinges
    qadr = np.concatenate([hinge_qadr(model, n), hinge_qadr(model, n, TWIN_PREFIX)], axis=1)
    return play(model, qadr, t, rows, f"{run.dir}: device solid, twin translucent")


def move_model(spec: DeviceSpec, target: TargetView | None = None) -> mujoco.MjModel:
    """The device's model for showing a move, with its target beside it where given (viz.render.add_target)."""
    if target is None:
        return mujoco.MjModel.from_xml_string(mjcf(spec))
    s = device_mjspec(spec)
    add_target(s, target)
    return s.compile()


def play_angles(spec: DeviceSpec, t, angles, target: TargetView | None = None, failed: str | None = None,
                slowmo: float = 1.0) -> str:
    """Hinge angles (samples, n) rad at times t (s), slowmo times slower than real time, beside a target where
    given."""
    model = move_model(spec, target)
    return play(model, hinge_qadr(model, spec.n_hinges), np.asarray(t) - t[0], angles, "the twin's move", failed,
                slowmo)


def _files(spec: DeviceSpec, t, panels, out_stem, title: str, target=None, failed=None, slowmo: float = 1.0,
           say=None) -> str:
    missing = offscreen_missing()
    if missing:
        raise UserError(missing)
    video, sheet = write_views(spec, t, panels, out_stem, title, target, failed, slowmo, say)
    return f"video {video}, contact sheet {sheet} ({title}" + (f"; FAILED: {failed})" if failed else ")")


def show_move(spec: DeviceSpec, trace, out_stem, files: bool = False, target: TargetView | None = None,
              failed: str | None = None, slowmo: float | None = None) -> str:
    """A twin's move (twin.records.trace.Trace, its true angles): `show_angles`."""
    return show_angles(spec, trace.time, trace.true_angle, out_stem, files, target, failed, slowmo)


def show_angles(spec: DeviceSpec, t, angles, out_stem, files: bool = False, target: TargetView | None = None,
                failed: str | None = None, slowmo: float | None = None) -> str:
    """Hinge angles (samples, n) rad at times t (s): MuJoCo's viewer where there is a display and files is False,
    else out_stem.mp4 and out_stem.png rendered off-screen; beside the target where given (the part the touch
    surface lies inside red), and FAILED with `failed` (what refused the move) where given; slowmo times slower
    than real time (None: `slowmo_for` the move's duration). A line saying what was shown or written."""
    slowmo = slowmo_for(float(t[-1] - t[0]), slowmo)
    title = ("the twin's move (true hinge angles" + ("" if slowmo == 1 else f"; slow motion x{slowmo:.3g}") + ")"
             + ("" if target is None else "; the target grey, red where the touch surface lies inside it"))
    if files or display_missing():
        return _files(spec, t, [angles], out_stem, title, target, failed, slowmo)
    return play_angles(spec, t, angles, target, failed, slowmo)


def show_run(run: Run, spec: DeviceSpec, out_stem, files: bool = False, say=None) -> str:
    """A recorded run: the viewer (device solid, twin translucent) where there is a display and files is False;
    else out_stem.mp4 and .png, the device (grey, left) and the twin (blue, right) side by side, the rendering's
    progress told to `say` where given."""
    if files or display_missing():
        t, rows = run_frames(run, spec)
        n = spec.n_hinges
        return _files(spec, t, [rows[:, :n], rows[:, n:]], out_stem,
                      f"{run.scenario}: device (grey, left; encoder angles) and twin (blue, right)", say=say)
    return view_run(run, spec)
