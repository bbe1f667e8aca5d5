"""Flap-on-flap contact from the hinge angles alone (pure numpy), as the gate finds it in MuJoCo.

Each flap's collision body is the MJCF's box (twin/device/mjcf.py): (pitch - flap_gap) long
across the row, the full depth along the hinges, the thickness behind the touch surface.
Neighbours meet at their hinge and never collide (the MJCF excludes them); any two flaps
two or more apart may. Their penetration depth is found by the separating-axis test:
the smallest overlap along any axis that could separate them is the depth, none means
no contact.
The gate (twin/sim/gate.py) counts a contact deeper than CONTACT_DEPTH; so does
`flap_overlap` here, and tests/test_gate.py checks the two agree.
"""

from __future__ import annotations

import numpy as np

from twin.device.kinematics import flap_frames
from twin.device.spec import DeviceSpec

CONTACT_DEPTH = 1e-4  # m: a flap-on-flap penetration deeper than this is a collision
# rad: two flaps meet only once the chain turns back on itself; below this total of |hinge angles| none
# can (measured: no collision under 208 deg in 40000 random curls), so `collides` answers at once
FREE_TURN = 0.8 * np.pi


def flap_overlap(spec: DeviceSpec, angles) -> float:
    """Deepest penetration (m) between any two flaps two or more apart at these hinge angles; 0 if none.

    All hinge axes are parallel (the device's y) and every box spans the same y range, so
    of the fifteen axes only the boxes' x and z in the x-z plane can separate them (along
    y they overlap by the full depth, and every cross product lies in that plane along one
    of those four): the test runs on the rectangles in the x-z plane.
    """
    frames = flap_frames(spec, angles)
    centre = frames[:, [0, 2], 3] - frames[:, [0, 2], 2] * (spec.thickness / 2)  # (n, 2) x, z
    axes = frames[:, [0, 2]][:, :, [0, 2]]  # (n, 2 (x, z), 2 (box x, box z)): columns are the box's axes
    half = np.array([(spec.flap_pitch - spec.flap_gap) / 2, spec.thickness / 2])
    i, j = np.triu_indices(spec.n_flaps, k=2)
    candidates = np.concatenate([axes[i], axes[j]], axis=2)  # (P, 2, 4) unit axes
    ra = np.einsum("k,pkl->pl", half, np.abs(np.einsum("pdk,pdl->pkl", axes[i], candidates)))
    rb = np.einsum("k,pkl->pl", half, np.abs(np.einsum("pdk,pdl->pkl", axes[j], candidates)))
    gap = np.abs(np.einsum("pd,pdl->pl", centre[j] - centre[i], candidates))
    depth = (ra + rb - gap).min(axis=1)
    return float(max(0.0, depth.max()))


def collides(spec: DeviceSpec, angles, depth: float = CONTACT_DEPTH) -> bool:
    """True where two flaps at these hinge angles (rad) press into each other deeper than `depth` (m)."""
    return float(np.abs(angles).sum()) >= FREE_TURN and flap_overlap(spec, angles) > depth
