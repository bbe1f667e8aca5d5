"""Benchmark of the surface approximation: field build time, grid error, time per approximation.

    .venv/bin/python benchmarks/bench_approximation.py [--starts 50] [--spacing 0.003]

Runs on one core (numba's and BLAS's threads pinned to 1 before import). Per shape:
the time to build its fields (no cache), the grid's SDF error against libigl's exact
signed distance at 4000 points -10..+30 mm off the surface, and the approximation's
time over `--starts` seeded starts (twin.evaluation.starts) for each variant, plus MSD and HD
(mm, exact mesh). Then each variant's median and p99 time per approximation over all shapes
and starts, in the same run ("refined", ours, includes the pipeline it starts from).
"""

import os

for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[var] = "1"

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from twin.device.spec import load_spec  # noqa: E402
from twin.morphpatch.approximation import VARIANTS, approximate  # noqa: E402
from twin.morphpatch.fields import GRID_SPACING, build_fields, exact_signed_distance  # noqa: E402
from twin.morphpatch.shapes import load_shape, shape_names  # noqa: E402
from twin.evaluation.starts import approach_starts  # noqa: E402
from twin.morphpatch.surface_metrics import msd_hd  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--starts", type=int, default=50)
    parser.add_argument("--spacing", type=float, default=GRID_SPACING, help="grid spacing, m")
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    spec = load_spec()
    times = {v: [] for v in VARIANTS}
    print(f"grid spacing {args.spacing * 1e3:g} mm, {args.starts} starts per shape, one core")
    print(f"{'shape':14s} {'grid':>15s} {'build_s':>7s} {'err_mean_mm':>11s} {'err_p99_mm':>10s} "
          f"{'err_max_mm':>10s}  " + "  ".join(f"{v + ' msd/hd mm':>22s}" for v in VARIANTS))
    for name in shape_names():
        mesh = load_shape(name)
        t0 = time.perf_counter()
        fields = build_fields(mesh, spacing=args.spacing, disk_cache=False)
        build = time.perf_counter() - t0
        rng = np.random.default_rng(0)
        points, faces = trimesh.sample.sample_surface(mesh, 4000, seed=0)
        points = points + mesh.face_normals[faces] * rng.uniform(-0.01, 0.03, (4000, 1))
        err = np.abs(fields.sdf_values(points) - exact_signed_distance(mesh, points)[0]) * 1e3
        starts = approach_starts(mesh, args.starts, seed=0)
        cols = []
        for variant in VARIANTS:
            approximate(fields, starts[0], spec, variant)  # warm-up: loads (or compiles) this variant's code
            results = [approximate(fields, s, spec, variant) for s in starts]
            times[variant] += [r.time for r in results]
            m = np.array([msd_hd(spec, mesh, r.root_pose, r.angles, r.widths) for r in results]) * 1e3
            cols.append(f"{m[:, 0].mean():5.2f}±{m[:, 0].std():4.2f} / {m[:, 1].mean():5.1f}")
        grid = "x".join(str(n) for n in fields.shape)
        print(f"{name:14s} {grid:>15s} {build:7.2f} {err.mean():11.3f} {np.percentile(err, 99):10.3f} "
              f"{err.max():10.3f}  " + "  ".join(f"{c:>22s}" for c in cols))
    for variant, t in times.items():
        t = np.array(t) * 1e3
        print(f"{variant:9s} time per approximation over {len(t)} runs: median {np.median(t):.3f} ms, "
              f"p99 {np.percentile(t, 99):.3f} ms, max {t.max():.3f} ms")


if __name__ == "__main__":
    main()
