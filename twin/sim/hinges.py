"""Where each hinge lives in a MuJoCo model (joint, dof, gearbox output, actuator, encoder), placing the
hinges, the physics steps per firmware tick, and when collision detection may be skipped."""

from __future__ import annotations

import mujoco
import numpy as np

from twin.device.flap_collision import apart_spreads
from twin.device.spec import DeviceSpec


def contact_free_spreads(spec: DeviceSpec, model: mujoco.MjModel) -> np.ndarray:
    """`apart`'s spreads for a model whose only colliding geoms are the spec's flap boxes, neighbours
    excluded and no explicit pairs (the generated device); empty for any other model (a scene with
    target shapes), where collision detection is never skipped."""
    n = spec.n_flaps
    flaps = np.array([model.body(f"flap{i}").id for i in range(n)])
    geoms = np.array([model.geom(f"flap{i}_collision").id for i in range(n)])
    colliding = np.flatnonzero(model.geom_contype | model.geom_conaffinity)
    neighbours = {(min(a, b) << 16) + max(a, b) for a, b in zip(flaps[:-1], flaps[1:])}
    size = [(spec.flap_pitch - spec.flap_gap) / 2, spec.depth / 2, spec.thickness / 2]
    if (model.npair or set(model.exclude_signature) != neighbours or not np.array_equal(colliding, np.sort(geoms))
            or np.any(model.geom_type[geoms] != mujoco.mjtGeom.mjGEOM_BOX)
            or not np.allclose(model.geom_size[geoms], size, rtol=1e-8, atol=0)):
        return np.zeros(0)
    return apart_spreads(spec, float(model.geom_margin[geoms].max()))


def place_hinges(qpos, hinges: "Hinges", angles) -> None:
    """Put each flap at its hinge angle (rad) and its gearbox output with it, mid-backlash (in qpos)."""
    qpos[hinges.qadr] = angles
    qpos[hinges.gear_qadr] = angles


def physics_substeps(spec: DeviceSpec, model: mujoco.MjModel) -> int:
    """Physics steps per firmware tick (the duty is held between them): the one rule every runner uses."""
    return max(1, round(spec.firmware_dt / model.opt.timestep))


class Hinges:
    """Addresses of each hinge's joint and dof (the flap), the joint and dof its motor turns (the gearbox
    output, beyond the backlash; the flap's own where there is none), its actuator and encoder."""

    def __init__(self, model: mujoco.MjModel, n: int):
        self.qadr = np.array([model.joint(f"hinge{k}").qposadr[0] for k in range(n)], np.int64)
        self.dadr = np.array([model.joint(f"hinge{k}").dofadr[0] for k in range(n)], np.int64)
        gear = [model.joint(model.actuator_trnid[model.actuator(f"motor{k}").id, 0]) for k in range(n)]
        self.gear_qadr = np.array([j.qposadr[0] for j in gear], np.int64)  # the flap's own without backlash
        self.gear_dof = np.array([j.dofadr[0] for j in gear], np.int64)
        self.enc = np.array([model.sensor(f"encoder{k}").adr[0] for k in range(n)], np.int64)
        act = [model.actuator(f"motor{k}").id for k in range(n)]
        if act != list(range(n)):
            raise ValueError("actuators must be declared in hinge order")

