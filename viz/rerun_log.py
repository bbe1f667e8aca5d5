"""Rerun recordings (.rrd) of a move or a run: the device in 3-D and every hinge's traces on one timeline.

Entities (units in the names; the timeline `time` is s from the record's start):

    world/<source>/<geom>               the flaps, motors and electronics of the MJCF (Boxes3D in the geom's
                                        frame, its pose per frame a Transform3D), <source> = device | twin
    world/target                        the target mesh (Mesh3D), coloured by distance to the device at the end
    hinge<k>/angle_deg/<source>         the hinge's encoder angle (target, twin, device): like with like
    hinge<k>/true_angle_deg/twin        the twin's flap angle, which the encoder does not see (backlash, its floor)
    hinge<k>/difference_deg             device - twin, encoder angles (at the device's sample times), where both are there
    hinge<k>/duty/<source>              the commanded duty, -1..1
    hinge<k>/current_A/<source>         the winding current, A

Rerun is an optional extra (`pip install '.[rerun]'`); open a recording with `rerun FILE.rrd` or in the web viewer.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from pathlib import Path

import mujoco
import numpy as np

from twin.device.mjcf import mjcf
from twin.device.spec import DeviceSpec
from twin.errors import UserError
from twin.formats.run import Run
from viz.render import FPS, TWIN_RGBA, frame_times, hinge_qadr, resample

APP = "vrscroll"
DEVICE_RGBA = (0.85, 0.85, 0.82, 1.0)


def _rerun():
    try:
        import rerun as rr
    except ImportError:
        raise UserError("--rerun needs the Rerun SDK: pip install 'vrscroll-twin[rerun]' (or pip install rerun-sdk)") \
            from None
    return rr


def _box_geoms(model: mujoco.MjModel) -> list[int]:
    """The visual boxes (group 2): flaps, motor housings, electronics."""
    return [g for g in range(model.ngeom)
            if model.geom_group[g] == 2 and model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX]


def _geom_poses(spec: DeviceSpec, model, angles: np.ndarray, root: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per frame and box geom: world position (frames, g, 3) m and quaternion (frames, g, 4) xyzw, the device's
    anchor at `root` (4x4, m)."""
    data = mujoco.MjData(model)
    qadr = hinge_qadr(model, spec.n_hinges)
    geoms = _box_geoms(model)
    pos, quat = np.zeros((len(angles), len(geoms), 3)), np.zeros((len(angles), len(geoms), 4))
    q = np.zeros(4)
    for f, row in enumerate(angles):
        data.qpos[qadr] = row[None]
        mujoco.mj_kinematics(model, data)
        for i, g in enumerate(geoms):
            rot = root[:3, :3] @ data.geom_xmat[g].reshape(3, 3)
            pos[f, i] = root[:3, :3] @ data.geom_xpos[g] + root[:3, 3]
            mujoco.mju_mat2Quat(q, rot.ravel())
            quat[f, i] = (q[1], q[2], q[3], q[0])
    return pos, quat


class RerunRecording:
    """One .rrd file being written: moves and runs added at their time on one timeline (s), the device's
    geometry logged once per source. Use as a context manager, or close()."""

    def __init__(self, path, spec: DeviceSpec):
        self.rr = _rerun()
        self.path = Path(path)
        self.spec = spec
        self.model = mujoco.MjModel.from_xml_string(mjcf(spec))
        self.stream = self.rr.RecordingStream(APP)
        self.stream.save(str(self.path))
        self.stream.log("world", self.rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self._sources = set()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        self.stream.flush()
        self.stream.disconnect()

    def add(self, at: float, series: dict, panels: dict, root=None) -> None:
        """series (source -> trace) as time series and panels (source -> (t s, hinge angles (samples, n) rad))
        as the 3-D device at FPS, the earliest sample of the panels at `at` s on the timeline, the series on
        the same clock; the anchor at root (4x4)."""
        rr = self.rr
        start = min(float(t[0]) for t, _ in panels.values())
        times = frame_times(start, max(float(t[-1]) for t, _ in panels.values()), FPS)
        index = [rr.TimeColumn("time", duration=at + times - start)]
        geoms = _box_geoms(self.model)
        root = np.eye(4) if root is None else np.asarray(root, float)
        for source, (t, angles) in panels.items():
            pos, quat = _geom_poses(self.spec, self.model, resample(np.asarray(t, float), angles, times), root)
            for i, g in enumerate(geoms):
                path = f"world/{source}/{mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_GEOM, g) or f'geom{g}'}"
                if source not in self._sources:
                    rgba = DEVICE_RGBA if source == "device" else TWIN_RGBA[:3] + (0.6,)
                    self.stream.log(path, rr.Boxes3D(half_sizes=[self.model.geom_size[g]], colors=[rgba],
                                                     fill_mode="solid"), static=True)
                self.stream.send_columns(path, indexes=index,
                                         columns=rr.Transform3D.columns(translation=pos[:, i], quaternion=quat[:, i]))
            self._sources.add(source)
        self._traces(series, at - start)

    def target(self, mesh, distances_mm=None) -> None:
        """The target mesh (trimesh, m), coloured by per-vertex distance (mm) where given."""
        colours = None
        if distances_mm is not None:
            import matplotlib

            top = max(0.5, float(np.max(distances_mm)))
            colours = (matplotlib.colormaps["viridis"](np.clip(distances_mm / top, 0, 1))[:, :3] * 255).astype(np.uint8)
        self.stream.log("world/target", self.rr.Mesh3D(vertex_positions=mesh.vertices, triangle_indices=mesh.faces,
                                                        vertex_colors=colours), static=True)

    def _scalars(self, path: str, t, values) -> None:
        self.stream.send_columns(path, indexes=[self.rr.TimeColumn("time", duration=np.asarray(t, float))],
                                 columns=self.rr.Scalars.columns(scalars=np.asarray(values, float)))

    def _traces(self, series: dict, shift: float) -> None:
        """series: source -> a Trace (twin.records.trace); the angles compared are the encoder's, the device's and
        the twin's alike."""
        first = next(iter(series.values()))
        for k in range(first.angle.shape[1]):
            self._scalars(f"hinge{k}/angle_deg/target", first.time + shift, np.degrees(first.target[:, k]))
            for source, s in series.items():
                self._scalars(f"hinge{k}/angle_deg/{source}", s.time + shift, np.degrees(s.angle[:, k]))
                if s.true_angle is not None:
                    self._scalars(f"hinge{k}/true_angle_deg/{source}", s.time + shift, np.degrees(s.true_angle[:, k]))
                self._scalars(f"hinge{k}/duty/{source}", s.time + shift, s.duty[:, k])
                self._scalars(f"hinge{k}/current_A/{source}", s.time + shift, s.current[:, k])
            if "device" in series and "twin" in series:
                dev, tw = series["device"], series["twin"]
                diff = np.degrees(dev.angle[:, k] - np.interp(dev.time, tw.time, tw.angle[:, k]))
                self._scalars(f"hinge{k}/difference_deg", dev.time + shift, diff)


def log_run(path, spec: DeviceSpec, run: Run) -> str:
    """A recorded HIL run (device and twin) as a Rerun recording; a line saying where."""
    from viz.viewer import run_frames

    t, rows = run_frames(run, spec)
    n = spec.n_hinges
    with RerunRecording(path, spec) as rec:
        rec.add(0.0, {"device": run.device, "twin": run.twin}, {"device": (t, rows[:, :n]), "twin": (t, rows[:, n:])})
    return f"rerun recording {path} ({run.scenario}: device and twin, {t[-1] - t[0]:.2f} s)"


def log_move(path, spec: DeviceSpec, trace, mesh=None, root=None, widths=None) -> str:
    """A twin's move as a Rerun recording; with a target mesh, the device's anchor at root (4x4) and the
    flaps' widths (m), the mesh coloured by each vertex's distance (mm) to the device where the move ended."""
    with RerunRecording(path, spec) as rec:
        if mesh is not None:
            rec.target(mesh, None if root is None or widths is None else
                       _vertex_distances(spec, mesh, trace.true_angle[-1], root, widths))
        rec.add(0.0, {"twin": trace}, {"twin": (trace.time, trace.true_angle)}, root)
    return f"rerun recording {path} (the twin's move, {trace.duration:.2f} s)"


def _vertex_distances(spec: DeviceSpec, mesh, angles, root, widths) -> np.ndarray:
    """mm from each target vertex to the nearest point of the device's touch surface at hinge angles (rad)."""
    from scipy.spatial import cKDTree

    from twin.device.kinematics import flap_frames
    from twin.morphpatch.sampling import METRIC_SPACING, grid_layout, world_points

    frames = flap_frames(spec, angles, root, widths)
    pts = np.concatenate([world_points(frames, widths, grid_layout(spec, METRIC_SPACING, w), [i])[0]
                          for i, w in enumerate(widths)])
    return cKDTree(pts).query(mesh.vertices)[0] * 1e3


def add_move(rec: RerunRecording, at: float, telemetry=None, prediction=None) -> None:
    """One move at `at` s on the timeline: the device's telemetry (a Trace, time from the moment the
    targets took effect; None without a device) and the twin's prediction (a Trace, or None). In 3-D the device
    at its encoder's angles, the twin at its true ones."""
    series, panels = {}, {}
    if telemetry is not None and len(telemetry.time) > 1:
        series["device"], panels["device"] = telemetry, (telemetry.time, telemetry.angle)
    if prediction is not None and len(prediction.time) > 1:
        pred = dataclasses.replace(prediction, time=prediction.time - prediction.time[0])
        series["twin"], panels["twin"] = pred, (pred.time, pred.true_angle)
    if panels:
        rec.add(at, series, panels)


def morph_recording(path, spec: DeviceSpec, morpher) -> RerunRecording:
    """A recording (`vrscroll serve --rerun`) every morph of `morpher` (twin.live.morph's) is added to, at its
    time since now (s): the morpher's on_move set to add it."""
    recording = RerunRecording(path, spec)
    started = time.monotonic()
    lock = threading.Lock()  # morphs run in a worker thread

    def on_move(telemetry, prediction):
        with lock:
            add_move(recording, time.monotonic() - started, telemetry, prediction)

    morpher.on_move = on_move
    return recording
