"""CBS, the paper's collision-based simulation baseline, in MuJoCo with real contact.

"A collision-driven configuration by incrementally bending the flaps until contact
with the target surface is established ... without any explicit optimization":

1. the root gets the same snap and alignment the methods get (the pipeline's steps
   1-4, twin.morphpatch.approximation.root_pose: the anchor on the target, the root
   turned to it), turned over so the touch surface faces the target, and is held there
   (by the hand: the root is welded, so MuJoCo does not collide it with the static target);
2. the hinges bend from the root outward, the two beside the root first, then the next
   pair, then the tips. Each bends in the direction that closes its own flap's gap:
   MuJoCo's contacts, probed along the hinge's range both ways with the rest of the device
   as it stands, give the nearer angle where the flap meets the target (or, for a flap
   whose straight continuation already cuts into it, the nearer angle where it comes
   free; within CUT_IN it rests on it already and stays), and the firmware drives the
   hinge there. Flaps not yet bent do not collide
   (the user bends one flap onto the target at a time: the unbent rest is not what
   stops it);
3. every flap collides again, 0.2 s of hold, and the end state is read.

Where the target pushes a flap past its range (a flap that cuts into the target at the root's
pose and comes free at no angle in range is thrown out of it once it collides), the firmware
faults (FAULT LIMIT), brakes and refuses further targets: the device stops where it stands, and
so does CBS (3. still follows). Before, the refusal ended the whole Table 1 run (arch, start 9).

Before: the tilted start was pressed along its normal and fixed, and all
hinges ramped together in one direction, so the tips met a convex target first and
held the middle off it (on the cube's flat top 14.8 mm MSD, the middle 20 mm off).
The result is reported in the approximation's convention (touch-surface normal
pointing out of the target), so the two compare directly.
"""

from __future__ import annotations

import math
import time

import mujoco
import numpy as np
import trimesh

from twin.device.kinematics import outer_flap
from twin.device.spec import DeviceSpec
from twin.evaluation.target_collision import CollisionError, collision_error, convex_parts, scene_model
from twin.morphpatch.approximation import root_pose
from twin.morphpatch.fields import build_fields
from twin.records.approximation import Approximation
from twin.sim.targets import TargetError
from twin.sim.twin import Twin

FLIP = np.diag([1.0, -1.0, -1.0, 1.0])  # a half turn about the device's x axis
PROBE_STEP = math.radians(1.0)  # rad between the contact probe's angles
PROBE_RESOLUTION = math.radians(0.1)  # rad: the probe's bisection stops here
CUT_IN = 0.5e-3  # m: a flap this deep in the target or less rests on it; deeper, it cuts in
MOVE_TIME = 1.5  # s the firmware gets to bring a pair of hinges to their contact angles


class CbsSimulator:
    """One target in MuJoCo, ready to run CBS from many starts."""

    def __init__(self, spec: DeviceSpec, mesh: trimesh.Trimesh):
        self.spec = spec
        parts = convex_parts(mesh)
        self.parts = len(parts)
        self.error: CollisionError = collision_error(mesh, parts)
        self.fields = build_fields(mesh)
        self.twin = Twin(spec, model=scene_model(spec, parts))
        m = self.twin.model
        self._probe = mujoco.MjData(m)
        self._target_geoms = {m.geom(f"target{i}").id for i in range(len(parts))}
        self._flap_of_body = {m.body(f"flap{i}").id: i for i in range(spec.n_flaps)}
        self._flap_geom = np.array([m.geom(f"flap{i}_collision").id for i in range(spec.n_flaps)])
        self._contype = m.geom_contype[self._flap_geom].copy()
        self._conaffinity = m.geom_conaffinity[self._flap_geom].copy()
        outer = outer_flap(spec)
        r = spec.root_flap
        # hinges in pairs by their flap's distance from the root: root outward
        self._stages = [[k for k in range(spec.n_hinges) if abs(outer[k] - r) == step]
                        for step in range(1, max(r, spec.n_flaps - 1 - r) + 1)]
        self._outer = outer
        self.last_touching: list[int] = []

    def touching(self, data: mujoco.MjData | None = None) -> set[int]:
        """Flaps in contact with the target now (in the twin, or in `data` after mj_forward)."""
        m, d = self.twin.model, self.twin.data if data is None else data
        out = set()
        for c in d.contact[: d.ncon]:
            g1, g2 = int(c.geom[0]), int(c.geom[1])
            if g1 in self._target_geoms or g2 in self._target_geoms:
                other = g2 if g1 in self._target_geoms else g1
                out.add(self._flap_of_body[int(m.geom_bodyid[other])])
        return out

    def _collide(self, flaps) -> None:
        """Only these flaps collide (with the target and each other)."""
        m = self.twin.model
        on = np.isin(np.arange(self.spec.n_flaps), list(flaps))
        m.geom_contype[self._flap_geom] = np.where(on, self._contype, 0)
        m.geom_conaffinity[self._flap_geom] = np.where(on, self._conaffinity, 0)

    def _place(self, pose: np.ndarray) -> None:
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, np.ascontiguousarray(pose[:3, :3]).ravel())
        self.twin.set_root_pose(pose[:3, 3], quat)

    def _depth(self, data: mujoco.MjData, flap: int) -> float:
        """The flap's deepest penetration into the target (m) in `data` after mj_forward; -1 if it is free."""
        m, deepest = self.twin.model, -1.0
        for c in data.contact[: data.ncon]:
            g1, g2 = int(c.geom[0]), int(c.geom[1])
            if (g1 in self._target_geoms) != (g2 in self._target_geoms):
                other = g2 if g1 in self._target_geoms else g1
                if self._flap_of_body.get(int(m.geom_bodyid[other])) == flap:
                    deepest = max(deepest, -float(c.dist))
        return deepest

    def _contact_angle(self, hinge: int, angles: np.ndarray) -> float | None:
        """The hinge angle (rad, MuJoCo's convention) nearest to angles[hinge] where its flap meets the target
        (or, if it cuts in deeper than CUT_IN now, where it no longer does), probed both ways; None where it
        rests on the target already or meets it neither way."""
        m, d, qadr = self.twin.model, self._probe, self.twin.hinges.qadr
        flap, lim = int(self._outer[hinge]), self.spec.hinge_limit

        def depth(a):
            d.qpos[qadr] = angles
            d.qpos[qadr[hinge]] = a
            mujoco.mj_forward(m, d)
            return self._depth(d, flap)

        now = depth(angles[hinge])
        if 0.0 <= now <= CUT_IN:
            return None
        done = (lambda x: x >= 0.0) if now < 0.0 else (lambda x: x <= CUT_IN)
        found = []
        for sign in (1.0, -1.0):
            prev = angles[hinge]
            while abs(prev) < lim:
                a = float(np.clip(prev + sign * PROBE_STEP, -lim, lim))
                if done(depth(a)):
                    lo, hi = prev, a  # bisect to the first angle that is done
                    while abs(hi - lo) > PROBE_RESOLUTION:
                        mid = (lo + hi) / 2
                        lo, hi = (lo, mid) if done(depth(mid)) else (mid, hi)
                    found.append(hi)
                    break
                prev = a
        return min(found, key=lambda a: abs(a - angles[hinge])) if found else None

    def run(self, start_pose) -> Approximation:
        """CBS from a start pose (4x4, anchor in the world; the approximation's convention).

        Returns the end state as an Approximation (variant "cbs", the physical flap
        widths), so it is measured and written like the methods' own results;
        `self.last_touching` lists the flaps in contact at the end.
        """
        t0 = time.perf_counter()
        twin, spec = self.twin, self.spec
        pose = root_pose(self.fields, start_pose, spec) @ FLIP
        self._place(pose)
        twin.reset()
        targets = np.zeros(spec.n_hinges)
        placed = [spec.root_flap]
        for stage in self._stages:
            for k in stage:
                self._collide(placed + [int(self._outer[k])])
                angle = self._contact_angle(k, twin.angles)
                if angle is not None:
                    targets[k] = angle
            placed += [int(self._outer[k]) for k in stage]
            self._collide(placed)
            try:
                twin.move_to(targets, max_time=MOVE_TIME)
            except TargetError:  # the firmware faulted in the last move and refuses: the device has stopped
                break
        twin.hold(0.2)
        self.last_touching = sorted(self.touching())
        self._collide(range(spec.n_flaps))
        # the hinge stops are soft in MuJoCo: a hinge held against one reads a hair past it
        angles = np.clip(-twin.angles, -spec.hinge_limit, spec.hinge_limit)
        return Approximation(root_pose=pose @ FLIP, angles=angles,
                             widths=np.full(spec.n_flaps, spec.flap_pitch),
                             time=time.perf_counter() - t0, variant="cbs")
