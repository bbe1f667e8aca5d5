"""A device plant nobody chose: the emulator's parameters drawn at random within the issue's ranges.

The drawn values go to the emulator only (its command line); the twin never sees them. Shared by the
calibration tests and benchmarks/bench_calibration.py.
"""

from __future__ import annotations

import numpy as np

# x the spec's value (scales) or absolute (backlash deg, latency ms): issue 13, "Must hold"
RANGES = {"speed_scale": (0.7, 1.3), "friction_scale": (0.7, 1.6), "armature_scale": (0.7, 1.4),
          "backlash_deg": (0.0, 0.5), "latency_ms": (0.0, 3.0)}
# the calibrated spec field each scale multiplies
FIELD = {"speed_scale": "no_load_speed", "friction_scale": "gear_friction", "armature_scale": "rotor_inertia"}


def draw_plant(seed: int) -> dict:
    """{option: value} drawn uniformly within RANGES."""
    rng = np.random.default_rng(seed)
    return {k: float(rng.uniform(lo, hi)) for k, (lo, hi) in RANGES.items()}


def emulator_args(plant: dict, seed: int) -> list[str]:
    """`vrscroll emulate` options for the drawn plant (gear damping as the spec's; encoder noise on)."""
    args = ["--damping-scale", "1", "--seed", str(seed)]
    for k, v in plant.items():
        args += ["--" + k.replace("_", "-"), f"{v:.6g}"]
    return args
