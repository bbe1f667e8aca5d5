"""The emulated device's body: a MuJoCo plant with what the twin's model leaves out.

The plant is the twin's model built from a perturbed spec (`plant_spec`), plus
backlash (as encoder hysteresis) and encoder noise. Each firmware tick is
`sense()` (positions and sensors at the start of the tick, encoder counts) then
`actuate(duty)` (drive voltage held for the tick's physics steps), the same
sequence and physics steps as the twin's loop. The H-bridge always drives with
slow decay (windings shorted at zero duty): the firmware's coast decay (IDLE)
is not modelled.
"""

from __future__ import annotations

import dataclasses
import math
import random

import mujoco
import numpy as np

from controllers.encoder import counts_from_motor_angles
from twin.device.mjcf import load_model
from twin.device.spec import DeviceSpec
from twin.sim.simulation import physics_substeps


@dataclasses.dataclass(frozen=True)
class PlantOptions:
    """How the emulated plant differs from the twin's."""

    friction_scale: float = 1.25  # gear_friction x
    damping_scale: float = 1.2  # gear_damping x
    speed_scale: float = 0.95  # no_load_speed x (so motor constant / 0.95)
    armature_scale: float = 1.0  # rotor_inertia x
    backlash_deg: float = 0.5  # dead zone between hinge and encoder, deg (full width)
    encoder_noise: float = 0.01  # probability per read that a count is off by one


IDEAL = PlantOptions(friction_scale=1.0, damping_scale=1.0, speed_scale=1.0, armature_scale=1.0, backlash_deg=0.0,
                     encoder_noise=0.0)


def plant_spec(spec: DeviceSpec, opt: PlantOptions) -> DeviceSpec:
    """The emulated device's physical spec: the twin's, perturbed."""
    return spec.replace(gear_friction=spec.gear_friction * opt.friction_scale,
                        gear_damping=spec.gear_damping * opt.damping_scale,
                        no_load_speed=spec.no_load_speed * opt.speed_scale,
                        rotor_inertia=spec.rotor_inertia * opt.armature_scale,
                        backlash=math.radians(opt.backlash_deg))


class Plant:
    """The hinges, motors and encoders of one emulated device."""

    def __init__(self, spec: DeviceSpec, opt: PlantOptions, rng: random.Random):
        self.spec = plant_spec(spec, opt)
        self.opt = opt
        self.rng = rng
        self.model = load_model(self.spec)
        self.data = mujoco.MjData(self.model)
        self.substeps = physics_substeps(self.spec, self.model)
        n = self.spec.n_hinges
        self.qadr = np.array([self.model.joint(f"hinge{k}").qposadr[0] for k in range(n)])
        self.dadr = np.array([self.model.joint(f"hinge{k}").dofadr[0] for k in range(n)])
        self.enc = np.array([self.model.sensor(f"encoder{k}").adr[0] for k in range(n)])
        mujoco.mj_resetDataKeyframe(self.model, self.data, self.model.key("flat").id)
        mujoco.mj_forward(self.model, self.data)
        self.measured = self.data.sensordata[self.enc].copy()  # motor angle as the encoder sees it (backlash), rad
        self.current = np.zeros(n)  # A, winding current of the last tick
        self.counts = self._read_counts()

    @property
    def angles(self) -> np.ndarray:
        """True hinge angles, rad."""
        return self.data.qpos[self.qadr].copy()

    def sense(self) -> np.ndarray:
        """Start a tick: positions, velocities and sensors now; returns the encoder counts."""
        mujoco.mj_step1(self.model, self.data)
        self.counts = self._read_counts()
        return self.counts

    def actuate(self, duty) -> None:
        """Finish the tick: drive duty [-1, 1] held over the tick's physics steps."""
        s, d = self.spec, self.data
        volts = np.asarray(duty, float) * s.drive_cap
        d.ctrl[:] = volts
        self.current = (volts - s.motor_constant * s.gear_ratio * d.qvel[self.dadr]) / s.resistance
        mujoco.mj_step2(self.model, d)
        for _ in range(self.substeps - 1):
            mujoco.mj_step(self.model, d)

    def hold_hinge(self, k: int, angle: float) -> None:
        """Lock hinge k at angle (rad): a jam."""
        self.data.qpos[self.qadr[k]] = angle
        self.data.qvel[self.dadr[k]] = 0.0

    def _read_counts(self) -> np.ndarray:
        """Encoder counts: the motor angle through the backlash dead zone, quantized, with noise."""
        s = self.spec
        motor = self.data.sensordata[self.enc]
        half = s.backlash * s.gear_ratio / 2
        self.measured = np.clip(self.measured, motor - half, motor + half)
        counts = counts_from_motor_angles(self.measured, s.counts_per_motor_rev)
        for k in range(len(counts)):
            if self.opt.encoder_noise > 0 and self.rng.random() < self.opt.encoder_noise:
                counts[k] += self.rng.choice((-1, 1))
        return counts
