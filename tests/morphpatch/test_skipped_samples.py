"""The refinement's shortcuts give the answers of the scans they shorten, to the bit, on shapes nobody tuned for.

Ours' walks along a line (`_path_clear`, `_path_dip`, the flaps-through check) skip the samples S cannot change
their answer at, and a lift's deepest sample (`_deepest`) is found without placing every sample; both rest on S
changing by at most `fields.LIPSCHITZ` per metre. Each is checked here against the plain scan, written here, that
reads S (and its gradient) at every sample, on a noisy sphere, a saddle and a thin tilted plate
(twin.evaluation.made_shapes) at poses drawn about them.
"""

from functools import lru_cache

import numpy as np
import pytest

from twin.device.kinematics import flap_frames
from twin.evaluation.made_shapes import noisy_sphere, plate, saddle
from twin.morphpatch import refinement
from twin.morphpatch.approximation import _layouts
from twin.morphpatch.fields import LIPSCHITZ, PATH_DEPTH, PATH_STEP, _path_clear, _path_dip, build_fields

SHAPES = {"noisy_sphere": noisy_sphere, "saddle": saddle, "plate": plate}
SOLID = ["noisy_sphere", "saddle"]  # lines and lifts go deep into these
THIN = ["saddle", "plate"]  # flaps' lines pass through these (a sphere's chord that does is longer than half a flap)


@lru_cache(maxsize=None)
def made(name):
    """(mesh, fields on a 4 mm grid) of a made shape."""
    mesh = SHAPES[name]()
    return mesh, build_fields(mesh, spacing=0.004)


@pytest.fixture(params=SOLID)
def target(request):
    return made(request.param)


@pytest.fixture(params=THIN)
def thin(request):
    return made(request.param)


def along(a, b):
    """The samples of the segment a -> b (m) the walks take, every PATH_STEP or so, as they compute them."""
    n = int(np.sqrt(((b - a) ** 2).sum()) / PATH_STEP) + 1
    f = np.arange(n + 1) / n
    return np.stack([a[i] + f * (b[i] - a[i]) for i in range(3)], axis=1)


def segments(mesh, rng, count):
    """Segments (a, b) near the target: from points up to 40 mm off its surface to points up to 40 mm inside it."""
    points, faces = mesh.sample(2 * count, return_index=True, seed=int(rng.integers(1 << 30)))
    normals = mesh.face_normals[faces]
    a = points[:count] + normals[:count] * rng.uniform(-0.01, 0.04, (count, 1))
    b = points[count:] + normals[count:] * rng.uniform(-0.04, 0.04, (count, 1))
    return list(zip(a, b))


def test_the_grid_changes_no_faster_than_the_bound_the_walks_skip_by(target):
    """S at neighbouring grid points differs by at most the spacing (exact distances), so along any line the
    interpolated S changes by less than LIPSCHITZ per metre, inside the grid and beyond it."""
    mesh, fields = target
    for axis in range(3):
        assert np.abs(np.diff(fields.sdf, axis=axis)).max() <= fields.spacing * (1 + 1e-6)
    rng = np.random.default_rng(3)
    for a, b in segments(mesh, rng, 40) + [(np.zeros(3), fields.origin - 0.05)]:  # the last leaves the grid
        points = along(a, b)
        s = fields.sdf_values(points)
        steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
        assert (np.abs(np.diff(s)) <= LIPSCHITZ * steps + 1e-12).all()


def test_a_walk_along_a_line_answers_as_one_that_reads_every_sample(target):
    """`_path_dip` is the deepest of every sample's S, to the bit; `_path_clear` says clear exactly where every
    sample is above the depth, for depths about the segment's own dip (where the answer turns)."""
    mesh, fields = target
    rng = np.random.default_rng(5)
    dips = []
    for a, b in segments(mesh, rng, 60):
        s = fields.sdf_values(along(a, b))
        dip = max(0.0, -float(s.min()))
        assert _path_dip(fields.grid, a, b) == dip
        dips.append(dip)
        for depth in (PATH_DEPTH, dip - 1e-6, dip + 1e-6, 0.5 * dip):
            assert _path_clear(fields.grid, a, b, depth) == bool((s >= -depth).all()), (a, b, depth)
    assert sum(d > 0.005 for d in dips) > 10 and sum(d == 0 for d in dips) > 5  # both kinds were walked


def through_every_sample(fields, frames, half):
    """How many flaps pass through the target, each flap's centre line walked at every sample (the refinement's
    rule: in deeper than PATH_DEPTH, out where S is above 0, by a face whose normal opposes the one it came in by)."""
    n = int(half / PATH_STEP)
    count = 0
    for frame in frames:
        through = False
        for end in (-1.0, 1.0):
            y = end * half * (1.0 - np.arange(n + 1) / n)
            points = np.stack([frame[i, 3] + frame[i, 1] * y for i in range(3)], axis=1)
            s, g = fields.sdf_grad(points)
            inside, entered = False, None
            for k in range(n + 1):
                if not inside and s[k] < -PATH_DEPTH:
                    inside, entered = True, g[k]
                elif inside and s[k] > 0.0:
                    inside = False
                    through |= entered @ g[k] < refinement.THROUGH_COS * np.linalg.norm(entered) * np.linalg.norm(g[k])
        count += through
    return count


def poses(mesh, spec, rng, count):
    """(root pose 4x4, hinge angles rad) about the target: the anchor up to 30 mm off or 60 mm into its surface,
    the root facing it or turned anyhow, the hinges anywhere in their range."""
    points, faces = mesh.sample(count, return_index=True, seed=int(rng.integers(1 << 30)))
    out = []
    for k, (p, n) in enumerate(zip(points, mesh.face_normals[faces])):
        z = -n + rng.normal(0, 0.5, 3) if k % 2 else rng.normal(size=3)
        x = np.cross(z, rng.normal(size=3))
        pose = np.eye(4)
        pose[:3, 2] = z / np.linalg.norm(z)
        pose[:3, 0] = x / np.linalg.norm(x)
        pose[:3, 1] = np.cross(pose[:3, 2], pose[:3, 0])
        pose[:3, 3] = p + n * rng.uniform(-0.06, 0.03)
        out.append((pose, rng.uniform(-spec.hinge_limit, spec.hinge_limit, spec.n_hinges)))
    return out


def test_the_flaps_through_check_counts_as_a_walk_over_every_sample(thin, spec):
    mesh, fields = thin
    widths = np.full(spec.n_flaps, spec.flap_pitch)
    counts = []
    for pose, angles in poses(mesh, spec, np.random.default_rng(7), 60):
        frames = flap_frames(spec, angles, pose, widths)
        counts.append(refinement.flaps_through(fields, spec, pose, angles, widths))
        assert counts[-1] == through_every_sample(fields, frames, 0.5 * spec.depth), (pose, angles)
    assert sum(c > 0 for c in counts) > 5 and sum(c == 0 for c in counts) > 5  # both kinds were counted


def test_a_lifts_deepest_sample_is_the_full_scans(target, spec):
    """After a scan (`_cost`, its S kept), lifted along the root's normal step by step (as a resting start or a
    trial is), `_deepest` returns the deepest sample's depth a full scan there returns, to the bit."""
    mesh, fields = target
    widths = np.full(spec.n_flaps, spec.flap_pitch)
    device = refinement._device(spec)
    rng = np.random.default_rng(9)
    for fine in (False, True):
        local = refinement._fine(spec, widths) if fine else _layouts(spec).flap.local(widths)
        deep = 0
        for pose, angles in poses(mesh, spec, rng, 15):
            rot, anchor = np.ascontiguousarray(pose[:3, :3]), pose[:3, 3].copy()
            values = np.empty(local.shape[:2])
            deepest = refinement._cost(fields.grid, device, local, rot, anchor, angles, widths, np.inf, values)[1]
            deep += deepest > 0.01
            for lift in rng.uniform(0.0, 0.01, 6):
                anchor = anchor + lift * rot[:, 2]
                full = refinement._cost(fields.grid, device, local, rot, anchor, angles, widths)[1]
                assert refinement._deepest(fields.grid, device, local, rot, anchor, angles, widths, values,
                                           lift) == full
        assert deep > 3  # poses deep in the target were lifted
