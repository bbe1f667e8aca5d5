"""A device plant nobody chose: the emulator draws its parameters at random within the issue's ranges.

The drawn values are in the emulator's log only (its "start" event); the twin never sees them. Shared by
the calibration tests and benchmarks/bench_calibration.py.
"""

from __future__ import annotations

# issue 13, "Must hold": x the spec's value, or deg and ms
RANGES = {"speed-scale": "0.7,1.3", "friction-scale": "0.7,1.6", "armature-scale": "0.7,1.4",
          "damping-scale": "0.7,1.6", "backlash-deg": "0,0.5", "latency-ms": "0,3"}
ENCODER_MISS = 0.0005  # probability per edge the encoder's counter misses it


def emulator_args(seed: int) -> list[str]:
    """`vrscroll emulate` options: every parameter drawn within RANGES from the seed."""
    args = ["--seed", str(seed), "--encoder-miss", str(ENCODER_MISS)]
    for k, v in RANGES.items():
        args += ["--" + k, v]
    return args


def drawn_plant(emulator) -> dict:
    """The plant the emulator drew (spec field -> SI value), from its log."""
    return next(e for e in emulator.events("start"))["plant"]
