"""Benchmark of pen redirection: time to build the field, time per redirected pen sample.

    .venv/bin/python benchmarks/bench_redirection.py [--starts 5] [--calls 20000]

Runs on one core (numba's and BLAS's threads pinned to 1 before import). Per shape,
from `--starts` seeded starts (twin.evaluation.starts), approximated with the full pipeline:
the time to build the redirection field (the target's SDF grid already built, as it
is when the approximation ran), the share of the touch surface within the perception
thresholds, and the time per pen sample two ways: one sample per call, as a 360 Hz
tracker delivers them (median and p99 over `--calls` calls), and in batches of 10 000.
Not a speed, but measured here on the same fields: how far the virtual pen moves for a
0.5 mm pen step across hinges and off the device's edges, blurred and raw
(twin.morphpatch.redirection.largest_virtual_step).
"""

import os

for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[var] = "1"

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from twin.device.spec import load_spec  # noqa: E402
from twin.morphpatch.approximation import approximate  # noqa: E402
from twin.morphpatch.fields import build_fields  # noqa: E402
from twin.morphpatch.redirection import build_field, largest_virtual_step, redirect, threshold_summary  # noqa: E402
from twin.morphpatch.shapes import load_shape, shape_names  # noqa: E402
from twin.evaluation.starts import approach_starts  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--starts", type=int, default=5)
    parser.add_argument("--calls", type=int, default=20000, help="single-sample calls per shape")
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    spec = load_spec()
    rng = np.random.default_rng(0)
    builds, singles, batches, steps, raw_steps = [], [], [], [], []
    print(f"{args.starts} starts per shape, one core")
    print(f"{'shape':14s} {'build_ms':>9s} {'within':>7s} {'largest mm/deg':>15s} {'single_us':>10s} {'batch_us':>9s}"
          f" {'step mm blurred/raw':>20s}")
    for name in shape_names():
        mesh = load_shape(name)
        fields = build_fields(mesh)
        shape_builds, within, largest = [], [], (0.0, 0.0)
        for start in approach_starts(mesh, args.starts, seed=0):
            a = approximate(fields, start, spec)
            field = build_field(spec, a.root_pose, a.angles, a.widths, mesh, fields)
            shape_builds.append(field.build_time * 1e3)
            s = threshold_summary(field)
            within.append(s["share_within"])
            largest = max(largest, (s["largest_offset_mm"], s["largest_rotation_deg"]))
            steps.append(largest_virtual_step(field) * 1e3)
            raw = build_field(spec, a.root_pose, a.angles, a.widths, mesh, fields, sigma=0.0)
            raw_steps.append(largest_virtual_step(raw) * 1e3)
        builds += shape_builds
        # pen samples around the last field's device, touching and hovering, random orientations
        n = 10_000
        pens = a.root_pose[:3, 3] + rng.uniform(-0.1, 0.1, (n, 3))
        quats = Rotation.random(n, random_state=rng).as_quat(scalar_first=True)
        redirect(field, pens[:1], quats[:1])  # warm-up: loads compiled code
        t = np.empty(args.calls)
        for k in range(args.calls):
            t0 = time.perf_counter()
            redirect(field, pens[k % n], quats[k % n])
            t[k] = time.perf_counter() - t0
        singles.append(t)
        t0 = time.perf_counter()
        redirect(field, pens, quats)
        batches.append((time.perf_counter() - t0) / n)
        print(f"{name:14s} {np.median(shape_builds):9.1f} {np.mean(within):7.1%} "
              f"{largest[0]:7.1f}/{largest[1]:5.1f}   {np.median(t) * 1e6:10.2f} {batches[-1] * 1e6:9.3f}"
              f" {max(steps[-args.starts:]):10.2f}/{max(raw_steps[-args.starts:]):5.2f}")
    t = np.concatenate(singles) * 1e6
    b = np.array(builds)
    print(f"field build over {len(b)} approximations: median {np.median(b):.1f} ms, max {b.max():.1f} ms")
    print(f"one pen sample per call over {len(t)} calls: median {np.median(t):.2f} us, p99 {np.percentile(t, 99):.2f} us"
          f" (goal < 50 us); in batches of 10 000: median {np.median(batches) * 1e6:.3f} us per sample")
    print(f"virtual pen move for a 0.5 mm pen step across hinges and off the edges: blurred median "
          f"{np.median(steps):.2f} mm, max {max(steps):.2f} mm; raw median {np.median(raw_steps):.2f} mm, "
          f"max {max(raw_steps):.2f} mm")


if __name__ == "__main__":
    main()
