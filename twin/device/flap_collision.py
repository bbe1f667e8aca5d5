"""Flap-on-flap contact from the hinge angles alone (pure numpy), as the gate finds it in MuJoCo.

Each flap's collision body is the MJCF's box (twin/device/mjcf.py): (pitch - flap_gap) long
across the row, the full depth along the hinges, the thickness behind the touch surface.
Neighbours meet at their hinge and never collide (the MJCF excludes them); any two flaps
two or more apart may. Their penetration depth is found by the separating-axis test
over the fifteen axes of two boxes (three face normals each, nine edge-edge cross
products): the smallest overlap along any axis is the depth, none means no contact.
The gate (twin/sim/gate.py) counts a contact deeper than CONTACT_DEPTH; so does
`flap_overlap` here, and tests/test_gate.py checks the two agree.
"""

from __future__ import annotations

import numpy as np

from twin.device.kinematics import flap_frames
from twin.device.spec import DeviceSpec

CONTACT_DEPTH = 1e-4  # m: a flap-on-flap penetration deeper than this is a collision


def flap_boxes(spec: DeviceSpec, angles) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Collision boxes of the flaps at hinge angles (rad): centres (n, 3) m, axes (n, 3, 3) as
    columns, half extents (3,) m, in the device frame."""
    frames = flap_frames(spec, angles)
    half = np.array([(spec.flap_pitch - spec.flap_gap) / 2, spec.depth / 2, spec.thickness / 2])
    centres = frames[:, :3, 3] - frames[:, :3, 2] * half[2]
    return centres, frames[:, :3, :3], half


def flap_overlap(spec: DeviceSpec, angles) -> float:
    """Deepest penetration (m) between any two flaps two or more apart at these hinge angles; 0 if none."""
    centres, axes, half = flap_boxes(spec, angles)
    i, j = np.triu_indices(spec.n_flaps, k=2)
    a, b = axes[i], axes[j]  # (P, 3, 3), columns are the box axes
    t = centres[j] - centres[i]  # (P, 3)
    cross = np.cross(a[:, :, :, None], b[:, :, None, :], axis=1).reshape(len(i), 3, 9)  # a_k x b_l
    candidates = np.concatenate([a, b, cross], axis=2)  # (P, 3, 15)
    norm = np.linalg.norm(candidates, axis=1)  # (P, 15)
    valid = norm > 1e-9  # parallel edges give no axis
    axis = candidates / np.where(valid, norm, 1.0)[:, None, :]
    ra = np.einsum("k,pkl->pl", half, np.abs(np.einsum("pdk,pdl->pkl", a, axis)))
    rb = np.einsum("k,pkl->pl", half, np.abs(np.einsum("pdk,pdl->pkl", b, axis)))
    overlap = ra + rb - np.abs(np.einsum("pd,pdl->pl", t, axis))
    depth = np.where(valid, overlap, np.inf).min(axis=1)
    return float(max(0.0, depth.max()))


def collides(spec: DeviceSpec, angles) -> bool:
    """True where two flaps at these hinge angles (rad) press into each other deeper than CONTACT_DEPTH."""
    return flap_overlap(spec, angles) > CONTACT_DEPTH
