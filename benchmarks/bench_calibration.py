"""Calibration on plants nobody told the twin: per-hinge held-out RMSE before and after, fitted against drawn.

For each seed, the emulator draws its plant within its stated ranges (tests/random_plant.py); the device is
woken to flat, the calibration scenario (seed 0, for the device's gains) and a held-out one (seed 1) are
recorded with `vrscroll hil`, and `vrscroll calibrate` fits the first and scores the second. The drawn
values are read from the emulator's log only to print beside the fit. Two floors: the held-out error of a
twin given the drawn values the twin can take (the shared ones: each hinge's own values and the effects the
twin does not model stay out of it), and the one `vrscroll calibrate` estimates from the run alone (the
encoder's resolution and the link's timing), with what no parameter explains above it.

    python benchmarks/bench_calibration.py [--seeds 1 2 3] [--out /tmp/bench-cal]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from random_plant import drawn_plant, emulator_args  # noqa: E402
from twin.cli import main as vrscroll  # noqa: E402
from twin.device.spec import load_spec  # noqa: E402
from twin.formats.run import read_run  # noqa: E402
from twin.hil.calibration import trace_rmse  # noqa: E402
from twin.hil.mirror import mirror  # noqa: E402
from twin.link.emulator_process import EmulatorProcess  # noqa: E402
from twin.link.serial_link import Link  # noqa: E402


def quiet(*args) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = vrscroll(list(args))
    if rc:
        raise SystemExit(f"vrscroll {' '.join(args)} failed ({rc})")
    return out.getvalue()


def one(seed: int, folder: Path) -> None:
    spec = load_spec()
    folder.mkdir(parents=True, exist_ok=True)
    with EmulatorProcess(folder / "emulator.jsonl", "--zeroed", *emulator_args(seed)) as emu:
        truth = drawn_plant(emu)
        with Link(emu.port) as link:
            assert mirror(link, spec, np.zeros(spec.n_hinges), tolerance_deg=30.0).ok
        for name, s in (("train", 0), ("hold", 1)):
            quiet("scenario", str(folder / f"{name}.toml"), "--serial", emu.port, "--seed", str(s))
            quiet("hil", str(folder / f"{name}.toml"), "--serial", emu.port, "--out", str(folder / name),
                  "--tolerance-deg", "30")
    t0 = time.perf_counter()
    cal = json.loads(quiet("calibrate", str(folder / "train"), "--holdout", str(folder / "hold"),
                           "--out", str(folder / "cal.toml"), "--json", "-"))
    wall = time.perf_counter() - t0
    floor = trace_rmse(read_run(folder / "hold", spec),
                       spec.replace(**{k: v for k, v in truth.items() if k != "supply_voltage"}), spec)
    h = cal["holdout"]
    print(f"seed {seed}: calibrated in {wall:.0f} s ({cal['replays']} replays)")
    print(f"  {'parameter':<14} {'drawn x':>8} {'fitted x':>9} {'95 % interval x':>17}  verdict")
    for p, e in cal["parameters"].items():
        verdict = "identifiable" if e["identifiable"] else "fitted" if e["value"] != e["prior"] else "prior"
        print(f"  {p:<14} {truth[p] / e['prior']:8.3f} {e['value'] / e['prior']:9.3f} "
              f"{e['low'] / e['prior']:8.3f}..{e['high'] / e['prior']:<7.3f}  {verdict}")
    print("  held-out RMSE per hinge, deg: before " + " ".join(f"{x:.3f}" for x in h["rmse_before_deg"]))
    print("                                after  " + " ".join(f"{x:.3f}" for x in h["rmse_after_deg"]))
    print("    twin given the drawn shared values " + " ".join(f"{x:.3f}" for x in floor))
    print("    floor from the run (encoder, link)  " + " ".join(f"{r['floor_deg']:.3f}" for r in h["per_hinge"]))
    print("    unexplained after calibration       " + " ".join(f"{r['unexplained_deg']:.3f}" for r in h["per_hinge"]))
    print(f"  overall: {h['overall_before_deg']:.3f} -> {h['overall_after_deg']:.3f} deg "
          f"(floor {float(np.sqrt(np.mean(floor ** 2))):.3f})", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--out", help="folder for the runs (default: a temporary one)")
    args = ap.parse_args()
    base = Path(args.out or tempfile.mkdtemp(prefix="bench-cal-"))
    for seed in args.seeds:
        one(seed, base / f"seed{seed}")


if __name__ == "__main__":
    main()
