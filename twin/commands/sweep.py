"""`vrscroll sweep SWEEP.toml`: designs x shapes x starts x methods x plants of approximations and morphs.

Runs on all local cores by default, on Ray with --backend ray (RAY_ADDRESS, or a local Ray). Records are
appended to OUT/records.jsonl as they come, so a second run continues where one stopped. Writes
OUT/table.parquet (or table.csv without pyarrow; a row per task), OUT/designs.csv (per design and method,
the Pareto front marked), OUT/designs.png and OUT/pareto.png. docs/sweeps.md; the file: docs/formats.md.
"""

from __future__ import annotations

import time
from pathlib import Path

from twin.evaluation.backends import add_backend_arguments, make_backend
from twin.evaluation.lock import folder_lock
from twin.evaluation.sweep import run_sweep, summarize_designs, write_csv, write_table
from twin.evaluation.table1 import METHODS
from twin.errors import UserError
from twin.formats.sweep import read_sweep, write_sweep
from twin.morphpatch.shapes import shape_names
from viz.charts import design_bars, pareto_front


EXAMPLE = "sweep.toml"  # what `--example` writes when no file is named


def add_arguments(p) -> None:
    p.add_argument("sweep", metavar="SWEEP.toml", nargs="?",
                   help=f"the sweep file (with --example: the file to write, default {EXAMPLE})")
    p.add_argument("--out", help="output folder (default results/sweep/<the sweep file's name>)")
    add_backend_arguments(p)
    p.add_argument("--example", action="store_true", help="instead of sweeping, write an example SWEEP.toml")


def run(args) -> int:
    if args.example:
        args.sweep = args.sweep or EXAMPLE
        if Path(args.sweep).exists():
            raise UserError(f"{args.sweep} exists; --example writes a new file and does not overwrite")
        write_sweep(args.sweep, ["cylinder", "ellipsoid"], 3, 0, ["full", "refined"],
                    {"n_flaps": [5, 7, 9], "hinge_limit": {"from": 90, "to": 110, "count": 2}},
                    {"draws": 1, "seed": 0, "tolerance_pct": {"no_load_speed": 20, "gear_friction": 20}})
        print(f"wrote {args.sweep}")
        return 0
    if args.sweep is None:
        raise UserError("name the sweep file to run (SWEEP.toml), or write one with --example")
    sweep = read_sweep(args.sweep, shape_names(), list(METHODS))
    out = Path(args.out or Path("results") / "sweep" / Path(args.sweep).stem)
    n = len(sweep.designs) * len(sweep.shapes) * sweep.starts * len(sweep.methods) * (sweep.plant_draws + 1)
    print(f"{len(sweep.designs)} designs x {len(sweep.shapes)} shapes x {sweep.starts} starts x "
          f"{len(sweep.methods)} methods x {sweep.plant_draws + 1} plants = {n} tasks into {out}", flush=True)
    with folder_lock(out, "vrscroll sweep"):
        t0 = time.perf_counter()
        with make_backend(args.backend, args.workers) as backend:
            records = run_sweep(out, sweep, backend)
        wall = time.perf_counter() - t0
        rows = summarize_designs(records)
        table = write_table(records, out / "table")
        designs = write_csv(rows, out / "designs.csv")
        design_bars(rows, out / "designs.png")
        pareto_front(rows, out / "pareto.png")
    print(f"{'design':<32} {'method':<9} {'mass g':>7} {'MSD mm':>7} {'twin MSD mm':>11} {'morph s':>8} "
          f"{'worst s':>8} {'settled':>7}  Pareto")
    for r in rows:
        mean, worst = r["morph_time_mean_s"], r["morph_time_max_s"]
        print(f"{r['design']:<32} {r['method']:<9} {r['mass_g']:>7.1f} {r['msd_mean_mm']:>7.2f} "
              f"{r['twin_msd_mean_mm']:>11.2f} {'-' if mean is None else f'{mean:.3f}':>8} "
              f"{'-' if worst is None else f'{worst:.3f}':>8} {r['settled_share']:>7.0%}  {'*' if r['pareto'] else ''}")
    print(f"wrote {table}, {designs}, {out / 'designs.png'}, {out / 'pareto.png'} ({wall:.1f} s, {args.backend})")
    return 0
