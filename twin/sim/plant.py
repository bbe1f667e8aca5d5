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

A device differs hinge by hinge, and has what the twin leaves out (docs/device.md "The emulator's plant"):
each hinge's motor and gearbox scaled on its own about the shared draw (`HingeDraw`: speed, friction,
damping, armature), and three effects the twin's default model does not have, drawn per hinge:
- cogging: the torque of MuJoCo's dcmotor `cogging` (twin.device.mjcf), amplitude x sin(periods x motor angle +
  phase), its amplitude a share of the motor's stall torque drawn per hinge (the spec's `cogging` is the twin's
  nominal), the spec's `cogging_periods` per motor revolution, its phase against the encoder's edges drawn per
  hinge (the twin's puts the detents mid-count). The plant applies it averaged over the angle the motor turns
  in the tick (`cogging_mean`), not sampled at the tick's start as the dcmotor does: above 10.4 rad/s at the
  output a period passes within the 1 ms step, and the sampled torque aliases into a drag a real rotor does not
  feel (its inertia averages the cogging out), largest where the alias stands still: seed 1's hinge 2 (4.8 %)
  was held near 10.4 rad/s, 9.4 rad/s where the twin without cogging reached 10.4;
- a winding that warms: MuJoCo's dcmotor `thermal` (copper's 0.393 %/K; WINDING_* below), starting at a
  drawn temperature (a device that has been running); the firmware's current reading stays the drive
  model's at the cold resistance (MuJoCo applies the hot one to the torque);
- a friction ripple: the gearbox's Coulomb friction modulated by the final gear's mesh, a share of it,
  sin(2 pi theta / RIPPLE_PERIOD + phase), added at the gearbox output each tick.
The twin may gain any of these; `draw_plant` always draws a ripple above zero, so a drawn plant always
keeps at least one effect the twin does not model.
"""

from __future__ import annotations

import dataclasses
import math
import random

import mujoco
import numpy as np

from controllers.encoder import counts_from_motor_angles
from twin.device.mjcf import load_model, motor_attributes
from twin.device.mount import DEFAULT_MOUNT, check_mount
from twin.device.spec import DeviceSpec
from twin.device.variation import SPREAD, scaled
from twin.sim.drive import drive, drive_params
from twin.sim.hinges import Hinges, physics_substeps


RIPPLE_PERIOD = math.radians(12.0)  # rad of gearbox output: a 30-tooth final gear's mesh (an assumption)
WINDING_RESISTANCE = 40.0  # K/W, winding to ambient: a 12 mm can motor (an assumption; none is published)
WINDING_TIMECONST = 30.0  # s, the winding's thermal time constant (an assumption)
COPPER_TEMPCOEF = 0.00393  # 1/K, copper's resistance
REFERENCE_C = 25.0  # deg C: where the spec's resistance holds, and the ambient


@dataclasses.dataclass(frozen=True)
class HingeDraw:
    """One hinge of an emulated plant: x on top of the shared draw (speed, friction, damping, armature), its
    cogging (a share of the motor's stall torque) and the cogging's phase against the encoder (rad at the
    motor x the spec's cogging_periods), friction ripple (a share of the gearbox's Coulomb friction) and its
    phase (rad), and its winding's temperature at power-on (deg C)."""

    speed: float = 1.0
    friction: float = 1.0
    damping: float = 1.0
    armature: float = 1.0
    cogging: float = 0.0
    ripple: float = 0.0
    ripple_phase: float = 0.0
    winding_c: float = REFERENCE_C
    cogging_phase: float = 0.0


@dataclasses.dataclass(frozen=True)
class PlantOptions:
    """How one emulated plant differs from the spec: scales on its parameters, its backlash and encoder, its pack."""

    speed_scale: float = 1.0  # no_load_speed x (the motor constant / x)
    friction_scale: float = 1.0  # gear_friction and gear_stiction x
    damping_scale: float = 1.0  # gear_damping x
    armature_scale: float = 1.0  # rotor_inertia x
    backdrive_scale: float = 1.0  # backdrive_efficiency x (at most 1 in all)
    backlash_deg: float = 0.0  # dead zone between gearbox output and flap, deg (full width)
    encoder_miss: float = 0.0  # probability that the counter misses an edge (they accumulate)
    pack_voltage: float | None = None  # V, the pack's open-circuit voltage (None: the spec's supply_voltage)
    mount: str = DEFAULT_MOUNT  # how the device is held (twin.device.mount.MOUNTS): its model is the twin's
    hinges: tuple = ()  # a HingeDraw per hinge; empty: every hinge the shared draw's, nothing the twin leaves out
    warming: bool = True  # with hinges: the windings warm as they work (their resistance with them)

    def __post_init__(self):
        check_mount(self.mount, "plant mount")


@dataclasses.dataclass(frozen=True)
class PlantRanges:
    """(low, high) per drawn parameter; low == high fixes it. The defaults are the documented ranges
    (docs/device.md "The emulator's plant"): the device's spread about its spec
    (twin.device.variation.SPREAD), the backlash from none to the spread's top, the link's latency, and per
    hinge: its own spread about those (micro metal gearmotors of one batch differ by 10-20 %), cogging,
    friction ripple and the winding's temperature."""

    speed_scale: tuple[float, float] = SPREAD["no_load_speed"]
    friction_scale: tuple[float, float] = SPREAD["gear_friction"]
    damping_scale: tuple[float, float] = SPREAD["gear_damping"]
    armature_scale: tuple[float, float] = SPREAD["rotor_inertia"]
    backlash_deg: tuple[float, float] = (0.01, 0.5)  # deg: SPREAD x the spec's 0.25 deg (less is no backlash to
    # a 0.3 deg count, and the MJCF makes 0 a rigid coupling: calibration's prior starts there too)
    latency_ms: tuple[float, float] = (0.0, 3.0)
    hinge_scale: tuple[float, float] = (0.85, 1.15)  # each hinge's own x on speed, friction, damping, armature
    cogging_pct: tuple[float, float] = (1.0, 5.0)  # % of the motor's stall torque
    ripple_pct: tuple[float, float] = (5.0, 20.0)  # % of the gearbox's Coulomb friction
    winding_c: tuple[float, float] = (25.0, 45.0)  # deg C at power-on
    backdrive_scale: tuple[float, float] = (0.6, 1.4)  # backdrive_efficiency x (0.3-0.7 about the spec's 0.5)

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
                "armature_scale": (0.1, 10.0), "backlash_deg": (0.0, 5.0), "latency_ms": (0.0, 100.0),
                "hinge_scale": (0.1, 10.0), "cogging_pct": (0.0, 50.0), "ripple_pct": (0.0, 90.0),
                "winding_c": (-20.0, 120.0), "backdrive_scale": (0.05, 2.0)}
PER_HINGE = ("hinge_scale", "cogging_pct", "ripple_pct", "winding_c")  # drawn for each hinge
LAST = ("backdrive_scale",)  # drawn after the hinges: the draws before it are those of a seed before it was added


def draw_plant(ranges: PlantRanges, rng: random.Random, encoder_miss: float = 0.0,
               pack_voltage: float | None = None, n_hinges: int = 6) -> tuple[PlantOptions, float]:
    """A plant drawn uniformly within the ranges, each of its n_hinges hinges' own values too, and its
    command latency (ms)."""
    shared = [f.name for f in dataclasses.fields(ranges) if f.name not in PER_HINGE + LAST]
    v = {name: rng.uniform(*getattr(ranges, name)) for name in shared}
    latency = v.pop("latency_ms")
    hinges = tuple(HingeDraw(*(rng.uniform(*ranges.hinge_scale) for _ in range(4)),
                             cogging=rng.uniform(*ranges.cogging_pct) / 100, ripple=rng.uniform(*ranges.ripple_pct) / 100,
                             ripple_phase=rng.uniform(0.0, 2 * math.pi), winding_c=rng.uniform(*ranges.winding_c))
                   for _ in range(n_hinges))
    v.update({name: rng.uniform(*getattr(ranges, name)) for name in LAST})
    # where each rotor's cogging sits against its encoder's edges: anywhere (drawn after the rest, as LAST)
    hinges = tuple(dataclasses.replace(h, cogging_phase=rng.uniform(0.0, 2 * math.pi)) for h in hinges)
    return PlantOptions(**v, encoder_miss=encoder_miss, pack_voltage=pack_voltage, hinges=hinges), latency


def as_twin(spec: DeviceSpec) -> PlantOptions:
    """The plant the twin of `spec` simulates (its backlash included, nothing scaled, no encoder fault)."""
    return PlantOptions(backlash_deg=math.degrees(spec.backlash))


def plant_spec(spec: DeviceSpec, opt: PlantOptions) -> DeviceSpec:
    """The emulated device's physical spec: the twin's, scaled (what its hinges share)."""
    body = scaled(spec, {"no_load_speed": opt.speed_scale, "gear_friction": opt.friction_scale,
                         "gear_damping": opt.damping_scale, "rotor_inertia": opt.armature_scale})
    return body.replace(backlash=math.radians(opt.backlash_deg),
                        backdrive_efficiency=min(spec.backdrive_efficiency * opt.backdrive_scale, 1.0),
                        supply_voltage=spec.supply_voltage if opt.pack_voltage is None else opt.pack_voltage)


def hinge_specs(body: DeviceSpec, opt: PlantOptions) -> list[DeviceSpec]:
    """Each hinge's own physical spec: the plant's (plant_spec), scaled by its HingeDraw."""
    return [scaled(body, {"no_load_speed": h.speed, "gear_friction": h.friction, "gear_damping": h.damping,
                          "rotor_inertia": h.armature}) for h in opt.hinges] or [body] * body.n_hinges


def _motor(s: DeviceSpec, h: HingeDraw, warming: bool) -> str:
    """One hinge's dcmotor attributes: its own motor and gearbox, its cogging, its winding's warming."""
    thermal = (f' thermal="{WINDING_RESISTANCE!r} 0 {WINDING_TIMECONST!r} {COPPER_TEMPCOEF!r} {REFERENCE_C!r} '
               f'{REFERENCE_C!r}"') if warming else ""
    return motor_attributes(s.replace(cogging=0.0)) + thermal  # the cogging: Plant.actuate's, averaged


def cogging_mean(angle: np.ndarray, swept: np.ndarray) -> np.ndarray:
    """The mean of sin over [angle, angle + swept] (rad, elementwise): sin(angle) where nothing is swept."""
    small = np.abs(swept) < 1e-6
    safe = np.where(small, 1.0, swept)
    return np.where(small, np.sin(angle), (np.cos(angle) - np.cos(angle + swept)) / safe)


class Plant:
    """The hinges, gearmotors, drivers, pack and encoders of one emulated device."""

    def __init__(self, spec: DeviceSpec, opt: PlantOptions, rng: random.Random):
        self.spec = plant_spec(spec, opt)
        self.opt = opt
        self.rng = rng
        if opt.hinges and len(opt.hinges) != self.spec.n_hinges:
            raise ValueError(f"the plant draws {len(opt.hinges)} hinges; the device has {self.spec.n_hinges}")
        self.hinge_specs = hinge_specs(self.spec, opt)
        motors = [_motor(s, h, opt.warming) for s, h in zip(self.hinge_specs, opt.hinges)] or None
        self.model = load_model(self.spec, mount=opt.mount, motors=motors)  # held as the twin of that mount is
        self.data = mujoco.MjData(self.model)
        self.substeps = physics_substeps(self.spec, self.model)
        n = self.spec.n_hinges
        self.hinges = Hinges(self.model, n)
        self.params = drive_params(self.spec, self.hinge_specs)
        mujoco.mj_resetDataKeyframe(self.model, self.data, self.model.key("flat").id)
        for k, h in enumerate(opt.hinges if opt.warming else ()):  # each winding at its power-on temperature: the
            # dcmotor's thermal state is the winding's rise above the ambient (REFERENCE_C), its resistance
            # R (1 + COPPER_TEMPCOEF x the rise), cooling back to 0 with WINDING_TIMECONST (measured: 20 -> 16.9
            # in 5 s with no current; the keyframe has 0)
            self.data.act[self.model.actuator_actadr[k]] = h.winding_c - REFERENCE_C
        # the friction ripple: per hinge its amplitude (N*m at the gearbox output) and phase
        self._ripple = np.array([[h.ripple * s.gear_friction, h.ripple_phase]
                                 for s, h in zip(self.hinge_specs, opt.hinges)]).reshape(-1, 2)
        # the cogging per hinge (the dcmotor's own is 0): N*m at the motor, and its phase (rad)
        self._cogging = np.array([[s.replace(cogging=h.cogging).cogging_torque, h.cogging_phase]
                                  for s, h in zip(self.hinge_specs, opt.hinges)]).reshape(-1, 2)
        mujoco.mj_forward(self.model, self.data)
        self.bus = self.spec.supply_voltage  # V, the battery voltage the firmware reads
        self.current = np.zeros(n)  # A, winding current of the last tick
        self.decay = np.ones(n, np.uint8)  # each motor's decay the last tick (0 coast: its windings open; 1 brake)
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
        self.decay = np.asarray(decay, np.uint8)
        self.bus = drive(self.params, np.asarray(pwm, np.float32), self.decay, d.qvel, self.hinges.gear_dof, d.ctrl,
                         d.qfrc_applied, self.current)
        for k, (amplitude, phase) in enumerate(self._ripple):  # friction opposes the motion, rippling with the mesh
            g = self.hinges.gear_dof[k]
            theta = d.qpos[self.hinges.gear_qadr[k]]
            d.qfrc_applied[g] -= amplitude * math.sin(2 * math.pi * theta / RIPPLE_PERIOD + phase) * math.tanh(
                d.qvel[g] / self.spec.stribeck_speed)
        if len(self._cogging):  # at the motor, through its gear, averaged over the tick's turn at this speed
            act, n = slice(0, len(self._cogging)), self.spec.cogging_periods
            mean = cogging_mean(n * d.actuator_length[act] + self._cogging[:, 1],
                                n * d.actuator_velocity[act] * self.spec.firmware_dt)
            d.qfrc_applied[self.hinges.gear_dof] += self.model.actuator_gear[act, 0] * self._cogging[:, 0] * mean
        mujoco.mj_step2(self.model, d)
        for _ in range(self.substeps - 1):
            mujoco.mj_step(self.model, d)

    def hold_hinge(self, k: int, angle: float) -> None:
        """Lock flap k at angle (rad): a jam (the gearbox behind it stops at the backlash's end)."""
        self.data.qpos[self.hinges.qadr[k]] = angle
        self.data.qvel[self.hinges.dadr[k]] = 0.0

    def _shaft_counts(self) -> np.ndarray:
        return counts_from_motor_angles(self.data.sensordata[self.hinges.enc], self.spec.counts_per_motor_rev)
