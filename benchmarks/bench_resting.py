"""Whether ours rests on its target from outside (issue 37): from each shape's default start, ours' MSD (exact
mesh), the deepest point of its touch surface inside the target, the share more than 2 mm inside and the gap of
flaps two or more apart, judged by twin/evaluation/outside_check.py (kinematics written apart from the
approximation's, from the result's JSON), and ours' time (best of 3 warm calls, one core). Shapes: those made for
tests/morphpatch/test_resting.py (`--shapes generated`, twin/evaluation/made_shapes.py) or the corpus (`--shapes corpus`, twin/evaluation/shape_corpus.py,
seed 0).

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_resting.py [--shapes corpus]

Before and after in one run: run it once with the old code first on PYTHONPATH (the shapes and the judge from this tree), once
with this tree's. Prints a line per shape and a summary.
"""

import os

for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[var] = "1"

import argparse  # noqa: E402

import numpy as np  # noqa: E402

from twin.device.spec import load_spec  # noqa: E402
from twin.evaluation.made_shapes import SHAPES  # noqa: E402
from twin.evaluation.outside_check import holds, judge  # noqa: E402
from twin.evaluation.shape_corpus import corpus  # noqa: E402
from twin.formats.target import approximation_json  # noqa: E402
from twin.morphpatch.approximation import approximate, measured, pose_from_mm_deg  # noqa: E402
from twin.morphpatch.fields import build_fields  # noqa: E402
from twin.morphpatch.default_start import default_start  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", choices=("generated", "corpus"), default="generated")
    parser.add_argument("--variant", default="refined")
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    spec = load_spec()
    items = [(k, f()) for k, f in SHAPES.items()] if args.shapes == "generated" else corpus(0)
    rows = []
    for name, mesh in items:
        mesh.apply_translation([-mesh.bounds.mean(0)[0], -mesh.bounds.mean(0)[1], -mesh.bounds[0, 2]])
        fields = build_fields(mesh)
        start = pose_from_mm_deg(default_start(mesh, fields, spec))
        approximate(fields, start, spec, args.variant)
        times = [approximate(fields, start, spec, args.variant).time for _ in range(3)]
        a = measured(spec, mesh, approximate(fields, start, spec, args.variant))
        v = judge(spec, mesh, approximation_json(a))
        rows.append((a.msd, v.deepest, v.share_2mm, v.gap, min(times), holds(v)))
        print(f"{name:15s} MSD {a.msd * 1e3:6.2f} mm  deepest {v.deepest * 1e3:6.2f} mm  >2 mm {v.share_2mm:6.1%}  "
              f"flap gap {v.gap * 1e3:6.2f} mm  {min(times) * 1e3:6.2f} ms  {'holds' if holds(v) else 'FAILS'}",
              flush=True)
    r = np.array(rows, float)
    print(f"{args.variant}: {int(r[:, 5].sum())} of {len(r)} hold the bar; mean MSD {r[:, 0].mean() * 1e3:.2f} mm, "
          f"mean deepest {r[:, 1].mean() * 1e3:.2f} mm, time median {np.median(r[:, 4]) * 1e3:.2f} ms, "
          f"p99 {np.percentile(r[:, 4], 99) * 1e3:.2f} ms")


if __name__ == "__main__":
    main()
