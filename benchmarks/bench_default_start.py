"""The default start for a mesh (twin.morphpatch.default_start, issue 37) against the starts a person would try
(twin/evaluation/shape_corpus.py's person_starts: from above and from each side, over the middle): per corpus shape (seed 0),
ours (refined) from the default start and from each of the person's, its MSD (exact mesh) and whether `approximate`
would refuse it (twin.morphpatch.resting's bar); a summary: refusals and mean MSD from the default start, from the
person's best start and from their median one, and where the default start is within 1 mm of the person's best.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_default_start.py [--shapes a,b]

Before and after in one run: run it with the old code first on PYTHONPATH, then this tree's; the person's
starts are the same in both.
"""

import os

for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[var] = "1"

import argparse  # noqa: E402

import numpy as np  # noqa: E402

from twin.device.spec import load_spec  # noqa: E402
from twin.evaluation.shape_corpus import corpus, person_starts  # noqa: E402
from twin.morphpatch.approximation import approximate, measured, pose_from_mm_deg  # noqa: E402
from twin.morphpatch.fields import build_fields  # noqa: E402
from twin.morphpatch.resting import refusal, resting  # noqa: E402
from twin.morphpatch.default_start import default_start  # noqa: E402


def ours(spec, mesh, fields, start) -> tuple[float, bool]:
    """Ours from a start [mm, deg]: (MSD m, whether it is refused)."""
    a = measured(spec, mesh, approximate(fields, pose_from_mm_deg(start), spec, "refined"))
    return a.msd, refusal(spec, mesh, resting(spec, mesh, fields, a), "refined", a.rests) is not None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", help="comma-separated corpus shapes (default: all 40)")
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    spec = load_spec()
    rows = []
    for name, mesh in corpus(0):
        if args.shapes and name not in args.shapes.split(","):
            continue
        fields = build_fields(mesh)
        default = ours(spec, mesh, fields, default_start(mesh, fields, spec))
        person = [ours(spec, mesh, fields, s) for s in person_starts(mesh)]
        delivered = sorted(m for m, refused in person if not refused) or [np.inf]
        rows.append((default[0], default[1], delivered[0], delivered[(len(delivered) - 1) // 2],
                     sum(r for _, r in person)))
        print(f"{name:16s} default {default[0] * 1e3:6.2f} mm{' refused' if default[1] else '        '}  person's "
              f"best {delivered[0] * 1e3:6.2f} median {delivered[(len(delivered) - 1) // 2] * 1e3:6.2f} mm, "
              f"refused {rows[-1][4]} of 5", flush=True)
    r = np.array(rows)
    ok = r[:, 1] == 0
    print(f"default start: refused on {int(r[:, 1].sum())} of {len(r)} shapes; mean MSD {r[:, 0].mean() * 1e3:.2f} mm "
          f"({r[ok, 0].mean() * 1e3:.2f} mm where delivered); within 1 mm of the person's best on "
          f"{int(np.sum(ok & (r[:, 0] <= r[:, 2] + 1e-3)))}, at or below their median on "
          f"{int(np.sum(ok & (r[:, 0] <= r[:, 3] + 1e-6)))}")
    fin = np.isfinite(r[:, 2])
    print(f"person's starts: refused {int(r[:, 4].sum())} of {5 * len(r)}; mean over shapes of their best "
          f"{r[fin, 2].mean() * 1e3:.2f} mm, of their median {r[fin, 3].mean() * 1e3:.2f} mm")


if __name__ == "__main__":
    main()
