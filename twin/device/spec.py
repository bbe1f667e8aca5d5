"""The device spec: every physical and firmware constant, read from models/vrscroll/spec.toml.

All fields are SI (m, kg, rad, s, V, A, N*m); the file is read (its rpm and degrees converted)
by twin.device.spec_toml, the one home of the spec TOML format. Derived quantities (motor constant, counts per output
revolution, gearbox efficiency, flap mass) are properties so they can never disagree with their inputs.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from twin.device.spec_toml import read_spec_toml
from twin.paths import MODELS_DIR

MAX_HINGES = 8  # the firmware core's VRS_MAX_HINGES (vrs_core.h): hinges one device may have
# Hz, inclusive: a control loop the twin simulates tick by tick and telemetry can follow (the host refuses a
# device reporting another in HELLO); beyond it a morph's trace is unbounded (a design's loop rate of 1e9 Hz
# once asked for 89 GiB), and the core's loop_rate_hz is 16 bits
LOOP_RATE_RANGE = (100, 10_000)
# m: the most a design's row of flaps (length) or its hinges (depth) may measure: a hand-held display (the
# paper's is 0.188 x 0.175 m); it keeps the touch surface's 2 mm metric grid within about 250,000 points (6 MB;
# a design 1e6 m long once asked for 3.9e10, 880 GiB)
MAX_EXTENT = 1.0
SPEC_PATH = MODELS_DIR / "vrscroll" / "spec.toml"


@dataclasses.dataclass(frozen=True)
class DeviceSpec:
    """VRScroll's constants in SI units; see spec.toml for where each comes from."""

    # geometry
    n_flaps: int
    length: float  # m, along the row of flaps (x)
    depth: float  # m, along the hinge axes (y)
    thickness: float  # m
    usable_depth: float  # m
    root_flap: int
    hinge_limit: float  # rad, symmetric about flat
    flap_gap: float  # m
    motor_diameter: float  # m, across the row of flaps (x) and behind the flap (z)
    motor_length: float  # m, along the hinge axis (y)
    # mass
    mass_total: float  # kg
    mass_motor: float  # kg
    mass_electronics: float  # kg
    # motor (output-shaft figures from the datasheet)
    rated_voltage: float  # V
    gear_ratio: float
    no_load_speed: float  # rad/s at the output
    stall_torque: float  # N*m at the output
    stall_current: float  # A
    resistance: float  # ohm
    rotor_inertia: float  # kg*m^2, motor side
    continuous_current: float  # A
    no_load_current: float  # A
    backdrive_efficiency: float  # share of the load's power that reaches the motor when the flap drives it
    gear_friction: float  # N*m at the output, Coulomb
    gear_stiction: float  # N*m at the output, static
    stribeck_speed: float  # rad/s at the output
    gear_damping: float  # N*m*s/rad at the output
    friction_stiffness: float  # N*m/rad at the output (LuGre bristles)
    friction_damping: float  # N*m*s/rad at the output (LuGre bristles)
    cogging: float  # the cogging torque's amplitude, a share of the motor's stall torque at the supply voltage
    cogging_periods: int  # cogging periods per motor revolution
    cogging_phase: float  # rad: the cogging torque is cogging_torque x sin(cogging_periods x motor angle + this)
    backlash: float  # rad, full width of the dead zone between gearbox output and flap
    # encoder
    counts_per_motor_rev: int
    # power
    supply_voltage: float  # V, the pack's open-circuit voltage
    pack_full_voltage: float  # V
    pack_low_voltage: float  # V
    pack_resistance: float  # ohm, shared by every driver
    drive_cap: float  # V at duty 1.0
    driver_on_resistance: float  # ohm, in series with each winding
    driver_current_limit: float  # A, per motor channel: the bridge limits the current here
    driver_peak_current: float  # A, per motor channel: the rating the gate checks
    # firmware
    loop_rate: float  # Hz
    kp: float  # duty per count
    ki: float  # duty per count-second
    kd: float  # duty per count/s
    derivative_cutoff: float  # Hz
    integral_limit: float  # duty
    deadband_duty: float  # duty
    hold_band: int  # counts
    settle_band: int  # counts
    settle_hold: float  # s
    watchdog: float  # s, host quiet this long while ACTIVE -> FAULT
    max_telemetry_rate: float  # Hz
    stall_duty: float  # duty
    stall_counts: int  # counts
    stall_time: float  # s
    limit_margin: int  # counts past the hinge range
    overcurrent: float  # A; 0: current not sensed
    overload_time: float  # s at stall current before the I2t protection derates (the budget's size)
    host_away_hold: float  # s the device holds its targets after the watchdog, before it releases
    # simulation
    timestep: float  # s

    # ---- derived -------------------------------------------------------------
    @property
    def n_hinges(self) -> int:
        return self.n_flaps - 1

    @property
    def flap_pitch(self) -> float:
        """Flap length along x, m (hinge to hinge)."""
        return self.length / self.n_flaps

    @property
    def flap_mass(self) -> float:
        """Mass of one bare flap, kg: what is left of the total after motors and electronics."""
        return (self.mass_total - self.n_hinges * self.mass_motor - self.mass_electronics) / self.n_flaps

    @property
    def counts_per_rev(self) -> float:
        """Encoder counts per output revolution (12 x 100.37 = 1204.44)."""
        return self.counts_per_motor_rev * self.gear_ratio

    @property
    def rad_per_count(self) -> float:
        return 2.0 * math.pi / self.counts_per_rev

    @property
    def motor_constant(self) -> float:
        """K, N*m/A = V*s/rad at the motor shaft, from the datasheet's no-load point: V = R*I0 + K*N*w0."""
        return (self.rated_voltage - self.resistance * self.no_load_current) / (self.gear_ratio * self.no_load_speed)

    @property
    def gearbox_efficiency(self) -> float:
        """Share of the motor's torque (times N) that reaches the output driving, from the datasheet's stall
        point: tau_stall = eta * N * K * I_stall - gear_friction (the stall is where the output stops turning)."""
        return (self.stall_torque + self.gear_friction) / (self.gear_ratio * self.motor_constant * self.stall_current)

    @property
    def drive_resistance(self) -> float:
        """Ohm in each motor's circuit: the winding and the driver's two conducting FETs."""
        return self.resistance + self.driver_on_resistance

    @property
    def cogging_torque(self) -> float:
        """N*m at the motor: the cogging's amplitude, `cogging` x the motor's stall torque at the supply voltage."""
        return self.cogging * self.motor_constant * self.supply_voltage / self.drive_resistance

    @property
    def firmware_dt(self) -> float:
        return 1.0 / self.loop_rate

    def current(self, voltage, speed):
        """Winding current, A, for terminal voltage (V) and output speed (rad/s): (V - K*N*w)/R."""
        return (voltage - self.motor_constant * self.gear_ratio * speed) / self.resistance

    def replace(self, **changes) -> "DeviceSpec":
        """A copy with some fields changed (e.g. a calibrated or perturbed plant)."""
        return dataclasses.replace(self, **changes)


def load_spec(path: str | Path = SPEC_PATH, defaults: DeviceSpec | None = None) -> DeviceSpec:
    """Read a spec TOML (twin.device.spec_toml); every DeviceSpec field must be there exactly once, but for those
    `defaults` gives (a device profile written before an entry was added takes the spec's). ValueError naming the
    file for sizes beyond what the twin allocates for (sizes_beyond_bounds)."""
    spec = DeviceSpec(**read_spec_toml(path, _NAMES, dataclasses.asdict(defaults) if defaults else None)[0])
    beyond = sizes_beyond_bounds(spec)
    if beyond:
        raise ValueError(f"{path}: {'; '.join(beyond)}")
    return spec


def sizes_beyond_bounds(spec: DeviceSpec) -> list[str]:
    """Why the spec's sizes are beyond what the twin allocates for (each naming its bound's constant in
    twin.device.spec): hinges over the firmware core's MAX_HINGES, a loop rate outside LOOP_RATE_RANGE, a length
    or depth over MAX_EXTENT."""
    reasons = []
    if spec.n_hinges > MAX_HINGES:
        reasons.append(f"n_flaps = {spec.n_flaps}: the firmware core drives at most {MAX_HINGES} hinges "
                       f"({MAX_HINGES + 1} flaps, MAX_HINGES)")
    low, high = LOOP_RATE_RANGE
    if not low <= spec.loop_rate <= high:
        reasons.append(f"loop_rate = {spec.loop_rate:g} Hz is outside the {low:g}-{high:g} Hz a control loop may run "
                       "at (LOOP_RATE_RANGE)")
    for key in ("length", "depth"):
        if getattr(spec, key) > MAX_EXTENT:
            reasons.append(f"{key} = {getattr(spec, key):g} m is over a hand-held display's {MAX_EXTENT:g} m "
                           "(MAX_EXTENT)")
    return reasons


def spec_sources(path: str | Path = SPEC_PATH, defaults: DeviceSpec | None = None) -> dict[str, str]:
    """Field name -> where its value came from (paper, datasheet, assumption), as `load_spec` reads it."""
    return read_spec_toml(path, _NAMES, dataclasses.asdict(defaults) if defaults else None)[1]


_NAMES = tuple(f.name for f in dataclasses.fields(DeviceSpec))
