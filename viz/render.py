"""Off-screen pictures and videos of the device, rendered by MuJoCo (EGL where there is no display).

`vrscroll view RUN --out`, `simulate --view` and `demo --view` on a machine without a display write
an MP4 (H.264, PyAV) and a contact-sheet PNG. A run shows the device (grey, left) and the twin
(blue, right) side by side, in the same camera; a twin's move shows the twin alone, and `demo`'s its target
beside it (`TargetView`: translucent grey, the part the touch surface lies inside red), with FAILED across
every frame where the gate refused the move.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the off-screen backend)
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import trimesh  # noqa: E402
from PIL import Image, ImageDraw, ImageFont  # noqa: E402

from twin.device.mjcf import mjcf  # noqa: E402
from twin.device.spec import DeviceSpec  # noqa: E402
from twin.morphpatch.surface_metrics import inside_faces  # noqa: E402

FPS = 30  # frames per second of a video, and of the run's time sampled into it
SIZE = (480, 640)  # one panel's (height, width), px: even, as H.264's 4:2:0 needs
TWIN_RGBA = (0.3, 0.6, 1.0, 1.0)  # the twin's flaps, beside the device's grey
SHEET_TILES = 8  # moments on a contact sheet
PROGRESS_LINES = 10  # lines of progress while a video's frames are rendered
CAMERA = {"azimuth": 90.0, "elevation": -28.0, "distance": 0.3}  # deg, deg, m: along the hinge axes (+y)
TARGET_DISTANCE = 0.45  # m: the camera's distance where the target is shown beside the device
TARGET_RGBA = (0.7, 0.7, 0.7, 0.45)  # the target, translucent grey
INSIDE_RGBA = (0.9, 0.1, 0.1, 1.0)  # the part of the target the touch surface lies inside
TARGET_EDGE = 4e-3  # m: the target's faces are split to at most this long for the picture, so that the red part
TARGET_FACES = 200_000  # follows the touch surface, not a large face's outline; coarser where that would pass this
FAILED_RGB = (200, 20, 20)  # the banner across every frame of a move the gate refused


class TargetView(NamedTuple):
    """The target as a picture shows it beside the device, in the device's root (anchor) frame, m."""

    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)
    inside: np.ndarray  # (F,) bool: faces the touch surface lies inside the target under


def target_view(spec: DeviceSpec, mesh: trimesh.Trimesh, root_pose, angles, widths=None) -> TargetView:
    """The target seen from the device at root_pose (4x4 m) with these hinge angles (rad) and widths (m): its
    faces split to at most TARGET_EDGE (coarser where that passes TARGET_FACES faces), those the touch surface
    lies more than twin.morphpatch.surface_metrics.INSIDE_TOLERANCE inside it under marked (`inside_faces`)."""
    vertices, faces = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
    edge = TARGET_EDGE
    if len(faces) < TARGET_FACES:  # an equilateral face of edge e has 0.43 e^2; split ones lie between e/2 and e
        edge = max(TARGET_EDGE, math.sqrt(float(mesh.area) / (0.25 * TARGET_FACES)))
        vertices, faces = trimesh.remesh.subdivide_to_size(vertices, faces, edge, max_iter=12)
    shown = trimesh.Trimesh(vertices, faces, process=False)
    # the touch surface sampled finer than the faces, so that every face under its inside part is some sample's
    inside = inside_faces(spec, mesh, root_pose, angles, widths, shown=shown, spacing=edge / 4)
    pose = np.asarray(root_pose, float)
    return TargetView((vertices - pose[:3, 3]) @ pose[:3, :3], np.asarray(faces), inside)


def add_target(s: mujoco.MjSpec, target: TargetView) -> None:
    """The target's two parts as fixed, non-colliding mesh geoms in the world of a device's MjSpec (root at the
    anchor): "target" (grey, translucent) and, where any face is marked, "target_inside" (red)."""
    for name, keep, rgba in (("target", ~target.inside, TARGET_RGBA), ("target_inside", target.inside, INSIDE_RGBA)):
        if not keep.any():
            continue
        mesh = s.add_mesh(name=name)
        mesh.uservert = target.vertices.ravel().tolist()
        mesh.userface = target.faces[keep].ravel().tolist()
        mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL
        s.worldbody.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_MESH, meshname=name, rgba=list(rgba),
                             contype=0, conaffinity=0, group=1)


def device_mjspec(spec: DeviceSpec) -> mujoco.MjSpec:
    """The device's MJCF as an MjSpec without its keyframes (so that it can be attached, lit, recoloured)."""
    s = mujoco.MjSpec.from_string(mjcf(spec))
    for key in list(s.keys):
        s.delete(key)
    return s


def hinge_qadr(model: mujoco.MjModel, n: int, prefix: str = "") -> np.ndarray:
    """qpos addresses (2, n): each hinge's, then its gearbox output's (both shown at the hinge's angle: the
    backlash between them is too small to see)."""
    return np.array([[model.joint(f"{prefix}{j}{k}").qposadr[0] for k in range(n)] for j in ("hinge", "gear")])


def offscreen_missing() -> str | None:
    """None where MuJoCo can render off-screen here; else a one-line reason naming what is missing."""
    try:
        model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='.1'/></worldbody></mujoco>")
        with mujoco.Renderer(model, 8, 8) as r:
            r.update_scene(mujoco.MjData(model))
            r.render()
    except Exception as exc:  # the GL back end's own error names the library it could not load
        return (f"no off-screen OpenGL context ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}): "
                "install libEGL (Debian: libegl1) or OSMesa (libosmesa6) and set MUJOCO_GL=egl or osmesa")
    return None


class DeviceCamera:
    """Renders the device (spec's MJCF) at given hinge angles (rad), one panel per call, from a fixed camera;
    with a target (TargetView), the target beside it (`add_target`)."""

    def __init__(self, spec: DeviceSpec, size=SIZE, rgba=None, target: TargetView | None = None):
        s = device_mjspec(spec)
        s.worldbody.add_light(pos=[0.0, -0.3, 0.6], dir=[0.0, 0.45, -0.9], type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)
        if rgba is not None:
            for g in s.geoms:
                g.material = ""
                g.rgba = list(rgba)
        if target is not None:
            add_target(s, target)
        self.model = s.compile()
        self.data = mujoco.MjData(self.model)
        self.spec = spec
        self.qadr = hinge_qadr(self.model, spec.n_hinges)
        self.renderer = mujoco.Renderer(self.model, *size)
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.camera.lookat[:] = (0.0, 0.0, -0.03)
        for k, v in CAMERA.items():
            setattr(self.camera, k, v)
        if target is not None:
            self.camera.distance = TARGET_DISTANCE

    def render(self, angles) -> np.ndarray:
        """(height, width, 3) uint8 of the device at hinge angles (rad); the gearbox outputs shown at them too."""
        self.data.qpos[self.qadr] = np.asarray(angles, float)[None]
        mujoco.mj_forward(self.model, self.data)
        self.renderer.update_scene(self.data, self.camera)
        return self.renderer.render().copy()

    def pixel(self, point) -> tuple[int, int]:
        """(row, column) px where a world point (m) lands in the last rendered panel (perspective camera)."""
        cam = self.renderer.scene.camera[0]
        fwd, up = np.asarray(cam.forward), np.asarray(cam.up)
        eye = (np.asarray(cam.pos) + np.asarray(self.renderer.scene.camera[1].pos)) / 2  # the stereo pair's middle
        v = np.asarray(point, float) - eye
        z = v @ fwd
        x, y = v @ np.cross(fwd, up) * cam.frustum_near / z, v @ up * cam.frustum_near / z
        h, w = self.renderer.height, self.renderer.width
        half = cam.frustum_width or (cam.frustum_top - cam.frustum_bottom) / 2 * w / h  # 0: from the aspect ratio
        col = (x - (cam.frustum_center - half)) / (2 * half) * w
        row = h - (y - cam.frustum_bottom) / (cam.frustum_top - cam.frustum_bottom) * h
        return int(row), int(col)

    def close(self) -> None:
        self.renderer.close()


def frame_times(t0: float, t1: float, fps: float = FPS) -> np.ndarray:
    """Frame times (s) covering [t0, t1] at fps: round((t1 - t0) * fps) + 1 frames."""
    return t0 + np.arange(int(round((t1 - t0) * fps)) + 1) / fps


def resample(t, rows, times) -> np.ndarray:
    """rows (samples, m) at times t (s), linearly interpolated to `times`."""
    rows = np.asarray(rows, float)
    return np.stack([np.interp(times, t, rows[:, k]) for k in range(rows.shape[1])], axis=1)


def render_panels(spec: DeviceSpec, panels: list[np.ndarray], size=SIZE,
                  target: TargetView | None = None, say=None) -> np.ndarray:
    """Frames (frames, height, width * len(panels), 3) uint8: each panel's hinge angles (frames, n) rad,
    the first in the device's grey, the others in the twin's blue, side by side; each with the target where
    given. say: where given, told "rendered K/N frames" PROGRESS_LINES times as the frames are rendered (a run
    of seconds takes a minute on a software renderer)."""
    cams = [DeviceCamera(spec, size, None if i == 0 else TWIN_RGBA, target) for i in range(len(panels))]
    total = len(panels[0])
    every = max(1, math.ceil(total / PROGRESS_LINES))
    frames = []
    try:
        for f in range(total):
            frames.append(np.concatenate([c.render(p[f]) for c, p in zip(cams, panels)], axis=1))
            if say is not None and ((f + 1) % every == 0 or f + 1 == total):
                say(f"rendered {f + 1}/{total} frames")
        return np.stack(frames)
    finally:
        for c in cams:
            c.close()


def with_banner(frames: np.ndarray, text: str) -> np.ndarray:
    """frames (frames, height, width, 3) uint8 with a red band across their top, `text` on it in white."""
    out = frames.copy()
    band = max(16, frames.shape[1] // 14)
    out[:, :band] = FAILED_RGB
    img = Image.fromarray(out[0, :band])
    ImageDraw.Draw(img).text((6, band // 6), text, fill=(255, 255, 255), font=ImageFont.load_default(band * 0.6))
    out[:, :band] = np.asarray(img)
    return out


def write_video(path, frames: np.ndarray, fps: int = FPS) -> Path:
    """An H.264 MP4 of frames (frames, height, width, 3) uint8 at fps; returns the path."""
    import av  # only when writing a video: PyAV carries its own FFmpeg

    path = Path(path)
    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=fps)
        stream.height, stream.width = frames.shape[1] - frames.shape[1] % 2, frames.shape[2] - frames.shape[2] % 2
        stream.pix_fmt = "yuv420p"
        for img in frames:
            img = np.ascontiguousarray(img[: stream.height, : stream.width])
            for packet in stream.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return path


def write_contact_sheet(path, frames: np.ndarray, times, title: str, angles_deg=None, tiles: int = SHEET_TILES,
                        title_color: str = "black") -> Path:
    """A PNG of `tiles` frames evenly spread over the run, each titled with its time (s) and, where given,
    the hinge angles (deg) of its first panel."""
    picks = np.unique(np.linspace(0, len(frames) - 1, min(tiles, len(frames))).round().astype(int))
    cols = min(4, len(picks))
    rows = math.ceil(len(picks) / cols)
    aspect = frames.shape[1] / frames.shape[2]
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, (4.2 * aspect + 0.6) * rows + 0.6), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, i in zip(axes.ravel(), picks):
        ax.imshow(frames[i])
        label = f"t = {times[i]:.2f} s"
        if angles_deg is not None:
            label += "\n" + " ".join(f"{round(a):d}" for a in angles_deg[i]) + " deg"
        ax.set_title(label, fontsize=9)
    fig.suptitle(title, fontsize=11, color=title_color)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def write_views(spec: DeviceSpec, t, panels: list[np.ndarray], out_stem, title: str,
                target: TargetView | None = None, failed: str | None = None, slowmo: float = 1.0,
                say=None) -> tuple[Path, Path]:
    """Video (out_stem.mp4) and contact sheet (out_stem.png) of hinge angles (samples, n) rad at times t (s),
    one panel per array (device first, then the twin), resampled to FPS frames per second of the video over the
    record; slowmo: the video's seconds per second of the record (a morph of a quarter second slowed to be seen;
    the sheet's times stay the record's); the target beside the device where given; where `failed` says what
    refused the move, "FAILED: ..." across every frame (`with_banner`) and in red as the sheet's title. say: told
    the rendering's progress (`render_panels`)."""
    t = np.asarray(t, float)
    times = frame_times(t[0], t[-1], FPS * slowmo)
    rows = [resample(t, p, times) for p in panels]
    frames = render_panels(spec, rows, target=target, say=say)
    if failed:
        frames = with_banner(frames, f"FAILED: {failed}")
        title = f"FAILED: {failed}\n{title}"
    stem = Path(out_stem)
    video = write_video(stem.with_suffix(".mp4"), frames)
    sheet = write_contact_sheet(stem.with_suffix(".png"), frames, times - times[0], title, np.degrees(rows[0]),
                                title_color="red" if failed else "black")
    return video, sheet
