"""Speed of the per-hinge trace figure (viz.traces.hinge_figure): what `simulate` and `demo` draw (six hinges, one
series) and what a HIL run's report draws once per hinge (one hinge, device and twin), on a real twin move.

    python benchmarks/bench_hinge_figure.py [--repeats 6]

Prints the median wall time of each figure over the repeats (the first, which loads fonts, left out) and the
load average: a shared machine is noisy, so compare runs made together.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from twin.device.spec import load_spec
from twin.sim.twin import Twin
from viz.traces import hinge_figure


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=6)
    args = p.parse_args()
    spec = load_spec()
    trace = Twin(spec).move_to(np.radians([30, -20, 40, 10, -35, 25]), max_time=0.3, stop_when_settled=False)
    band = math.degrees(spec.settle_band * spec.rad_per_count)
    cases = {"six hinges, the twin (simulate, demo)": ([("twin", trace)], range(spec.n_hinges), 4.0),
             "one hinge, device and twin (a HIL report's)": ([("device", trace), ("twin", trace)], [2], 10.0)}
    times = {name: [] for name in cases}
    with tempfile.TemporaryDirectory() as folder:
        for _ in range(args.repeats):
            for name, (series, hinges, width) in cases.items():
                start = time.perf_counter()
                hinge_figure(Path(folder) / "f.png", "bench", series, hinges, band, column_width=width)
                times[name].append(time.perf_counter() - start)
    for name, ts in times.items():
        print(f"{name}: median {statistics.median(ts[1:]):.2f} s over {len(ts) - 1} (all: "
              + ", ".join(f"{t:.2f}" for t in ts) + ")")
    print(f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
