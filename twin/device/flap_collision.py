"""Flap-on-flap contact from the hinge angles alone (no MuJoCo), as the gate finds it in MuJoCo.

Each flap's collision body is the MJCF's box (twin/device/mjcf.py): (pitch - flap_gap) long
across the row, the full depth along the hinges, the thickness behind the touch surface.
Neighbours meet at their hinge and never collide (the MJCF excludes them); any two flaps
two or more apart may. Their penetration depth is found by the separating-axis test:
the smallest overlap along any axis that could separate them is the depth, none means
no contact.
The gate (twin/sim/gate.py) counts a contact deeper than CONTACT_DEPTH; so does
`flap_overlap` here, and tests/sim/test_gate.py checks the two agree.

`apart` is a cheaper, proven bound for the twin's loop: where it holds, no two flaps two or more
apart touch, so MuJoCo's collision detection can be skipped for that step.
"""

from __future__ import annotations

import numba
import numpy as np

from twin.device.kinematics import _chain, hinge_axis_sign
from twin.device.spec import DeviceSpec

CONTACT_DEPTH = 1e-4  # m: a flap-on-flap penetration deeper than this is a collision
# rad: two flaps meet only once the chain between them turns back on itself; below this total of |hinge
# angles| between them they cannot (measured: no collision under 208 deg in 40000 random curls), so
# `collides` skips those pairs
FREE_TURN = 0.8 * np.pi
APART_CLEARANCE = 1e-6  # m: the gap `apart` asks for beyond touching (rounding, MuJoCo's own arithmetic)


def flap_overlap(spec: DeviceSpec, angles, turn: float = 0.0) -> float:
    """Deepest penetration (m) between any two flaps two or more apart at these hinge angles; 0 if none.

    All hinge axes are parallel (the device's y) and every box spans the same y range, so
    of the fifteen axes only the boxes' x and z in the x-z plane can separate them (along
    y they overlap by the full depth, and every cross product lies in that plane along one
    of those four): the test runs on the rectangles in the x-z plane. Pairs whose hinges
    between them turn by less than `turn` (rad, total of |angle|) in all are skipped.
    """
    return overlap(flap_boxes(spec), np.asarray(angles, float), turn)


def flap_boxes(spec: DeviceSpec) -> tuple:
    """What `overlap` needs of a spec: the hinges' axis signs, the flaps' widths (m), the root flap and
    the boxes' half sizes (across the row, thickness; m)."""
    return (hinge_axis_sign(spec).astype(float), np.full(spec.n_flaps, spec.flap_pitch), int(spec.root_flap),
            np.array([(spec.flap_pitch - spec.flap_gap) / 2, spec.thickness / 2]))


@numba.njit(cache=True)
def overlap(boxes, angles, turn):
    """`flap_overlap` compiled, from `flap_boxes(spec)`: callable from compiled loops (the refinement's)."""
    signs, widths, root_flap, half = boxes
    frames = _chain(signs * angles, widths, root_flap, np.eye(4))
    return _deepest(frames, half, np.abs(angles), turn)


@numba.njit(cache=True)
def _deepest(frames, half, turns, turn):
    n = frames.shape[0]
    deepest = 0.0
    axes = np.empty((4, 2))
    for i in range(n):
        for j in range(i + 2, n):
            if turns[i:j].sum() < turn:
                continue
            # rectangle centres (x, z), a thickness/2 behind the touch surface, and their axes
            ci = (frames[i, 0, 3] - frames[i, 0, 2] * half[1], frames[i, 2, 3] - frames[i, 2, 2] * half[1])
            cj = (frames[j, 0, 3] - frames[j, 0, 2] * half[1], frames[j, 2, 3] - frames[j, 2, 2] * half[1])
            axes[0, 0], axes[0, 1] = frames[i, 0, 0], frames[i, 2, 0]
            axes[1, 0], axes[1, 1] = frames[i, 0, 2], frames[i, 2, 2]
            axes[2, 0], axes[2, 1] = frames[j, 0, 0], frames[j, 2, 0]
            axes[3, 0], axes[3, 1] = frames[j, 0, 2], frames[j, 2, 2]
            depth = np.inf
            for k in range(4):
                ux, uz = axes[k, 0], axes[k, 1]
                ra = half[0] * abs(axes[0, 0] * ux + axes[0, 1] * uz) + half[1] * abs(axes[1, 0] * ux + axes[1, 1] * uz)
                rb = half[0] * abs(axes[2, 0] * ux + axes[2, 1] * uz) + half[1] * abs(axes[3, 0] * ux + axes[3, 1] * uz)
                gap = abs((cj[0] - ci[0]) * ux + (cj[1] - ci[1]) * uz)
                depth = min(depth, ra + rb - gap)
            deepest = max(deepest, depth)
    return deepest


@numba.njit(cache=True)
def collides(boxes, angles, depth=CONTACT_DEPTH):
    """True where two flaps at these hinge angles (rad) press into each other deeper than `depth` (m);
    boxes: `flap_boxes(spec)`. Compiled, for the refinement's loop."""
    return overlap(boxes, angles, FREE_TURN) > depth


def apart_spreads(spec: DeviceSpec, margin: float = 0.0) -> np.ndarray:
    """What `apart` needs of a spec: per number g of flaps between two flaps (index g, 1 .. n_flaps - 2;
    index 0 unused), the largest spread of the flaps' directions (rad) at which those two stay at least
    margin + APART_CLEARANCE (m) apart.

    The bound: let R be the spread (largest minus smallest direction in the x-z plane) of flaps i .. j
    and u the direction halfway. Each flap between advances the hinge line by the pitch p along u at least
    p cos(R/2); flap i lies behind its outer hinge along u, but for its thickness t, which reaches at most
    t sin(R/2) ahead of it, and flap j likewise. So for R < pi the two are apart along u where
    g p cos(R/2) - 2 t sin(R/2) >= margin + clearance, i.e. R/2 <= acos(c / hypot(g p, 2 t)) - atan2(2 t, g p).
    """
    c = margin + APART_CLEARANCE
    g = np.arange(spec.n_flaps - 1, dtype=float)
    a, b = g * spec.flap_pitch, 2.0 * spec.thickness
    h = np.hypot(a, b)
    spreads = 2.0 * (np.arccos(np.minimum(c / h, 1.0)) - np.arctan2(b, a))
    spreads[0] = 0.0
    return spreads


@numba.njit(cache=True)
def apart(spreads, angles) -> bool:
    """True where no two flaps two or more apart can touch at these hinge angles (rad): a bound on the
    spread of the flaps' directions, from `apart_spreads(spec, margin)`. Flap k + 1 points the way of flap k
    turned by hinge k's angle (the same sense on either side of the root)."""
    n = angles.shape[0] + 1
    for i in range(n - 2):
        direction = lo = hi = 0.0
        for j in range(i + 1, n):
            direction += angles[j - 1]
            lo, hi = min(lo, direction), max(hi, direction)
            if j >= i + 2 and hi - lo >= spreads[j - i - 1]:
                return False
    return True
