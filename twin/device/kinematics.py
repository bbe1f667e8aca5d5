"""Forward kinematics of VRScroll's touch surface (pure numpy, device frame conventions).

Device frame: x along the row of flaps (flap 0 -> flap n-1), y along the hinge
axes, z the touch-surface normal; origin (the anchor) at the centre of the root
flap's touch surface. Hinge k joins flap k and flap k+1 and lies on the touch
surface; its angle is the outer flap's rotation relative to the inner one
(the neighbour nearer the root), 0 = flat, positive = the touch surface bends
concave (the outer flap's free end rises towards +z, as when wrapping a ball).
"""

from __future__ import annotations

import numba
import numpy as np

from twin.device.spec import DeviceSpec


def hinge_axis_sign(spec: DeviceSpec) -> np.ndarray:
    """Per hinge, the sign s of its axis s*y in the inner flap's frame (+1 left of the root, -1 right)."""
    k = np.arange(spec.n_hinges)
    return np.where(k < spec.root_flap, 1.0, -1.0)


def outer_flap(spec: DeviceSpec) -> np.ndarray:
    """Per hinge, the index of the flap it moves (the one farther from the root)."""
    k = np.arange(spec.n_hinges)
    return np.where(k < spec.root_flap, k, k + 1)


def flap_frames(spec: DeviceSpec, angles, root_pose=None, widths=None) -> np.ndarray:
    """Pose of each flap's touch-surface frame, shape (n_flaps, 4, 4).

    angles: hinge angles, rad, shape (n_hinges,). root_pose: 4x4 world pose of
    the anchor (identity if None). widths: per-flap length along x, m (the flap
    pitch if None): a flap's outer hinge sits at its inner hinge + width.
    The frame's origin is the centre of the flap's touch surface; its axes are the
    device axes carried through the hinges.
    """
    angles = np.asarray(angles, dtype=float)
    if angles.shape != (spec.n_hinges,):
        raise ValueError(f"expected {spec.n_hinges} hinge angles, got shape {angles.shape}")
    w = np.full(spec.n_flaps, spec.flap_pitch) if widths is None else np.asarray(widths, float)
    root = np.eye(4) if root_pose is None else np.asarray(root_pose, float)
    return _chain(hinge_axis_sign(spec) * angles, w, spec.root_flap, root)


@numba.njit(cache=True)
def _chain(signed_angles, widths, r, root):
    """flap_frames' loop, compiled (the approximation's, the refinement's and the collision check's inner step)."""
    n = len(widths)
    frames = np.zeros((n, 4, 4))
    for i in range(n):
        frames[i] = np.eye(4)
    for step in (1, -1):
        inner = r
        i = r + step
        while 0 <= i < n:
            hinge = i - 1 if step == 1 else i
            c, s = np.cos(signed_angles[hinge]), np.sin(signed_angles[hinge])
            for a in range(3):  # rot = inner rot @ (rotation by the angle about +y)
                x, y, z = frames[inner, a, 0], frames[inner, a, 1], frames[inner, a, 2]
                frames[i, a, 0], frames[i, a, 1], frames[i, a, 2] = c * x - s * z, y, s * x + c * z
            for a in range(3):  # hinge point on the inner flap's edge, then this flap's centre beyond it
                frames[i, a, 3] = (frames[inner, a, 3] + frames[inner, a, 0] * step * widths[inner] / 2
                                   + frames[i, a, 0] * step * widths[i] / 2)
            inner = i
            i += step
    out = np.empty((n, 4, 4))
    for i in range(n):
        out[i] = root @ frames[i]
    return out


def pose_matrix(position, rotation) -> np.ndarray:
    """4x4 homogeneous transform from a position (3,) and a rotation matrix (3, 3)."""
    t = np.eye(4)
    t[:3, :3] = rotation
    t[:3, 3] = position
    return t


def quat_matrix(quat) -> np.ndarray:
    """The rotation matrix (3, 3) of a unit quaternion (w, x, y, z). Scipy's `Rotation.from_quat(...).as_matrix()`
    to rounding, at a tenth of its cost (the live worker converts every pose)."""
    w, x, y, z = (float(v) for v in quat)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def matrix_quat(rotation) -> tuple[float, float, float, float]:
    """The unit quaternion (w, x, y, z) of a rotation matrix (3, 3): Markley's method, choosing the branch and so
    the sign as scipy's `Rotation.from_matrix(...).as_quat(scalar_first=True)` does, at a tenth of its cost (the
    live worker encodes every approximation)."""
    m = [[float(v) for v in row] for row in rotation]
    trace = m[0][0] + m[1][1] + m[2][2]
    decision = (m[0][0], m[1][1], m[2][2], trace)
    choice = max(range(4), key=decision.__getitem__)  # the first of equals, as numpy's argmax
    if choice == 3:
        q = [m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1], 1 + trace]
    else:
        i, j, k = choice, (choice + 1) % 3, (choice + 2) % 3
        q = [0.0, 0.0, 0.0, m[k][j] - m[j][k]]
        q[i] = 1 - trace + 2 * m[i][i]
        q[j] = m[j][i] + m[i][j]
        q[k] = m[k][i] + m[i][k]
    norm = (q[0] ** 2 + q[1] ** 2 + q[2] ** 2 + q[3] ** 2) ** 0.5
    return q[3] / norm, q[0] / norm, q[1] / norm, q[2] / norm
