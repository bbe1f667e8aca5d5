"""`demo --view`'s picture of the target (issue 37 item 5): the target beside the device, the part the touch
surface lies inside coloured, FAILED across the frames where the gate refused. Judged on the scene's data and the
rendered frames' colours against geometry worked out here, not by eye."""

import math

import av
import numpy as np
import pytest
import trimesh

from twin.device.kinematics import pose_matrix
from viz.render import FAILED_RGB, INSIDE_RGBA, DeviceCamera, target_view, write_views

BOX = (0.25, 0.25, 0.05)  # m: a slab wider than the device (188 x 175 mm), its top face at z = 25 mm


def _box_and_pose(spec, depth, tilt=0.0):
    """The slab, and a flat device whose anchor is `depth` (m) below its top face, turned by `tilt` (rad) about
    the hinge axis (y)."""
    c, s = math.cos(tilt), math.sin(tilt)
    rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return trimesh.creation.box(BOX), pose_matrix(np.array([0.0, 0.0, BOX[2] / 2 - depth]), rot)


def _area(view, mask):
    return float(trimesh.Trimesh(view.vertices, view.faces, process=False).area_faces[mask].sum())


def test_the_coloured_part_is_the_target_under_the_touch_surface_inside_it(spec):
    touch = spec.n_flaps * spec.flap_pitch * spec.usable_depth  # m^2: the flat touch surface
    box, pose = _box_and_pose(spec, 0.005)  # pressed 5 mm in, flat: all of it inside
    view = target_view(spec, box, pose, np.zeros(spec.n_hinges))
    assert _area(view, view.inside) == pytest.approx(touch, rel=0.05)
    # in the device's root frame: the top face 5 mm above the touch surface, every red face on it
    assert view.vertices[:, 2].max() == pytest.approx(0.005, abs=1e-9)
    assert np.allclose(view.vertices[view.faces[view.inside]][..., 2], 0.005, atol=1e-9)
    # lifted 2 mm off it: nothing coloured
    box, pose = _box_and_pose(spec, -0.002)
    assert not target_view(spec, box, pose, np.zeros(spec.n_hinges)).inside.any()
    # tilted 3 deg about the anchor on the surface: inside where the touch surface is more than 0.5 mm below the
    # face, the strip x < -0.5 mm / sin(3 deg) of the row's 188 mm
    tilt = math.radians(3.0)
    box, pose = _box_and_pose(spec, 0.0, tilt)
    view = target_view(spec, box, pose, np.zeros(spec.n_hinges))
    half = spec.n_flaps * spec.flap_pitch / 2
    strip = (half - 0.5e-3 / math.sin(tilt)) * math.cos(tilt) * spec.usable_depth
    assert _area(view, view.inside) == pytest.approx(strip, rel=0.08)
    world = view.vertices[view.faces[view.inside]].mean(axis=1) @ pose[:3, :3].T + pose[:3, 3]
    assert world[:, 0].min() > 0.5e-3 / math.sin(tilt) - 0.005  # (+x goes down at this tilt)
    # the scene the viewer and the video show: the target in two mesh geoms, the red one these faces
    cam = DeviceCamera(spec, target=view)
    model = cam.model
    red = model.geom("target_inside")
    assert np.allclose(model.geom_rgba[red.id], INSIDE_RGBA)
    assert model.mesh_facenum[model.geom_dataid[red.id]] == view.inside.sum()
    assert model.mesh_facenum[model.geom_dataid[model.geom("target").id]] == (~view.inside).sum()
    cam.close()


def _frames(path):
    with av.open(str(path)) as video:
        return [f.to_ndarray(format="rgb24") for f in video.decode(video.streams.video[0])]


@pytest.mark.slow  # 14 s on the shared machine: two videos of a 55 000-face target
def test_the_video_shows_the_red_part_and_says_failed(spec, tmp_path):
    t = np.array([0.0, 0.2])
    angles = np.zeros((2, spec.n_hinges))
    reds = {}
    for depth, failed in ((0.005, "the gate refused: collision"), (-0.002, None)):
        box, pose = _box_and_pose(spec, depth)
        view = target_view(spec, box, pose, angles[0])
        stem = tmp_path / f"v{depth}"
        write_views(spec, t, [angles], stem, "test", view, failed)
        frame = _frames(stem.with_suffix(".mp4"))[-1].astype(int)
        band = frame[:8].reshape(-1, 3).mean(axis=0)
        assert (np.abs(band - FAILED_RGB).max() < 30) == bool(failed), band
        below = frame[frame.shape[0] // 10:]
        reds[depth] = np.mean((below[..., 0] > 150) & (below[..., 1] < 80) & (below[..., 2] < 80))
        assert stem.with_suffix(".png").stat().st_size > 10_000
    assert reds[0.005] > 0.02 and reds[-0.002] < 0.001, reds
