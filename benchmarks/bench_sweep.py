"""The sweep backends' throughput: tasks per second on the local pool and on a local Ray, and Ray's overhead.

    .venv/bin/python benchmarks/bench_sweep.py [--workers 2] [--tasks 40] [--sizes 0.01 0.05 0.2] [--real 24]

1. Ray's start-up: `ray.init(num_cpus=workers)` to a cluster ready for tasks, s.
2. Tasks of a fixed size (a busy loop of --sizes seconds of CPU each, --tasks of them) through
   twin.evaluation.backends on both: wall time from the first task sent to the last result (each
   backend warmed up by one round of tiny tasks first, so neither pays its start here), tasks per
   second, the ideal (tasks x size / workers) and Ray's overhead against the local pool:
   (Ray's wall - local wall) / local wall.
3. Real sweep tasks (--real of them: designs of 5, 7 and 9 flaps, cylinder, `full`), cold (each worker
   builds its shape's fields and the twin once, as a sweep's first tasks do): tasks per second.

The machine's load (uptime) is printed before and after: on a shared machine the figures move with it.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from twin.evaluation.backends import LocalBackend, RayBackend  # noqa: E402
from twin.evaluation.sweep import run_sweep  # noqa: E402
from twin.evaluation.table1 import METHODS  # noqa: E402
from twin.formats.sweep import read_sweep  # noqa: E402
from twin.morphpatch.shapes import shape_names  # noqa: E402


def busy(seconds: float) -> float:
    """A task of `seconds` of CPU time (a busy loop); returns the CPU time it took."""
    t0 = time.process_time()
    x = 0
    while time.process_time() - t0 < seconds:
        x += 1
    return time.process_time() - t0


def load() -> str:
    return "load average " + ", ".join(f"{x:.2f}" for x in os.getloadavg())


def timed_map(backend, fn, tasks) -> float:
    """Wall time, s, of mapping fn over tasks on the backend until the last result."""
    t0 = time.perf_counter()
    for _ in backend.map(fn, tasks):
        pass
    return time.perf_counter() - t0


def real_sweep(backend, n: int, out: Path) -> float:
    """Wall time, s, of a cold sweep of n real tasks into a fresh folder."""
    starts = -(-n // 3)
    path = out / "bench.toml"
    path.write_text(f'shapes = ["cylinder"]\nstarts = {starts}\nmethods = ["full"]\n[design]\nn_flaps = [5, 7, 9]\n')
    sweep = read_sweep(path, shape_names(), list(METHODS))
    t0 = time.perf_counter()
    run_sweep(out / backend.name, sweep, backend, progress=False)
    return time.perf_counter() - t0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--tasks", type=int, default=40, help="tasks per size (default %(default)s)")
    p.add_argument("--sizes", type=float, nargs="+", default=[0.01, 0.05, 0.2], help="task sizes, s of CPU")
    p.add_argument("--real", type=int, default=24, help="real sweep tasks (0: none) (default %(default)s)")
    args = p.parse_args()
    import ray

    print(f"before: {load()}; {args.workers} workers, {os.cpu_count()} cores")
    t0 = time.perf_counter()
    ray.init(num_cpus=args.workers, include_dashboard=False, log_to_driver=False)
    startup = time.perf_counter() - t0
    print(f"Ray start-up (ray.init, local, {args.workers} CPUs): {startup:.1f} s")
    results = {}
    with LocalBackend(args.workers) as local, RayBackend() as on_ray, tempfile.TemporaryDirectory() as tmp:
        for backend in (local, on_ray):  # start the workers (the pool's processes, Ray's) before timing
            timed_map(backend, busy, [0.001] * (2 * args.workers))
        print(f"{'task s':>7} {'tasks':>6} {'ideal s':>8} {'local s':>8} {'local task/s':>12} {'Ray s':>7} "
              f"{'Ray task/s':>10} {'Ray overhead':>12}")
        for size in args.sizes:
            tasks = [size] * args.tasks
            wall = {b.name: timed_map(b, busy, tasks) for b in (local, on_ray)}
            overhead = wall["ray"] / wall["local"] - 1
            results[size] = overhead
            print(f"{size:>7.3f} {args.tasks:>6} {args.tasks * size / args.workers:>8.2f} {wall['local']:>8.2f} "
                  f"{args.tasks / wall['local']:>12.1f} {wall['ray']:>7.2f} {args.tasks / wall['ray']:>10.1f} "
                  f"{overhead:>+12.0%}")
        if args.real:
            with LocalBackend(args.workers) as fresh:
                walls = {"local": real_sweep(fresh, args.real, Path(tmp))}
            walls["ray"] = real_sweep(on_ray, args.real, Path(tmp))
            for name, wall in walls.items():
                print(f"real sweep tasks on {name}: {args.real} in {wall:.1f} s, {args.real / wall:.2f} tasks/s "
                      "(cold: each worker builds its fields and twins)")
    ray.shutdown()
    print(f"after: {load()}")


if __name__ == "__main__":
    main()
