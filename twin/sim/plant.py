"""The emulated device's body: the twin's own drive train and MuJoCo model, with parameters nobody told the twin.

The plant is the twin's model (twin.device.mjcf: gearbox output joints, backlash as a dead zone
between gearbox output and flap, LuGre friction) built from a spec whose uncertain parameters are
drawn at random within ranges (`PlantRanges`, `draw_plant`), driven by the twin's drive model
(twin.sim.drive: pack, drivers, decay, current limit, gearbox efficiency). The encoder is on the
motor, inside the loop; the backlash is outside it. The encoder's fault is the one hardware
shows: edges missed now and then, which accumulate (the count drifts from the shaft), never
independent +-1 noise. Each firmware tick is `sense()` (positions and sensors at the start of the
tick, encoder counts) then `actuate(pwm, decay)` (the drive held for the tick's physics steps),
the same sequence and physics steps as the twin's loop.
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
from twin.device.variation import SPREAD, scaled
from twin.sim.drive import drive, drive_params
from twin.sim.hinges import Hinges, physics_substeps


@dataclasses.dataclass(frozen=True)
class PlantOptions:
    """How one emulated plant differs from the spec: scales on its parameters, its backlash and encoder, its pack."""

    speed_scale: float = 1.0  # no_load_speed x (the motor constant / x)
    friction_scale: float = 1.0  # gear_friction and gear_stiction x
    damping_scale: float = 1.0  # gear_damping x
    armature_scale: float = 1.0  # rotor_inertia x
    backlash_deg: float = 0.0  # dead zone between gearbox output and flap, deg (full width)
    encoder_miss: float = 0.0  # probability that the counter misses an edge (they accumulate)
    pack_voltage: float | None = None  # V, the pack's open-circuit voltage (None: the spec's supply_voltage)
    lying_flat: bool = False  # on a table (the flaps cannot fold below it), not held up by the root flap


@dataclasses.dataclass(frozen=True)
class PlantRanges:
    """(low, high) per drawn parameter; low == high fixes it. The defaults are the documented ranges
    (docs/device.md "The emulator's plant"): the device's spread about its spec
    (twin.device.variation.SPREAD), the backlash from none to the spread's top, the link's latency."""

    speed_scale: tuple[float, float] = SPREAD["no_load_speed"]
    friction_scale: tuple[float, float] = SPREAD["gear_friction"]
    damping_scale: tuple[float, float] = SPREAD["gear_damping"]
    armature_scale: tuple[float, float] = SPREAD["rotor_inertia"]
    backlash_deg: tuple[float, float] = (0.0, 0.5)  # deg: SPREAD's top x the spec's 0.25 deg
    latency_ms: tuple[float, float] = (0.0, 3.0)

    def __post_init__(self):
        for f in dataclasses.fields(self):
            lo, hi = getattr(self, f.name)
            low, high = RANGE_LIMITS[f.name]
            if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi or lo < low or hi > high:
                raise ValueError(f"{f.name}: range {lo:g}..{hi:g} must be finite, low <= high, within "
                                 f"{low:g}..{high:g}")


# what a drawn parameter may be at all: a plant the twin's model still simulates (a scale of 0 divides by
# zero; a backlash of degrees is a broken gearbox, not a tolerance; latency beyond 100 ms is no USB link)
RANGE_LIMITS = {"speed_scale": (0.1, 10.0), "friction_scale": (0.0, 10.0), "damping_scale": (0.0, 10.0),
                "armature_scale": (0.1, 10.0), "backlash_deg": (0.0, 5.0), "latency_ms": (0.0, 100.0)}


def draw_plant(ranges: PlantRanges, rng: random.Random, encoder_miss: float = 0.0,
               pack_voltage: float | None = None) -> tuple[PlantOptions, float]:
    """A plant drawn uniformly within the ranges, and its command latency (ms)."""
    v = {f.name: rng.uniform(*getattr(ranges, f.name)) for f in dataclasses.fields(ranges)}
    latency = v.pop("latency_ms")
    return PlantOptions(**v, encoder_miss=encoder_miss, pack_voltage=pack_voltage), latency


def as_twin(spec: DeviceSpec) -> PlantOptions:
    """The plant the twin of `spec` simulates (its backlash included, nothing scaled, no encoder fault)."""
    return PlantOptions(backlash_deg=math.degrees(spec.backlash))


def plant_spec(spec: DeviceSpec, opt: PlantOptions) -> DeviceSpec:
    """The emulated device's physical spec: the twin's, scaled."""
    body = scaled(spec, {"no_load_speed": opt.speed_scale, "gear_friction": opt.friction_scale,
                         "gear_damping": opt.damping_scale, "rotor_inertia": opt.armature_scale})
    return body.replace(backlash=math.radians(opt.backlash_deg),
                        supply_voltage=spec.supply_voltage if opt.pack_voltage is None else opt.pack_voltage)


class Plant:
    """The hinges, gearmotors, drivers, pack and encoders of one emulated device."""

    def __init__(self, spec: DeviceSpec, opt: PlantOptions, rng: random.Random):
        self.spec = plant_spec(spec, opt)
        self.opt = opt
        self.rng = rng
        self.model = load_model(self.spec, table=opt.lying_flat)
        self.data = mujoco.MjData(self.model)
        self.substeps = physics_substeps(self.spec, self.model)
        n = self.spec.n_hinges
        self.hinges = Hinges(self.model, n)
        self.params = drive_params(self.spec)
        mujoco.mj_resetDataKeyframe(self.model, self.data, self.model.key("flat").id)
        mujoco.mj_forward(self.model, self.data)
        self.bus = self.spec.supply_voltage  # V, the battery voltage the firmware reads
        self.current = np.zeros(n)  # A, winding current of the last tick
        scratch = mujoco.MjData(self.model)  # the drive model compiled (or loaded) now, so the first tick is on time
        drive(self.params, np.zeros(n, np.float32), np.zeros(n, np.uint8), scratch.qvel, self.hinges.gear_dof,
              scratch.ctrl, scratch.qfrc_applied, np.zeros(n))
        self._shaft = self._shaft_counts()  # the counts the shaft has turned through
        self.missed = np.zeros(n, np.int64)  # edges the counter missed, signed: they accumulate
        self.counts = self._shaft - self.missed

    @property
    def angles(self) -> np.ndarray:
        """True hinge (flap) angles, rad."""
        return self.data.qpos[self.hinges.qadr].copy()

    def sense(self) -> np.ndarray:
        """Start a tick: positions, velocities and sensors now; returns the encoder counts."""
        mujoco.mj_step1(self.model, self.data)
        shaft = self._shaft_counts()
        edges = shaft - self._shaft
        self._shaft = shaft
        p = self.opt.encoder_miss
        if p > 0:
            for k in np.flatnonzero(edges):
                self.missed[k] += int(np.sign(edges[k])) * sum(self.rng.random() < p for _ in range(abs(edges[k])))
        self.counts = shaft - self.missed
        return self.counts

    def actuate(self, pwm, decay) -> None:
        """Finish the tick: the drive (the core's PWM and decay per hinge) held over the tick's physics steps."""
        d = self.data
        self.bus = drive(self.params, np.asarray(pwm, np.float32), np.asarray(decay, np.uint8), d.qvel,
                         self.hinges.gear_dof, d.ctrl, d.qfrc_applied, self.current)
        mujoco.mj_step2(self.model, d)
        for _ in range(self.substeps - 1):
            mujoco.mj_step(self.model, d)

    def hold_hinge(self, k: int, angle: float) -> None:
        """Lock flap k at angle (rad): a jam (the gearbox behind it stops at the backlash's end)."""
        self.data.qpos[self.hinges.qadr[k]] = angle
        self.data.qvel[self.hinges.dadr[k]] = 0.0

    def _shaft_counts(self) -> np.ndarray:
        return counts_from_motor_angles(self.data.sensordata[self.hinges.enc], self.spec.counts_per_motor_rev)
