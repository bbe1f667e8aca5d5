"""Our method beyond the paper: a bounded local refinement of the pipeline's result ("refined").

The pipeline (twin.morphpatch.approximation) turns the root and each hinge by the
angle of a mean gradient: a good start, not a fit. This refines its result by
minimising what the metrics measure, the signed distance S of the proxy's touch-surface
samples (the pipeline's 5 mm flap grid, the pipeline's widths) to the target on the SDF
grid, over the root pose (anchor position and a rotation about it) and the hinge angles:
sum_j r(S_j)^2 with

    r(S) = S                          outside the target (S >= 0),
    r(S) = S sqrt(1 + (S / TAIL)^2)   inside it: r^2 = S^2 + S^4 / TAIL^2,

so a flap buried in the target costs more than one as far above it (a pressed device
cannot sink into the object; on the torus the largest distances, HD, are flap tips
20-40 mm inside the tube, which plain squares traded against the mean). Levenberg-Marquardt
with analytic Jacobians, dr_j = r'(S_j) dS_j and

    dS_j/d(anchor)   = g_j,
    dS_j/d(rotation) = (x_j - anchor) x g_j           (a small turn w about the anchor),
    dS_j/d(angle_h)  = a_h . ((x_j - q_h) x g_j)      for samples on the flaps hinge h moves,

with g_j = grad S(x_j), a_h and q_h hinge h's axis and a point on it in the world.

Bounds, so every result is a pose the device can take where the user asked for it, resting on the
target from outside (issue 37; docs/approximation.md, "Resting from outside"):
- no touch-surface sample deeper in the target than INSIDE_LIMIT (on the grid): the step is solved with every
  sample's S, linearised, kept above FLOOR x INSIDE_LIMIT deep (`_kept_out`: an active set of the samples it would
  take deeper); a trial that still goes deeper (S is not linear) is lifted back along the root's normal (`_lifted`)
  and refused if it still does; the
  search starts from poses that rest (`_feasible`: the first phase's end, its angles scaled down (SCALES),
  each lifted along its normal until it rests, by at most LIFT_REACH; where no lift within the anchor's ball
  rests, the ball goes up with the lift, and a curl that rests nowhere eased towards the next flatter scale; and
  the pipeline's own pose flat, and curled where it rests as it is, or lifted until it rests where the first
  phase's end, curled (as it ended or eased), does not), searched from each, the one whose samples
  lie nearest the target on the grid kept (mean |S|: `grid_msd`), or, where none rests, returns saying so;
- the anchor stays (nearly) out of the target, at most ANCHOR_DEPTH in: where a step
  would take it deeper, it is moved back along grad S, and while it is at that depth
  with the sum falling inwards, steps keep to the surface's tangent plane there (least
  squares alone sinks the root flap's middle up to 17 mm into a convex target to bring
  its 155 mm long ends closer; the device is meant to lie on the target, not in it);
- the anchor keeps to the side the device came from: a step whose straight path crosses the
  target (deeper than PATH_DEPTH, twin.morphpatch.fields) is refused like a collision, and the
  result is the last kept state whose anchor the snapped one reaches in a straight line (to
  CHORD_DEPTH: steps each clear can add up to a line that is not; refusing such steps instead
  changed where an arch start stopped, 1.34 mm inside the exact mesh);
- no flap passes through the target: walking each flap's centre line (along its hinge axis, the
  device's whole depth) from either end to its middle, the line may go into the target and stay
  there (a flap pressed onto it), but not go in and come out through another face (the two faces'
  normals more than 120 deg apart, THROUGH_COS: a cup's wall, a plate, a torus's tube; not a corner
  it cuts, which the distances already count); the start has none, a step that puts one through
  is refused like a collision, and a search whose kept state has one returns its start instead. Without it, from above a
  cup narrower than the device, the samples' distances to the inner wall pulled the anchor down
  into the cavity with the root flap's ends through the wall (issue 22);
- the anchor stays within ANCHOR_RADIUS of the snapped point (the pipeline's step 1:
  where the user brought the device; unbounded, it drifts up to 150 mm to the easiest
  flat patch, which is not the region the user chose), or of the point above it the start was
  lifted to where it could rest no nearer; on the ball's surface, steps
  slide along it, and one that still leaves the ball is cut back to it;
- hinge angles are clipped inside +-spec.hinge_limit;
- flaps two or more apart at least FLAP_APART apart (`_flap_gap`: the collision boxes of
  twin.device.flap_collision seen along the hinges, their exact gap): a pipeline result
  that is closer already (it curls 188 mm of flaps round a thin cylinder's 126 mm
  circumference, the tips meet under a torus's tube) is first unrolled from its tips
  (`_uncurled`), until it is not. Such a search starts at the contact, where the sum mostly
  wants more curl: a step into contact is tried again with the hinges it curled further held
  where they are, until a step is kept (refusing the whole step ended the search where it
  began: on issue 22's tori, ours stayed at the unrolled start); where holding them leaves no
  expected gain, they are let go. In every other search, and in that one once they are let go,
  a step into contact is refused like one that does not lower the sum (holding hinges in every search also let the anchor into a
  cup's cavity, 11 mm inside its hull, and across a bowl's wall on the exact mesh).
A step is kept only when it lowers the sum, so the result is never worse than its start
on the grid's objective. The search ends when the model expects a gain below TOLERANCE of
the sum, or after two kept steps in a row that each gained less: one small kept step is
often a step cut short by a bound (the anchor's ball, its depth) or a refused collision,
and ending there left a torus start 0.81 mm above the pipeline's MSD. SI units (m, rad).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numba
import numpy as np

from twin.device.flap_collision import flap_boxes
from twin.device.kinematics import _chain, hinge_axis_sign, outer_flap
from twin.device.spec import DeviceSpec
from twin.morphpatch.fields import (CHORD_DEPTH, LIPSCHITZ, PATH_DEPTH, PATH_STEP, Fields, _interpolate, _path_clear,
                                    _path_dip, _value)
from twin.morphpatch.sampling import METRIC_SPACING, grid_layout

FLAP_APART = 3.5e-3  # m: refined poses keep flaps two or more apart this far apart (issue 37 asks 3 mm; 0.5 mm spare)
INSIDE_LIMIT = 1.5e-3  # m: no touch-surface sample of a refined pose lies deeper in the target than this (on the grid;
# the exact mesh between samples and the grid's error add up to 1.5 mm: the stated bound is 3 mm, exact)
LIFT_STEPS = 40  # at most this many lifts of the start along its normal until it rests outside (`_feasible`)
LIFT_MIN = 1e-3  # m: the smallest such lift
LIFT_REACH = 0.06  # m: ... and the most, beyond which the ball goes with it (a torus start wrapped 39 mm into the
# tube rests lifted by about that; within the 20 mm ball alone, 14 of the tests' 80 paper-shape starts found none)
SCALES = (1.0, 0.5, 0.0)  # the pipeline's hinge angles times these, each lifted (`_feasible`; finer steps,
# 1, 0.9, 0.8, 0.65, 0.5, 0.25, 0, left a can's wrap 16.4 mm MSD where these leave 14.2)
OWN_SCALES = (1.0, 0.0)  # the pipeline's own pose is searched curled (`_search`: where the first phase's curled end
# rests at no lift, or it rests as it is) and flat (plate_0: flat on the plate's face from the pipeline's root, where
# the first phase's end curled over its edges; 44 -> 6 % above the best pose within the bounds); "curled end" is the
# first phase's curl as it ended or eased (CURL_STEPS)
CURL_STEPS = 3  # a curl that rests at no lift is eased towards the next flatter scale that rests, the most curl
# that rests kept, by this many bisections (`_feasible`; torus_0: the first phase's curl round the tube rests nowhere,
# halved it stands off it, 20.6 -> 14.7 mm)
LIFT_TRIES = 3  # a search step that goes deeper is lifted back along the normal at most this many times (`_lifted`)
ANCHOR_RADIUS = 0.02  # m: the anchor stays this close to where the device snapped onto the target
MAX_STEPS = 40  # Levenberg-Marquardt trials
SCREEN_STEPS = 12  # `refine_best`: every bounded search of ours' two starts is tried for this many trials, then
FINISHED = 3  # ... only this many of them, those whose ends lie nearest the target, searched on to MAX_STEPS and only
# the nearest of those settled (issue 37's ninth session: 40 corpus shapes x 3 starts, CPU median 38 -> 30 ms, mean
# MSD 9.136 -> 9.068 mm; 4 trials and 2 finished took 26 ms for 9.385 mm: a short search's end does not tell well
# where it ends, docs/approximation.md)
DAMPING = 1e-3  # initial damping, relative to the normal matrix's diagonal
# a step expected to lower the sum by less than this fraction, or two kept steps in a row that did, end the
# search (with the tail objective and the two-step end, 3e-3 took 1 ms more in the benchmark's median for
# the same mean MSD and HD drops to 0.5 %; with the one-step end, 1e-4 took about twice 3e-3's time)
TOLERANCE = 6e-3
FLOOR = 0.75  # the bounded searches' steps keep every sample's linearised S above FLOOR x INSIDE_LIMIT deep
# (`_kept_out`; the lift of a trial still too deep leaves its deepest sample half the limit deep: the floor between.
# Lifted after each trial instead, a step that took a sample deeper was refused or lifted off, and the search ended
# at the bound short of where it slides along it: ours' mean MSD 9.07 -> 6.8 mm on the 40 corpus shapes x 3 starts,
# docs/approximation.md, "Issue 37's tenth session")
FLOOR_SLACK = 5e-5  # m: a sample predicted this little below that floor is let be
ACTIVE_STEPS = 8  # at most this many samples join the step's active set (`_kept_out`)
ANCHOR_DEPTH = 0.5e-3  # m: the anchor may sit this far inside the target, no farther (on the SDF grid)
TAIL = 2e-2  # m: inside the target, a sample's residual grows as S sqrt(1 + (S/TAIL)^2) (module docstring)
ON_LIMIT = 1e-5  # m: an anchor this close to a bound (its depth, the ball) is on it
THROUGH_COS = -0.5  # a flap's line leaving the target by a face whose normal is more than 120 deg from the one it
# entered by has passed through it (a wall, a plate, a tube); a corner it cuts (90 deg) or a face it presses is not


def refine(fields: Fields, spec: DeviceSpec, local: np.ndarray, root_pose: np.ndarray, angles: np.ndarray,
           widths: np.ndarray, centre: np.ndarray, radius: float = ANCHOR_RADIUS) -> tuple[np.ndarray, np.ndarray, bool]:
    """The refined (root pose 4x4, hinge angles rad, whether it rests on the target from outside) from the
    pipeline's root pose and angles.

    local: (n_flaps, M, 3) sample points in each flap's frame at its width (m); widths (m)
    stay as given; centre (3,) m: the snapped anchor, which the anchor stays within
    `radius` of (of the point above it the start was lifted to, where no nearer start rests: `_feasible`).
    The whole search runs compiled (`_search`, every bounded search to its end).
    Where no start rests from outside (`_feasible`), the pose returned is the pipeline's, unrolled, and False.
    """
    return refine_best(fields, spec, local, np.array(root_pose, float)[None], np.array(angles, float)[None],
                       widths, centre, radius, screen=MAX_STEPS)


def refine_best(fields: Fields, spec: DeviceSpec, local: np.ndarray, root_poses: np.ndarray, angles: np.ndarray,
                widths: np.ndarray, centre: np.ndarray, radius: float = ANCHOR_RADIUS,
                screen: int = SCREEN_STEPS) -> tuple[np.ndarray, np.ndarray, bool]:
    """`refine` from several of the pipeline's poses at once (root poses (n, 4, 4), hinge angles (n, n_hinges) rad),
    screened (`_search`): every bounded search of every pose is tried for `screen` trials (SCREEN_STEPS), and only the
    FINISHED whose ends lie nearest the target on the grid are searched on; of those the nearest kept and settled.
    Where no start rests, the first pose's as `refine` returns it, and False."""
    widths = np.asarray(widths, float)
    finish = FINISHED if screen < MAX_STEPS else len(SCALES) + len(OWN_SCALES)  # every search to its end: all of them
    return _search(fields.grid, _device(spec), np.ascontiguousarray(local, dtype=float), _fine(spec, widths),
                   np.ascontiguousarray(root_poses, dtype=float), np.ascontiguousarray(angles, dtype=float),
                   widths, np.asarray(centre, float), float(radius), float(spec.depth),
                   screen, finish)


def _fine(spec: DeviceSpec, widths: np.ndarray) -> np.ndarray:
    """The touch surface's samples (n_flaps, M, 3) in each flap's frame at these widths (m) every METRIC_SPACING, as
    the resting bar samples it (twin.morphpatch.resting): where the search's end is settled (`_settled`)."""
    return _fine_layout(spec).local(widths)


@lru_cache(maxsize=8)
def _fine_layout(spec: DeviceSpec):
    return grid_layout(spec, METRIC_SPACING)


def objective(fields: Fields, spec: DeviceSpec, local: np.ndarray, root_pose, angles, widths) -> float:
    """The refinement's objective at a pose, sum of r(S)^2 (m^2; module docstring): what it lowers."""
    return _costs(fields, spec, local, root_pose, angles, widths)[0]


def grid_msd(fields: Fields, spec: DeviceSpec, local: np.ndarray, root_pose, angles, widths) -> float:
    """The mean |S| (m) of a pose's samples on the grid: what the MSD measures (on the exact mesh), and what picks
    among the refinement's results from different starts (the sum of squares picked, on seed 0's cup_3 from over
    its rim, an end 13.6 mm MSD, its anchor 11.6 mm down the cavity, over one at 11.4 mm on the rim)."""
    return _costs(fields, spec, local, root_pose, angles, widths)[2]


def _costs(fields: Fields, spec: DeviceSpec, local: np.ndarray, root_pose, angles, widths) -> tuple:
    """`_cost` of a pose. (Every argument passed: called from Python with its defaults left out, numba's dispatch
    took 260 us a call where this takes 30.)"""
    return tuple(float(v) for v in _cost(fields.grid, _device(spec), np.ascontiguousarray(local, dtype=float),
                                         np.ascontiguousarray(root_pose[:3, :3], dtype=float),
                                         np.array(root_pose[:3, 3], float), np.asarray(angles, float),
                                         np.asarray(widths, float), np.inf, None))


def flaps_through(fields: Fields, spec: DeviceSpec, root_pose, angles, widths) -> int:
    """How many flaps of a pose pass through the target (module docstring; root pose 4x4 m, hinge angles rad,
    flap widths m): what the refinement does not add to, for any pose."""
    return int(_through_at(fields.grid, _device(spec), np.asarray(angles, float), np.asarray(widths, float),
                           np.ascontiguousarray(root_pose, dtype=float), 0.5 * spec.depth))


@lru_cache(maxsize=8)
def _device(spec: DeviceSpec) -> tuple:
    """What the compiled search needs of the device: flap boxes, hinges (`_hinges`), root flap, hinge limit."""
    return flap_boxes(spec), _hinges(spec), int(spec.root_flap), float(spec.hinge_limit)


def flap_gap(spec: DeviceSpec, angles) -> float:
    """The smallest gap (m) between flaps two or more apart at these hinge angles (rad); negative where they
    overlap (`_flap_gap`)."""
    return float(_flap_gap(_device(spec)[0], np.asarray(angles, float)))


def uncurled(spec: DeviceSpec, angles) -> np.ndarray:
    """The hinge angles (rad) if no flaps touch there, else the angles unrolled from the tips until none do
    (`_uncurled`)."""
    return _uncurled(_device(spec)[0], np.asarray(angles, float), int(spec.root_flap))


@numba.njit(cache=True)
def _search(grid, device, local, fine, root_poses, angles, widths, centre, radius, depth, screen, finish):
    """Levenberg-Marquardt within the bounds (module docstring) from each of the pipeline's root poses (n, 4, 4) and
    hinge angles (n, n_hinges) rad, in two phases: first with the bound on depth left to the objective's tail (as
    before issue 37: from the pipeline's pose, which may lie in the target), then from where that ended, lifted until
    it rests (`_feasible`), with the bound kept: from each of its resting starts (curled as the first phase ended,
    halved, flat: each, also where the first phase's end rests as it is, which had left the plates' flat pose
    untried: plate_0 6.9 -> 3.3 mm on two starts of bench_reachable's), and from the pipeline's own pose (OWN_SCALES)
    flat, and curled where it rests as it is, or lifted until it rests where the first phase's end curled (as it
    ended or eased) rests nowhere (seed 0's height_field_3 start 1: the first phase curled the flaps under the slab,
    which no lift along the root's normal frees, and the halved and flat ends stand on its side wall, 13.7 mm; the
    pipeline's curl lifted, 4.7 mm; lifted always, a search more on most starts for the same fits elsewhere) (`_starts`).
    Every such bounded search of every pose is tried for `screen` trials; in the order of their ends' mean |S| on the
    grid (what the MSD measures), searched on for the rest of MAX_STEPS until `finish` of them are taken (an end the
    snapped anchor does not reach in a straight line is not: seed 0's cup_1, issue 37); the one nearest the target
    kept and its anchor settled (`_settled`). `refine` runs every search to its end
    (`screen` MAX_STEPS), `refine_best` screens them. (One start, the best by the objective before searching, left
    ours 11.0 % above the best pose within its bounds (median over ten corpus shapes), 24.7 % worst; all of the first
    phase's, 9.1 % and 17.4 %: docs/approximation.md, "How far the bounds allow". The pipeline's pose too: where it
    rests already, the first phase can dive into the target from it and every lift of its end rest farther off,
    7.80 mm MSD on an ellipsoid start where the pipeline's pose rested at 7.15 mm. Starting the bounded search from
    the pipeline's pose lifted alone left a can's wrap 7 mm above it, MSD 14 mm, where the first phase ends on it at
    2.6 mm.) (Root pose 4x4, hinge angles rad, whether the pose rests on the target from outside; where none rests,
    the first pose's, unrolled, and False.)"""
    half = 0.5 * depth
    n, per = root_poses.shape[0], len(SCALES) + len(OWN_SCALES)
    rots, anchors = np.empty((n * per, 3, 3)), np.empty((n * per, 3))
    scaled, centres = np.empty((n * per, angles.shape[1])), np.empty((n * per, 3))
    chords = np.empty(n * per)
    count = 0
    fallback = (root_poses[0][:3, :3].copy(), root_poses[0][:3, 3].copy(), angles[0].copy())
    for s in range(n):
        rot0, _, angles0, r, a, g, c = _starts(grid, device, local, root_poses[s], angles[s], widths, centre, radius,
                                               depth)
        if s == 0:
            fallback = (rot0, root_poses[0][:3, 3].copy(), angles0)
        for k in range(len(r)):
            rots[count], anchors[count], scaled[count], centres[count] = r[k], a[k], g[k], c[k]
            chords[count] = max(PATH_DEPTH, _path_dip(grid, c[k], a[k]))
            count += 1
    fits = np.empty(count)
    for k in range(count):  # the short searches
        r, a, g, _ = _descend(grid, device, local, rots[k], anchors[k].copy(), scaled[k].copy(), widths,
                              centres[k].copy(), radius, half, INSIDE_LIMIT, 0, False, chords[k], screen)
        rots[k], anchors[k], scaled[k] = r, a, g
        fits[k] = _cost(grid, device, local, r, a, g, widths)[2]
    ends = np.full(count, np.inf)  # the searched-on ends' mean |S|
    order = np.argsort(fits, kind="mergesort")
    taken = done = 0
    while taken < finish and done < count:
        k = order[done]
        done += 1
        r, a, g = rots[k], anchors[k], scaled[k]
        if screen < MAX_STEPS:
            r, a, g, _ = _descend(grid, device, local, r, a.copy(), g.copy(), widths, centres[k].copy(), radius,
                                  half, INSIDE_LIMIT, 0, False, chords[k], MAX_STEPS - screen)
        if not _path_clear(grid, centre, a, CHORD_DEPTH):
            continue
        rots[k], anchors[k], scaled[k] = r, a, g
        ends[k] = _cost(grid, device, local, r, a, g, widths)[2]
        taken += 1
    if count == 0 or ends.min() == np.inf:
        return _pose(fallback[0], fallback[1]), fallback[2], False
    k = np.argmin(ends)
    return _pose(rots[k], _settled(grid, device, fine, rots[k], anchors[k], scaled[k], widths, half, centre)), \
        scaled[k], True


@numba.njit(cache=True)
def _starts(grid, device, local, root_pose, angles, widths, centre, radius, depth):
    """The bounded searches' starts of `_search` from the pipeline's pose (root pose 4x4, hinge angles rad): the
    first phase (no bound on depth but the objective's) from it, then the starts that rest (`_feasible`) from where
    that ended and from the pipeline's own pose. (The pipeline's rotation, anchor and hinge angles unrolled; per
    start that rests its rotation (n, 3, 3), anchor (n, 3) m, hinge angles (n, n_hinges) rad and the centre of its
    anchor's ball (n, 3) m.)"""
    boxes, _, root_flap, _ = device
    rot0 = root_pose[:3, :3].copy()
    unrolled = _too_close(boxes, angles)  # the pipeline's pose with flaps too close: the search starts apart
    half = 0.5 * depth
    angles0 = _uncurled(boxes, angles, root_flap)
    anchor0 = _bounded(grid, root_pose[:3, 3].copy(), centre, radius)
    passing = _through_at(grid, device, angles0, widths, _pose(rot0, anchor0), half)
    rot, anchor, angles, passing = _descend(grid, device, local, rot0, anchor0, angles0, widths, centre, radius, half,
                                            np.inf, passing, unrolled, CHORD_DEPTH, MAX_STEPS)
    lifted, scaled, centres, resting = _feasible(grid, device, local, rot, anchor, angles, widths, half, centre, radius,
                                                 SCALES)
    own = _feasible(grid, device, local, rot0, anchor0, angles0, widths, half, centre, radius, OWN_SCALES)
    as_is = _distance(own[0][0], anchor0) == 0.0 and (own[1][0] == angles0).all()
    n = len(SCALES) + len(OWN_SCALES)
    rots, anchors, angles_out, centres_out = np.empty((n, 3, 3)), np.empty((n, 3)), np.empty((n, len(angles))), \
        np.empty((n, 3))
    count = 0
    for k in range(n):  # the first phase's end at each scale; then the pipeline's pose
        if k < len(SCALES):
            if not resting[k]:
                continue
            r0, a0, g0, c0 = rot, lifted[k], scaled[k], centres[k]
        else:  # the pipeline's curl where it rests as it is or the first phase's end curled rests nowhere; flat
            j = k - len(SCALES)
            if not own[3][j] or (j == 0 and resting[0] and not as_is):
                continue
            r0, a0, g0, c0 = rot0, own[0][j], own[1][j], own[2][j]
        rots[count], anchors[count], angles_out[count], centres_out[count] = r0, a0, g0, c0
        count += 1
    return rot0, anchor0, angles0, rots[:count], anchors[:count], angles_out[:count], centres_out[:count]


@numba.njit(cache=True)
def _descend(grid, device, local, rot, anchor, angles, widths, centre, radius, half, inside_limit, passing, unrolled,
             chord_depth, steps):
    """One Levenberg-Marquardt search from a state: no sample deeper than inside_limit (m; inf: no bound but
    the objective's), no more flaps through the target than `passing`. (rot, anchor, angles, flaps through.)
    Within the bound on depth, each step keeps the samples' linearised S above FLOOR x inside_limit deep (`_kept_out`),
    and a kept state's anchor must be reached from the snapped one in a straight line
    no deeper than the start's anchor is (at least PATH_DEPTH), not CHORD_DEPTH: a slide round a cup's bottom
    edge to its wall cut the edge 4 mm deep on the exact mesh, which the grid's rounded edge hid; and held to
    PATH_DEPTH alone, a start whose own chord dipped 1-2 mm (the first phase's end at the edge of the ball on a
    convex target) never kept a step (docs/approximation.md, "Where the bounded search stalled")."""
    boxes, _, _, limit = device
    start = (rot, anchor, angles, passing)
    kept = start  # the last state whose anchor the snapped one reaches in a straight line
    lin = np.empty((local.shape[0], local.shape[1], 7))  # per sample S and its gradient's rows (`_normal_equations`)
    mfs = np.empty((local.shape[0], 6 + len(angles), 6))
    cost, jtj, jtr, s_anchor, g_anchor = _evaluate(grid, device, local, rot, anchor, angles, widths, lin, mfs)
    damping = DAMPING
    small = 0
    frozen = np.zeros(len(angles), np.bool_)  # hinges a refused step curled into contact, held until a step is kept
    may_hold = unrolled  # only a search that starts unrolled at the contact holds hinges (module docstring)
    for _ in range(steps):
        basis = _free_directions(jtr, s_anchor, g_anchor, anchor, centre, radius)
        for k in np.flatnonzero(frozen):
            basis[6 + k, :] = 0.0
        lhs = basis.T @ jtj @ basis
        lhs = lhs + damping * np.diag(np.diag(lhs) + 1e-12)
        if inside_limit == np.inf:
            step = -_times(basis, _solved(_cholesky(lhs), basis.T @ jtr))
        else:
            step = _kept_out(lhs, basis.T @ jtr, basis, lin, mfs, -FLOOR * inside_limit)
        if -(2.0 * jtr @ step + step @ jtj @ step) < TOLERANCE * cost:  # the model expects no real gain
            if not frozen.any():
                break
            frozen[:] = False  # ... without the held hinges: let them go, and refuse as before until a step is kept
            may_hold = False
            continue
        new_angles = np.minimum(np.maximum(angles + step[6:], -limit), limit)
        if _too_close(boxes, new_angles):  # refused; the hinges it curled further are held, and
            curling = frozen | (np.abs(new_angles) > np.abs(angles))  # the step tried again without them
            if may_hold and (curling & ~frozen).any():
                frozen = curling
                continue
            damping *= 4.0  # else refused like a step that does not lower the sum
            continue
        new_rot = _rodrigues(step[3:6].copy()) @ rot
        new_anchor = _bounded(grid, anchor + step[:3], centre, radius)
        if not _path_clear(grid, anchor, new_anchor):  # through the target: off the side the device came from
            damping *= 4.0
            continue
        new_anchor, new_cost, deepest = _lifted(grid, device, local, new_rot, new_anchor, new_angles, widths,
                                                inside_limit, cost if inside_limit == np.inf else np.inf)
        if deepest > inside_limit or not _path_clear(grid, anchor, new_anchor) or \
                _distance(new_anchor, centre) > radius:  # deeper than allowed, or lifted out of the ball: refused
            damping *= 4.0
            continue
        lower = new_cost < cost
        through = _through_at(grid, device, new_angles, widths, _pose(new_rot, new_anchor), half) \
            if lower else passing  # (the costlier checks only for a step that lowers the sum)
        if through > passing:  # a flap through the target: refused like a collision
            damping *= 4.0
            continue
        if lower:
            trial = _evaluate(grid, device, local, new_rot, new_anchor, new_angles, widths, lin, mfs)
            gain = cost - trial[0]
            rot, anchor, angles, passing = new_rot, new_anchor, new_angles, through
            held = frozen.any()  # a small gain with hinges held is not the search's end: they are let go now
            frozen[:] = False
            may_hold = unrolled
            if _path_clear(grid, centre, anchor, chord_depth):
                kept = (rot, anchor, angles, passing)
            cost, jtj, jtr, s_anchor, g_anchor = trial
            damping *= 0.3
            small = small + 1 if gain < TOLERANCE * (cost + gain) and not held else 0
            if small == 2:
                break
        else:
            damping *= 4.0
    if kept[3] > start[3]:  # no step adds a flap through the target; the anchor pulled into its ball may have
        return start
    return kept  # each step's path clear, the whole way from the snapped anchor not always


@numba.njit(cache=True)
def _kept_out(lhs, grad, basis, lin, mfs, floor):
    """The damped step (in the full parameters) minimising the model 1/2 z^T lhs z + grad^T z over the columns of
    `basis` with every sample's linearised S kept at or above `floor` (m): S_j + (M_f w_j) . step >= floor, lin
    (n_flaps, M, 7) each sample's S and raw rows w_j = (g, x cross g), mfs (n_flaps, n, 6) each flap's M_f
    (`_normal_equations`). Active set: the sample the step takes furthest below the floor joins it, the step is
    solved with those samples on the floor, one whose multiplier is negative leaves it (at most ACTIVE_STEPS).
    lhs is factored once (`_cholesky`); each sample that joins costs one solve with its factor, lhs^-1 a_j."""
    n, m = basis.shape
    factor = _cholesky(lhs)
    z0 = _solved(factor, grad)
    for i in range(m):
        z0[i] = -z0[i]
    z = z0
    rows = np.empty((ACTIVE_STEPS, m))  # the active samples' constraint rows a_j (in the basis' coordinates)
    cols = np.empty((ACTIVE_STEPS, m))  # ... and lhs^-1 a_j
    need = np.empty(ACTIVE_STEPS)
    count = 0
    u = np.empty(6)
    w = np.empty(n)
    for _ in range(ACTIVE_STEPS):
        step = _times(basis, z)
        worst, wf, wp = -FLOOR_SLACK, -1, -1
        for f in range(lin.shape[0]):
            for k in range(6):
                total = 0.0
                for i in range(n):
                    total += mfs[f, i, k] * step[i]
                u[k] = total
            for p in range(lin.shape[1]):
                v = lin[f, p, 0] - floor
                for k in range(6):
                    v += lin[f, p, 1 + k] * u[k]
                if v < worst:
                    worst, wf, wp = v, f, p
        if wf < 0:
            break
        for i in range(n):  # the sample's row: basis^T M_f w_j
            total = 0.0
            for k in range(6):
                total += mfs[wf, i, k] * lin[wf, wp, 1 + k]
            w[i] = total
        for j in range(m):
            total = 0.0
            for i in range(n):
                total += basis[i, j] * w[i]
            rows[count, j] = total
        cols[count] = _solved(factor, rows[count])
        need[count] = floor - lin[wf, wp, 0]
        count += 1
        while count > 0:
            s_mat = np.empty((count, count))
            rhs = np.empty(count)
            for i in range(count):
                for j in range(count):
                    s_mat[i, j] = _dot(rows[i], cols[j])
                rhs[i] = need[i] - _dot(rows[i], z0)
            ridge = 1e-12 * (np.trace(s_mat) + 1e-30)
            for i in range(count):
                s_mat[i, i] += ridge
            mu = _solved(_cholesky(s_mat), rhs)
            j = np.argmin(mu)
            if mu[j] >= 0.0:
                z = z0.copy()
                for i in range(count):
                    z += mu[i] * cols[i]
                break
            rows[j:count - 1] = rows[j + 1:count].copy()
            cols[j:count - 1] = cols[j + 1:count].copy()
            need[j:count - 1] = need[j + 1:count].copy()
            count -= 1
        if count == 0:
            z = z0
    return _times(basis, z)


@numba.njit(cache=True)
def _times(a, x):
    """a @ x for a small matrix (n, m) and vector (m,), in loops (numba's @ is a BLAS call each, which costs more)."""
    out = np.zeros(a.shape[0])
    for i in range(a.shape[0]):
        total = 0.0
        for j in range(a.shape[1]):
            total += a[i, j] * x[j]
        out[i] = total
    return out


@numba.njit(cache=True)
def _dot(a, b):
    """a . b of two short vectors, in a loop."""
    total = 0.0
    for i in range(len(a)):
        total += a[i] * b[i]
    return total


@numba.njit(cache=True)
def _cholesky(a):
    """The lower Cholesky factor of a small symmetric positive definite matrix (in loops: a LAPACK call through numba
    costs more than the factorisation of a 12 x 12 matrix)."""
    n = a.shape[0]
    low = np.zeros((n, n))
    for j in range(n):
        d = a[j, j]
        for k in range(j):
            d -= low[j, k] * low[j, k]
        d = math.sqrt(max(d, 1e-300))
        low[j, j] = d
        for i in range(j + 1, n):
            total = a[i, j]
            for k in range(j):
                total -= low[i, k] * low[j, k]
            low[i, j] = total / d
    return low


@numba.njit(cache=True)
def _solved(low, b):
    """x with (low low^T) x = b, low a lower Cholesky factor (`_cholesky`)."""
    n = len(b)
    x = np.empty(n)
    for i in range(n):
        total = b[i]
        for k in range(i):
            total -= low[i, k] * x[k]
        x[i] = total / low[i, i]
    for i in range(n - 1, -1, -1):
        total = x[i]
        for k in range(i + 1, n):
            total -= low[k, i] * x[k]
        x[i] = total / low[i, i]
    return x


@numba.njit(cache=True)
def _lifted(grid, device, local, rot, anchor, angles, widths, inside_limit, bound):
    """A trial state projected back onto the bound on depth: where a sample lies deeper in the target than
    inside_limit (m), the anchor lifted along the root's normal by the excess (and half the limit), at most
    LIFT_TRIES times, and no more once a lift leaves more than half the excess it met (a step that curls a flap
    into the target, which no lift of the root mends: the step is refused; 14 % fewer sums in the bounded searches,
    the same results on eight corpus shapes: docs/approximation.md, "How far the bounds allow"). (anchor (3,) m, the
    sum of r(S)^2 m^2 there, inf where a lift leaves it deeper than the limit, the deepest sample's depth m: after a
    lift by `_deepest`, which need not place every sample.) Without a bound on depth (inside_limit inf: nothing is
    lifted) the sum stops once it exceeds `bound`, the sum the trial must beat (`_cost`): the same steps kept, a
    refused trial's scan cut short."""
    normal = rot[:, 2].copy()
    values = np.empty((local.shape[0], local.shape[1]))
    cost, deepest, _ = _cost(grid, device, local, rot, anchor, angles, widths, bound, values)
    for _ in range(LIFT_TRIES):
        if deepest <= inside_limit:
            break
        excess = deepest - inside_limit
        lift = deepest - 0.5 * inside_limit
        anchor = anchor + lift * normal
        deepest = _deepest(grid, device, local, rot, anchor, angles, widths, values, lift)
        cost = _cost(grid, device, local, rot, anchor, angles, widths)[0] \
            if deepest <= inside_limit else np.inf  # (the sum only where the lift rests: one still too deep is refused)
        if deepest - inside_limit > 0.5 * excess:
            break
    return anchor, cost, deepest


@numba.njit(cache=True)
def _settled(grid, device, fine, rot, anchor, angles, widths, half, centre):
    """The anchor (3,) m of a search's end lifted along the root's normal until no sample of `fine` (the touch
    surface every 2 mm, the resting bar's samples) is deeper in the target than INSIDE_LIMIT on the grid (by the
    excess, at most LIFT_STEPS times; only a lift that makes the deepest shallower, not one whose path crosses the
    target, nor one the snapped anchor `centre` (3,) m does not reach in a straight line to CHORD_DEPTH, nor one that
    puts a flap through it). The search holds its 5 mm samples to the limit: a sharp edge (the
    stairs' noses) can poke between them, 0.7 mm deeper on curved_stairs start 37 of the fresh-start test (seed 13),
    which with the grid's rounding of that edge (0.9 mm) put the exact deepest point 3.07 mm inside, over the 3 mm
    bar."""
    normal = rot[:, 2].copy()
    values = np.empty((fine.shape[0], fine.shape[1]))
    deepest = _cost(grid, device, fine, rot, anchor, angles, widths, np.inf, values)[1]
    for _ in range(LIFT_STEPS):  # (a sample on a flap turned from the root's plane rises by less than the lift)
        if deepest <= INSIDE_LIMIT:
            break
        lifted = anchor + (deepest - INSIDE_LIMIT) * normal
        lower = _deepest(grid, device, fine, rot, lifted, angles, widths, values, deepest - INSIDE_LIMIT)
        if lower >= deepest or not _path_clear(grid, anchor, lifted) or \
                not _path_clear(grid, centre, lifted, CHORD_DEPTH) or \
                _through_at(grid, device, angles, widths, _pose(rot, lifted), half) > 0:
            break  # a lift that brings another sample deeper (a face the normal points into), or crosses: not taken
        anchor, deepest = lifted, lower
    return anchor


@numba.njit(cache=True)
def _feasible(grid, device, local, rot, anchor, angles, widths, half, centre, radius, scales):
    """The starts that rest on the target from outside (no sample deeper than INSIDE_LIMIT, no flap through
    it): the hinge angles times each of `scales`, each lifted along the root's normal
    (never through the target, nor where the snapped anchor does not reach it in a straight line, at most
    LIFT_REACH) until it rests (by the excess depth each time, at least LIFT_MIN, at most LIFT_STEPS times:
    `_rest_lift`); a scale that rests at no lift where the next flatter one does is eased towards it, the most curl
    that rests taken (CURL_STEPS bisections); only those within the anchor's ball about `centre` where any is.
    Where one left the ball, its ball's centre goes up with it along the normal: the search goes on about the point
    above the snapped one the device was lifted to. Per scale (anchor (3,) m, hinge angles rad, the
    ball's centre (3,) m), and which of them rest (bool): the bounded search runs from each (`_search`)."""
    n = len(scales)
    anchors, scaled, centres = np.empty((n, 3)), np.empty((n, len(angles))), np.empty((n, 3))
    found, out_of_ball = np.zeros(n, np.bool_), np.zeros(n, np.bool_)
    for i in range(n - 1, -1, -1):  # flattest first: a curl that rests nowhere is eased towards the next flatter
        scaled[i] = angles * scales[i]
        found[i], out_of_ball[i], anchors[i], centres[i] = _rest_lift(grid, device, local, rot, anchor, scaled[i],
                                                                      widths, half, centre, radius)
        if found[i] or i == n - 1 or not found[i + 1]:
            continue
        lo, hi = scales[i + 1], scales[i]  # the most curl between a scale that rests and one that does not
        for _ in range(CURL_STEPS):
            mid = 0.5 * (lo + hi)
            rests, out, p, c = _rest_lift(grid, device, local, rot, anchor, angles * mid, widths, half, centre, radius)
            if rests:
                lo = mid
                found[i], out_of_ball[i], anchors[i], centres[i], scaled[i] = True, out, p, c, angles * mid
            else:
                hi = mid
    if (found & ~out_of_ball).any():  # a start within the anchor's ball is preferred to one lifted out of it
        found &= ~out_of_ball
    return anchors, scaled, centres, found


@numba.njit(cache=True)
def _rest_lift(grid, device, local, rot, anchor, angles, widths, half, centre, radius):
    """The pose lifted along the root's normal until it rests (`_feasible`): (whether it does within LIFT_REACH,
    whether that left the anchor's ball about `centre`, the lifted anchor (3,) m, the ball's centre (3,) m, lifted
    with it where it left the ball)."""
    normal = rot[:, 2].copy()
    lift = step = 0.0
    values = np.empty((local.shape[0], local.shape[1]))
    for k in range(LIFT_STEPS):
        p = anchor + lift * normal
        if lift > LIFT_REACH or not _path_clear(grid, anchor, p) or not _path_clear(grid, centre, p, CHORD_DEPTH):
            break  # too far, through the target, or off the side the device came from
        if k == 0:
            deepest = _cost(grid, device, local, rot, p, angles, widths, np.inf, values)[1]
        else:  # moved by the last lift's step since
            deepest = _deepest(grid, device, local, rot, p, angles, widths, values, step)
        if deepest <= INSIDE_LIMIT and _through_at(grid, device, angles, widths, _pose(rot, p), half) == 0:
            out = _distance(p, centre) > radius
            lifted_centre = centre + ((p - centre) @ normal) * normal if out else centre
            if out and not _path_clear(grid, centre, lifted_centre, CHORD_DEPTH):
                break  # the ball's centre lifted with it would be off the side the device came from
            return True, out, p, lifted_centre
        step = max(deepest - 0.5 * INSIDE_LIMIT, LIFT_MIN)
        lift += step
    return False, False, anchor.copy(), centre.copy()


@numba.njit(cache=True)
def _pose(rot, anchor):
    """The 4x4 pose of a rotation (3, 3) and an anchor (3,)."""
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = anchor
    return pose


@numba.njit(cache=True)
def _through_at(grid, device, angles, widths, root_pose, half):
    """_flaps_through of the device at a pose (root pose 4x4, hinge angles rad, flap widths m)."""
    _, hinges, root_flap, _ = device
    return _flaps_through(grid, _chain(hinges[1] * angles, widths, root_flap, root_pose), half)


@numba.njit(cache=True)
def _flaps_through(grid, frames, half):
    """How many flaps pass through the target (module docstring): each flap's centre line, y from -+half (m)
    to 0 in its frame, walked from either end, going into the target (deeper than PATH_DEPTH) and out of it
    (S above 0) where the normal it leaves by opposes the one it came in by. The walk's samples are every
    PATH_STEP or so; where S is far from what would change the walk's state (going in, or coming out), the samples
    S cannot reach it by are skipped (`LIPSCHITZ`): the same state at every sample walked, the same count."""
    count = 0
    n = int(half / PATH_STEP)
    step = half / n
    for f in range(frames.shape[0]):
        through = False
        for end in (-1.0, 1.0):
            inside = False
            gin = np.zeros(3)
            k = 0
            while k <= n and not through:
                y = end * half * (1.0 - k / n)
                x, yy, z = frames[f, 0, 3] + frames[f, 0, 1] * y, frames[f, 1, 3] + frames[f, 1, 1] * y, \
                    frames[f, 2, 3] + frames[f, 2, 1] * y
                v = _value(grid, x, yy, z)  # the gradient only where the line goes in or out
                if not inside and v < -PATH_DEPTH:
                    inside = True
                    _, gin[0], gin[1], gin[2] = _interpolate(grid, x, yy, z)
                elif inside and v > 0.0:
                    inside = False
                    _, gx, gy, gz = _interpolate(grid, x, yy, z)
                    if gin[0] * gx + gin[1] * gy + gin[2] * gz < THROUGH_COS * math.sqrt(
                            (gin[0] ** 2 + gin[1] ** 2 + gin[2] ** 2) * (gx * gx + gy * gy + gz * gz)):
                        through = True
                room = -v if inside else v + PATH_DEPTH  # how far S is from changing the state
                k += max(1, int(room / (LIPSCHITZ * step)))
        count += through
    return count


@numba.njit(cache=True)
def _too_close(boxes, angles):
    """Whether two flaps two or more apart come closer than FLAP_APART at these hinge angles (rad)."""
    return _flap_gap(boxes, angles) < FLAP_APART


@numba.njit(cache=True)
def _flap_gap(boxes, angles):
    """The smallest gap (m) between two flaps two or more apart at these hinge angles (rad), minus their overlap
    where they overlap: each flap the collision box of twin.device.flap_collision (`flap_boxes`) seen along the
    hinges, a rectangle in the x-z plane; the gap of two rectangles that do not overlap is the shortest of their
    corner-to-edge distances, the overlap the smallest along their edges' normals (the separating-axis test)."""
    signs, widths, root_flap, half = boxes
    frames = _chain(signs * angles, widths, root_flap, np.eye(4))
    n = frames.shape[0]
    corners = np.empty((n, 4, 2))
    for i in range(n):
        for c in range(4):
            along = half[0] if c == 1 or c == 2 else -half[0]
            behind = 2.0 * half[1] if c >= 2 else 0.0
            corners[i, c, 0] = frames[i, 0, 3] + along * frames[i, 0, 0] - behind * frames[i, 0, 2]
            corners[i, c, 1] = frames[i, 2, 3] + along * frames[i, 2, 0] - behind * frames[i, 2, 2]
    reach = 2.0 * math.hypot(half[0], 2.0 * half[1])  # two rectangles whose centres are farther apart cannot touch
    gap = np.inf
    for i in range(n):
        for j in range(i + 2, n):
            dx, dz = frames[j, 0, 3] - frames[i, 0, 3], frames[j, 2, 3] - frames[i, 2, 3]
            if math.hypot(dx, dz) - reach > gap:
                continue
            gap = min(gap, _rectangle_gap(corners[i], corners[j]))
    return gap


@numba.njit(cache=True)
def _rectangle_gap(p, q):
    """The gap (m) between two rectangles of corners p, q (4, 2) in order, minus their overlap where they overlap."""
    overlap = np.inf
    for poly in (p, q):
        for k in range(2):
            ex, ez = poly[k + 1, 0] - poly[k, 0], poly[k + 1, 1] - poly[k, 1]
            norm = math.hypot(ex, ez)
            nx, nz = -ez / norm, ex / norm
            a_lo = b_lo = np.inf
            a_hi = b_hi = -np.inf
            for c in range(4):
                a, b = p[c, 0] * nx + p[c, 1] * nz, q[c, 0] * nx + q[c, 1] * nz
                a_lo, a_hi, b_lo, b_hi = min(a_lo, a), max(a_hi, a), min(b_lo, b), max(b_hi, b)
            overlap = min(overlap, min(a_hi, b_hi) - max(a_lo, b_lo))
    if overlap > 0.0:
        return -overlap
    gap = np.inf
    for which in range(2):
        a, b = (p, q) if which == 0 else (q, p)
        for c in range(4):
            for k in range(4):
                s0x, s0z, s1x, s1z = b[k, 0], b[k, 1], b[(k + 1) % 4, 0], b[(k + 1) % 4, 1]
                dx, dz = s1x - s0x, s1z - s0z
                t = min(max(((a[c, 0] - s0x) * dx + (a[c, 1] - s0z) * dz) / (dx * dx + dz * dz), 0.0), 1.0)
                gap = min(gap, math.hypot(a[c, 0] - s0x - t * dx, a[c, 1] - s0z - t * dz))
    return gap


@numba.njit(cache=True)
def _uncurled(boxes, angles, root_flap):
    """The angles if no flaps collide there, else angles unrolled from the tips until none do, outermost hinges
    first: for the outermost hinges (one per side), the largest fraction of their angles (bisection) at which
    no flaps collide, turning the left one, the right one or both, whichever changes the angles least; where
    none does, those hinges go flat and the next ones in are tried. Curled flaps meet at their tips, so the
    inner hinges keep their fit (scaling every angle down together cost torus starts of issue 22's corpus
    up to 5 mm of MSD)."""
    if not _too_close(boxes, angles):
        return angles
    a = angles.copy()
    n = len(a)
    for level in range(max(root_flap, n - root_flap), 0, -1):  # hinges `level` flaps out from the root flap
        left, right = root_flap - level, root_flap + level - 1  # hinge k joins flaps k and k + 1
        best, best_change = a, -1.0
        for which in range(3):  # the left hinge, the right one, both
            turned = np.zeros(n, np.bool_)
            if which != 1 and left >= 0:
                turned[left] = True
            if which != 0 and right < n:
                turned[right] = True
            if not turned.any():
                continue
            flat = np.where(turned, 0.0, a)
            if _too_close(boxes, flat):
                continue
            trial = _apart_way(boxes, flat, a)
            change = np.abs(trial - a).sum()
            if best_change < 0.0 or change < best_change:
                best, best_change = trial, change
        if best_change >= 0.0:
            return best
        for k in (left, right):  # no turn of these alone parts the flaps: flat, and the next ones in
            if 0 <= k < n:
                a[k] = 0.0
    return a


@numba.njit(cache=True)
def _apart_way(boxes, apart, to):
    """The hinge angles (rad) farthest along the straight way from `apart` (no flaps in contact) to `to` at which
    no flaps are in contact (bisection, to 1/4096 of the way)."""
    lo, hi = 0.0, 1.0
    for _ in range(12):
        mid = (lo + hi) / 2
        if not _too_close(boxes, apart + mid * (to - apart)):
            lo = mid
        else:
            hi = mid
    return apart + lo * (to - apart)


@numba.njit(cache=True)
def _free_directions(jtr, s_anchor, g_anchor, anchor, centre, radius):
    """Columns spanning the parameter directions a step may take: all, but where the anchor is on one of
    its bounds (as deep as it may go, or on the ball's surface) and the sum would fall by crossing it, not
    across that bound (the surface's normal, the ball's radius): the step slides along it instead."""
    n = len(jtr)
    inwards = s_anchor <= -ANCHOR_DEPTH + ON_LIMIT and jtr[:3] @ g_anchor > 0.0  # the sum falls inwards
    out = anchor - centre
    outwards = _distance(anchor, centre) >= radius - ON_LIMIT and jtr[:3] @ out < 0.0  # ... or outwards
    if not (inwards or outwards):
        return np.eye(n)
    blocked = np.zeros((int(inwards) + int(outwards), 3))
    if inwards:
        blocked[0] = g_anchor
    if outwards:
        blocked[-1] = out
    _, sv, vt = np.linalg.svd(blocked)
    rank = int(np.sum(sv > 1e-9 * sv[0]))
    basis = np.zeros((n, n - rank))
    basis[:3, :3 - rank] = vt[rank:].T  # orthonormal, across none of the blocked directions
    basis[3:, 3 - rank:] = np.eye(n - 3)
    return basis


@numba.njit(cache=True)
def _out_of_target(grid, p):
    """p if it is no deeper in the target than ANCHOR_DEPTH, else the point at that depth that Newton's
    steps along grad S reach from it."""
    for _ in range(3):
        v, gx, gy, gz = _interpolate(grid, p[0], p[1], p[2])
        if v >= -ANCHOR_DEPTH:
            break
        g = np.array([gx, gy, gz])
        p = p - (v + ANCHOR_DEPTH) * g / max(g @ g, 1e-12)
    return p


@numba.njit(cache=True)
def _evaluate(grid, device, local, rot, anchor, angles, widths, lin, mfs):
    """(sum of r(S)^2 m^2, J^T J, J^T r, S and grad S at the anchor) at one state; J over (anchor, rotation,
    hinge angles). lin, mfs: `_normal_equations`' per-sample S and rows, per-flap maps (written)."""
    _, hinges, root_flap, _ = device
    moved, sign, inner, half = hinges
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = anchor
    frames = _chain(sign * angles, widths, root_flap, pose)
    # hinge h turns the flaps beyond it about axis a_h through q_h on its inner flap's outer edge
    n_hinges = len(inner)
    axes = np.empty((n_hinges, 3))
    on_axis = np.empty((n_hinges, 3))
    for h in range(n_hinges):
        f = inner[h]
        for i in range(3):
            axes[h, i] = frames[f, i, 1] * sign[h]
            on_axis[h, i] = frames[f, i, 3] + frames[f, i, 0] * half[h] * widths[f]
    cost, jtj, jtr = _normal_equations(grid, frames, local, moved, axes, on_axis, anchor, lin, mfs)
    v, gx, gy, gz = _interpolate(grid, anchor[0], anchor[1], anchor[2])
    return cost, jtj, jtr, v, np.array([gx, gy, gz])


@numba.njit(cache=True)
def _cost(grid, device, local, rot, anchor, angles, widths, bound=np.inf, values=None):
    """(The sum of r(S)^2 m^2, the deepest sample's depth in the target m, 0 if none is inside, the mean |S| m) at
    one state, without derivatives: what a trial step is judged by (the sum), and a search's ends (the mean |S|:
    `_search`). The sum grows flap by flap: once it exceeds `bound` (m^2) the scan stops, the sum returned above
    `bound` and the rest partial (a trial of the first phase that cannot lower the sum it must beat). values
    (n_flaps, M), where given: each sample's S (m) is written into it (where a lift starts from: `_deepest`)."""
    _, hinges, root_flap, _ = device
    frames = _chain(hinges[1] * angles, widths, root_flap, _pose(rot, anchor))
    cost, lowest, total = 0.0, 0.0, 0.0
    for f in range(local.shape[0]):
        for p in range(local.shape[1]):
            x, y, z = _placed(frames[f], local[f, p])
            r = _value(grid, x, y, z)
            if values is not None:
                values[f, p] = r
            lowest = min(lowest, r)
            total += abs(r)
            t = min(r, 0.0) / TAIL
            cost += r * r * (1.0 + t * t)
        if cost > bound:
            break
    return cost, -lowest, total / (local.shape[0] * local.shape[1])


@numba.njit(cache=True)
def _deepest(grid, device, local, rot, anchor, angles, widths, bounds, moved):
    """`_cost`'s deepest sample's depth in the target (m, 0 if none is inside) at a state the last one scanned was
    moved from, by a translation of at most `moved` (m; a lift: the same turn and hinge angles), without placing
    every sample. bounds (n_flaps, M): S at each sample there (`_cost`'s values), or a lower bound of it; S moves by
    at most LIPSCHITZ times the distance (twin.morphpatch.fields), so a sample whose bound less that cannot be deeper
    than the deepest found is skipped: the same depth as `_cost`'s, its S the same number where it is placed. The
    bounds are brought to this state (the samples placed: their S)."""
    _, hinges, root_flap, _ = device
    frames = _chain(hinges[1] * angles, widths, root_flap, _pose(rot, anchor))
    bounds -= LIPSCHITZ * moved
    first = np.argmin(bounds)  # the one deepest before first: the deepest found soon skips the rest
    f0, p0 = first // bounds.shape[1], first % bounds.shape[1]
    x, y, z = _placed(frames[f0], local[f0, p0])
    bounds[f0, p0] = _value(grid, x, y, z)
    lowest = min(0.0, bounds[f0, p0])
    for f in range(local.shape[0]):
        for p in range(local.shape[1]):
            if bounds[f, p] < lowest:
                x, y, z = _placed(frames[f], local[f, p])
                r = _value(grid, x, y, z)
                bounds[f, p] = r
                lowest = min(lowest, r)
    return -lowest


@numba.njit(cache=True)
def _placed(frame, q):
    """A point q (3,) of a flap's frame (4x4) in the world, as three scalars (m)."""
    return (frame[0, 3] + frame[0, 0] * q[0] + frame[0, 1] * q[1] + frame[0, 2] * q[2],
            frame[1, 3] + frame[1, 0] * q[0] + frame[1, 1] * q[1] + frame[1, 2] * q[2],
            frame[2, 3] + frame[2, 0] * q[0] + frame[2, 1] * q[1] + frame[2, 2] * q[2])


@lru_cache(maxsize=8)
def _hinges(spec: DeviceSpec) -> tuple:
    """Per spec: which flaps each hinge turns (n_flaps, n_hinges), each hinge's axis sign, its inner flap,
    and the side (+-1/2 of the inner flap's width) its axis lies on."""
    outer = outer_flap(spec)
    beyond = outer > spec.root_flap
    moved = np.zeros((spec.n_flaps, spec.n_hinges))
    for h, o in enumerate(outer):
        if beyond[h]:
            moved[o:, h] = 1.0
        else:
            moved[:o + 1, h] = 1.0
    return moved, hinge_axis_sign(spec).astype(float), np.where(beyond, outer - 1, outer + 1), np.where(beyond, 0.5, -0.5)


@numba.njit(cache=True, fastmath={"reassoc", "contract"})
def _normal_equations(grid, frames, local, moved, axes, on_axis, anchor, lin, mfs):
    """Sum of r(S)^2, J^T J (n, n) and J^T r (n,) over the flaps' samples `local` (n_flaps, M, 3) placed by
    their frames, S and grad S interpolated on the grid as they are placed (no arrays of points). Written: lin
    (n_flaps, M, 7) each sample's S (m) and raw rows w = (g, x cross g), mfs (n_flaps, n, 6) each flap's M_f.

    A sample's Jacobian row is linear in w = r'(S) (g, x cross g): row = M_f w, with M_f fixed per flap
    (module docstring), so the samples are summed per flap as w w^T and w r first.
    """
    n_flaps, n_hinges = moved.shape
    ww = np.empty((n_flaps, 6, 6))
    ws = np.empty((n_flaps, 6))
    rows = np.empty((7, local.shape[1]))  # per sample of one flap: w, then r(S)
    cost = 0.0
    for f in range(n_flaps):
        for p in range(local.shape[1]):
            x, y, z = _placed(frames[f], local[f, p])
            r, gx, gy, gz = _interpolate(grid, x, y, z)
            lin[f, p, 0], lin[f, p, 1], lin[f, p, 2], lin[f, p, 3] = r, gx, gy, gz
            lin[f, p, 4], lin[f, p, 5], lin[f, p, 6] = y * gz - z * gy, z * gx - x * gz, x * gy - y * gx
            t = min(r, 0.0) / TAIL  # the residual r k and its derivative d (module docstring)
            k = math.sqrt(1.0 + t * t)
            d = (1.0 + 2.0 * t * t) / k
            gx, gy, gz = d * gx, d * gy, d * gz
            rows[0, p], rows[1, p], rows[2, p] = gx, gy, gz
            rows[3, p], rows[4, p], rows[5, p] = y * gz - z * gy, z * gx - x * gz, x * gy - y * gx
            rows[6, p] = r * k
        for a in range(7):  # (w, r) summed over the flap's samples as outer products
            for b in range(a, 7):
                total = 0.0
                for p in range(local.shape[1]):
                    total += rows[a, p] * rows[b, p]
                if b < 6:
                    ww[f, a, b] = ww[f, b, a] = total
                elif a < 6:
                    ws[f, a] = total
                else:
                    cost += total
    n = 6 + n_hinges
    jtj = np.zeros((n, n))
    jtr = np.zeros(n)
    mf = np.zeros((n, 6))
    mw = np.empty((n, 6))
    for f in range(n_flaps):
        mf[:] = 0.0
        for i in range(3):
            mf[i, i] = 1.0  # anchor: g
            mf[3 + i, 3 + i] = 1.0  # rotation: x cross g - anchor cross g
        c = anchor
        mf[3, 1], mf[3, 2] = c[2], -c[1]
        mf[4, 0], mf[4, 2] = -c[2], c[0]
        mf[5, 0], mf[5, 1] = c[1], -c[0]
        for h in range(n_hinges):
            if moved[f, h] != 0.0:  # a . (x cross g) - (a cross q) . g
                a0, a1, a2 = axes[h, 0], axes[h, 1], axes[h, 2]
                q0, q1, q2 = on_axis[h, 0], on_axis[h, 1], on_axis[h, 2]
                mf[6 + h, 0], mf[6 + h, 1], mf[6 + h, 2] = -(a1 * q2 - a2 * q1), -(a2 * q0 - a0 * q2), -(a0 * q1 - a1 * q0)
                mf[6 + h, 3], mf[6 + h, 4], mf[6 + h, 5] = a0, a1, a2
        mfs[f] = mf
        for i in range(n):  # J^T J += M_f ww M_f^T, J^T r += M_f ws, in loops (BLAS calls cost more here)
            for b in range(6):
                mw[i, b] = 0.0
                for a in range(6):
                    mw[i, b] += mf[i, a] * ww[f, a, b]
            for j in range(i + 1):
                total = 0.0
                for b in range(6):
                    total += mw[i, b] * mf[j, b]
                jtj[i, j] += total
            for a in range(6):
                jtr[i] += mf[i, a] * ws[f, a]
    for i in range(n):
        for j in range(i):
            jtj[j, i] = jtj[i, j]
    return cost, jtj, jtr


@numba.njit(cache=True)
def _bounded(grid, p, centre, radius):
    """p moved out of the target (to ANCHOR_DEPTH); if that is farther than `radius` from the centre (the
    snapped anchor, on the surface), pulled back just inside the ball and out of the target again, or,
    if that still leaves the ball, the farthest point out of the target towards p that does not, to 1/64
    of the way (bisection along centre -> p: only pulling a point on a convex target back into the ball
    would cut a chord through it, 2 mm deep for 20 mm on the cone)."""
    q = _out_of_target(grid, p)
    if _distance(q, centre) <= radius:
        return q
    pulled = _out_of_target(grid, centre + (q - centre) * (0.999 * radius / _distance(q, centre)))
    if _distance(pulled, centre) <= radius:  # a step along the ball's surface leaves it by a hair
        return pulled
    lo, hi, best = 0.0, 1.0, centre.copy()
    for _ in range(6):
        mid = (lo + hi) / 2
        q = _out_of_target(grid, centre + mid * (p - centre))
        if _distance(q, centre) <= radius:
            lo, best = mid, q
        else:
            hi = mid
    return best


@numba.njit(cache=True)
def _distance(a, b):
    d = a - b
    return math.sqrt(d @ d)


@numba.njit(cache=True)
def _rodrigues(w):
    """Rotation matrix of the rotation vector w (rad)."""
    theta = math.sqrt(w @ w)
    if theta < 1e-12:
        return np.eye(3)
    k = w / theta
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * kx + (1.0 - math.cos(theta)) * (kx @ kx)
