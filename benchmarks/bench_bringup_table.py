"""The figures behind bring-up's table test (twin.hil.bringup.lifting_way, issue 38): each hinge pulsed at the
strongest bring-up pulse each way from rest, on the spec's plant and drawn ones, lying flat and hanging, the
emulator stepped in-process (no pty, no real time).

Per hinge: beside the root, the pushing way's counts as a share of the lifting way's (BLOCKED_SHARE decides at or
below it); further out, the hinges between it and the root moved as a share of its own counts, pushing and lifting
(TENT_SHARE and STILL_SHARE). Lying flat "lift" is the positive duty (the plant's own, no wiring fault); hanging it
is the way that moved the hinge more, as bring-up would take it. Hanging is read after --rest-ms (3000: the flaps
at rest) and after 100 ms (still sagging).

    python benchmarks/bench_bringup_table.py [--seeds 7,12,13,29,37,61]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from twin.commands import emulate  # noqa: E402
from twin.device.spec import load_spec  # noqa: E402
from twin.hil.bringup import BLOCKED_SHARE, PULSES, STILL_SHARE, TENT_SHARE, between_root  # noqa: E402
from twin.link import protocol as P  # noqa: E402
from twin.link.drawn_plant import emulator_args  # noqa: E402
from twin.link.emulator import Emulator  # noqa: E402


def emulator(spec, seed: int | None, flat: bool) -> Emulator:
    p = argparse.ArgumentParser()
    emulate.add_arguments(p)
    plant = emulator_args(seed) if seed is not None else ["--ideal"]
    return Emulator(spec, emulate.options_from_args(
        p.parse_args([*plant, "--latency-ms", "0", *(["--lying-flat"] * flat)]), spec))


def run(emu: Emulator, ticks: int) -> None:
    for t in range(ticks):
        if t % 50 == 0:
            emu.receive(P.encode(P.Heartbeat(), 1))
        emu.step()
        emu.take_output()


def from_rest(spec, seed, flat: bool, hinge: int, sign: int, rest_ms: int) -> np.ndarray:
    """The plant's counts moved by one strongest pulse of `hinge` at `sign`, from rest_ms after power-on."""
    duty, seconds = PULSES[-1]
    emu = emulator(spec, seed, flat)
    run(emu, rest_ms)
    before = emu.plant.counts.copy()
    emu.receive(P.encode(P.Pulse(hinge, int(sign * duty * P.DUTY_SCALE), round(seconds * 1000)), 2))
    run(emu, round((seconds + 0.1) * 1000))
    return emu.plant.counts - before


def shares(spec, seeds, flat: bool, rest_ms: int) -> dict:
    """Per kind of hinge, the shares over the plants: beside the root [push/lift], further out [push, lift]."""
    out = {"beside": [], "push": [], "lift": []}
    for seed in seeds:
        for k in range(spec.n_hinges):
            moved = {s: from_rest(spec, seed, flat, k, s, rest_ms) for s in (1, -1)}
            own = {s: abs(float(m[k])) for s, m in moved.items()}
            lift = 1 if flat or own[1] >= own[-1] else -1
            beside = between_root(spec, k)
            if not beside:
                out["beside"].append(own[-lift] / max(own[lift], 1.0))
            else:
                def share(m):
                    return float(np.abs(m[beside]).sum()) / max(abs(float(m[k])), 1.0)
                out["push"].append(share(moved[-lift]))
                out["lift"].append(share(moved[lift]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="7,12,13,29,37,61", help="drawn plants (the spec's is always one)")
    ap.add_argument("--rest-ms", type=int, default=3000)
    a = ap.parse_args()
    spec = load_spec()
    seeds = [None, *(int(s) for s in a.seeds.split(","))]
    print(f"decided at: beside the root push/lift <= {BLOCKED_SHARE:g}; further out push >= {TENT_SHARE:g} "
          f"and lift <= {STILL_SHARE:g}")
    for name, flat, rest in (("lying flat", True, 300), ("hanging at rest", False, a.rest_ms),
                             ("hanging sagging", False, 100)):
        s = shares(spec, seeds, flat, rest)
        print(f"{name:16}: beside the root push/lift {min(s['beside']):.2f}-{max(s['beside']):.2f}; further out "
              f"push {min(s['push']):.2f}-{max(s['push']):.2f}, lift {min(s['lift']):.2f}-{max(s['lift']):.2f}")


if __name__ == "__main__":
    main()
