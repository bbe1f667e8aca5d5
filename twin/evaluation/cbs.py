"""CBS, the paper's collision-based simulation baseline, in MuJoCo with real contact.

The device starts at the start pose, turned to face the target with its touch
surface (so the touch surface, not the device's back, meets the target). It moves
along its normal until it touches (the user pressing it on), then the firmware
ramps every hinge to bend the flaps towards the target; a hinge stops where its
own flap meets the target, or where it stalls (contact further out holds it),
or at its limit: a physically plausible end state, no optimisation.
The result is reported in the approximation's convention (touch-surface normal
pointing out of the target), so the two compare directly.
"""

from __future__ import annotations

import math
import time

import mujoco
import numpy as np
import trimesh

from twin.morphpatch.approximation import Approximation
from twin.evaluation.target_collision import CollisionError, collision_error, convex_parts, scene_model
from twin.device.kinematics import outer_flap
from twin.sim.simulation import Twin
from twin.device.spec import DeviceSpec

FLIP = np.diag([1.0, -1.0, -1.0, 1.0])  # a half turn about the device's x axis
RAMP_STEP = math.radians(1.0)  # rad of hinge target per chunk
CHUNK = 0.01  # s of firmware per ramp step: 100 deg/s, well within the motor's speed
SNAP_RESOLUTION = 1e-4  # m
SNAP_REACH = 0.3  # m: a start farther than this from the target along its normal is an error
STALL = math.radians(5.0)  # rad: a hinge this far behind its ramp is held by contact further out


class CbsSimulator:
    """One target in MuJoCo, ready to run CBS from many starts."""

    def __init__(self, spec: DeviceSpec, mesh: trimesh.Trimesh):
        self.spec = spec
        parts = convex_parts(mesh)
        self.parts = len(parts)
        self.error: CollisionError = collision_error(mesh, parts)
        self.twin = Twin(spec, model=scene_model(spec, parts))
        m = self.twin.model
        self._target_geoms = {m.geom(f"target{i}").id for i in range(len(parts))}
        self._flap_of_body = {m.body(f"flap{i}").id: i for i in range(spec.n_flaps)}
        self._outer = outer_flap(spec)

    def touching(self) -> set[int]:
        """Flaps in contact with the target now."""
        m, d = self.twin.model, self.twin.data
        out = set()
        for c in d.contact[: d.ncon]:
            g1, g2 = int(c.geom[0]), int(c.geom[1])
            if g1 in self._target_geoms or g2 in self._target_geoms:
                other = g2 if g1 in self._target_geoms else g1
                out.add(self._flap_of_body[int(m.geom_bodyid[other])])
        return out

    def _place(self, pose: np.ndarray) -> None:
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, np.ascontiguousarray(pose[:3, :3]).ravel())
        self.twin.set_root_pose(pose[:3, 3], quat)

    def _snap(self, facing: np.ndarray) -> np.ndarray:
        """Move the flat device along its normal (towards the target) to the first contact."""
        normal = facing[:3, 2]

        def contact_at(s):
            pose = facing.copy()
            pose[:3, 3] += s * normal
            self._place(pose)
            return bool(self.touching())

        lo, step = 0.0, 0.002
        if contact_at(0.0):  # starts inside: back off until free
            while contact_at(lo):
                lo -= step
                if lo < -SNAP_REACH:
                    raise ValueError("CBS: the start pose is buried in the target")
            hi = lo + step
        else:
            hi = step
            while not contact_at(hi):
                lo, hi = hi, hi + step
                if hi > SNAP_REACH:
                    raise ValueError(f"CBS: the device does not reach the target within {SNAP_REACH * 1e3:.0f} mm "
                                     "along its normal from this start")
        while hi - lo > SNAP_RESOLUTION:
            mid = (lo + hi) / 2
            lo, hi = (lo, mid) if contact_at(mid) else (mid, hi)
        pose = facing.copy()
        pose[:3, 3] += lo * normal
        self._place(pose)
        return pose

    def run(self, start_pose) -> Approximation:
        """CBS from a start pose (4x4, anchor in the world, z the touch normal pointing away from the target).

        Returns the end state as an Approximation (variant "cbs", the physical flap
        widths), so it is measured and written like the method's own results;
        `self.last_touching` lists the flaps in contact at the end.
        """
        t0 = time.perf_counter()
        twin, lim = self.twin, self.spec.hinge_limit
        twin.reset()
        pose = self._snap(np.asarray(start_pose, float) @ FLIP)
        twin.reset()
        targets = np.zeros(self.spec.n_hinges)
        stopped = np.zeros(self.spec.n_hinges, bool)
        for _ in range(int(math.ceil(lim / RAMP_STEP)) + 1):
            touching = self.touching()
            angles = twin.angles
            for k, flap in enumerate(self._outer):
                if stopped[k]:
                    continue
                if flap in touching or targets[k] - angles[k] > STALL:  # its flap meets the target, or it stalls
                    stopped[k], targets[k] = True, float(np.clip(angles[k], -lim, lim))
                else:
                    targets[k] = min(targets[k] + RAMP_STEP, lim)
                    stopped[k] = targets[k] >= lim and angles[k] >= lim - math.radians(2.0)
            if stopped.all():
                break
            twin.move_to(targets, max_time=CHUNK, stop_when_settled=False)
        twin.hold(0.2)
        self.last_touching = sorted(self.touching())
        return Approximation(root_pose=pose @ FLIP, angles=-twin.angles,
                             widths=np.full(self.spec.n_flaps, self.spec.flap_pitch),
                             time=time.perf_counter() - t0, variant="cbs")
