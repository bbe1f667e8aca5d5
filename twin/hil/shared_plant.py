"""A plant the shared calibration can represent, and its recording: what the calibration tests
(tests/tuning/test_tuning_hil.py) and benchmarks/bench_calibration.py (`--repeat`) record and calibrate.

SHARED_PLANT and ALIKE are the emulator's options for it (every hinge alike, no cogging, no friction ripple,
windings that do not warm), `shared_truth` the same plant as a spec (the twin given the emulator's own values);
`record_soft` wakes the emulated device and records a training run (`training_scenario`) and a held-out one (HOLDOUT)
with soft gains, whose slow creeps show the friction in the duty.
"""

from __future__ import annotations

import math

import numpy as np

from controllers.pid import PidGains
from twin.device.spec import DeviceSpec
from twin.device.variation import scaled
from twin.formats.scenario import read_scenario, scenario_of_steps, write_scenario
from twin.hil.mirror import mirror
from twin.hil.record import run_hil
from twin.link.serial_link import Link


def training_scenario(duration: float, t1: float, t2: float):
    """The training scenario "steps": three targets, at 0, t1 and t2 s, over duration s (twin.formats.scenario)."""
    return scenario_of_steps("steps", [(0.0, [30, 20, 10, 10, 20, 30]), (t1, [5, 40, 25, 0, -10, 60]),
                                       (t2, [8, 8, 8, 8, 8, 8])], duration)


HOLDOUT = scenario_of_steps("holdout", [(0.0, [45, 5, 20, 30, 10, 15]), (0.6, [10, 30, 5, 15, 50, 40]),
                                        (1.2, [25, 15, 35, 5, 20, 0])], 1.8)

SHARED_SCALES = {"no_load_speed": 0.75, "gear_friction": 1.6, "rotor_inertia": 1.3, "gear_damping": 1.0}
SHARED_BACKLASH_DEG = 0.05
OPTION = {"no_load_speed": "--speed-scale", "gear_friction": "--friction-scale", "rotor_inertia": "--armature-scale",
          "gear_damping": "--damping-scale"}  # the emulator's option for each
SHARED_PLANT = (*(a for p, x in SHARED_SCALES.items() for a in (OPTION[p], str(x))),
                "--backlash-deg", str(SHARED_BACKLASH_DEG))  # the calibration tests' plant, as the emulator's options
# every hinge alike, no cogging, no ripple, windings that do not warm: a plant the shared fit can represent
ALIKE = ("--hinge-scale", "1", "--cogging-pct", "0", "--ripple-pct", "0", "--winding-c", "25", "--no-warming")
WAKE_TOLERANCE_DEG = 30.0  # the limp boot pose (hanging under gravity) parts this far from the twin's flat


def shared_truth(spec: DeviceSpec) -> DeviceSpec:
    """SHARED_PLANT, ALIKE, as a spec: the twin given the emulator's own values (no cogging: ALIKE has none)."""
    return scaled(spec, SHARED_SCALES).replace(backlash=math.radians(SHARED_BACKLASH_DEG), cogging=0.0)


def record_soft(emu, spec: DeviceSpec, folder):
    """Wake the emulated device (emu: its port in `emu.port`) and record a training run and a held-out one with
    soft gains (slow creeps: friction shows in the duty), another recipe than the calibration scenario's
    (tests/hil/test_calibration_profile.py); returns the two run folders and a path for the calibrated spec.
    RuntimeError where the device did not come to flat."""
    soft = PidGains.from_spec(spec).replace(kp=0.015, ki=0.05, kd=0.0003)
    train, hold = folder / "train", folder / "hold"
    write_scenario(folder / "a.toml", training_scenario(2.0, 0.7, 1.4))
    write_scenario(folder / "b.toml", HOLDOUT)
    with Link(emu.port) as link:
        woken = mirror(link, spec, np.zeros(spec.n_hinges), tolerance_deg=WAKE_TOLERANCE_DEG)
        if not woken.ok:
            raise RuntimeError(f"the device did not come to flat: {woken.message}")
        run_hil(link, spec, read_scenario(folder / "a.toml", spec), train, gains=[soft] * spec.n_hinges)
        run_hil(link, spec, read_scenario(folder / "b.toml", spec), hold, gains=[soft] * spec.n_hinges)
    return train, hold, folder / "cal.toml"
