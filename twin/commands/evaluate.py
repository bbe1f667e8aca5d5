"""`vrscroll evaluate`: the paper's Table 1 (CBS, no_hcevf, full) and ours (refined) from the same seeded starts.

Results are appended to OUT/results.jsonl as they come; rerunning with the same
--out, --starts and --seed resumes. Writes OUT/table.md, OUT/table.csv and
OUT/chart.png (MSD, HD and the MSD on the twin per shape and method, the paper's means as ticks).
"""

from __future__ import annotations

import time

from twin.commands.options import comma_list
from twin.evaluation.backends import add_backend_arguments, make_backend
from twin.evaluation.lock import folder_lock
from twin.evaluation.table1 import METHODS, paper_table, run_evaluation, summarize, write_tables
from twin.morphpatch.shapes import shape_names
from viz.charts import method_bars


def add_arguments(p) -> None:
    p.add_argument("--shapes", type=comma_list(shape_names()), default=shape_names(), metavar="S1,S2,...",
                   help=f"shapes to evaluate (default all: {', '.join(shape_names())})")
    p.add_argument("--starts", type=int, default=50, help="starts per shape (default 50)")
    p.add_argument("--seed", type=int, default=0, help="seed of the start generator (default 0)")
    add_backend_arguments(p, workers_default=2)
    p.add_argument("--out", default="results/evaluation", help="output folder (default results/evaluation)")


MAX_STARTS = 1000  # per shape: the paper's 50 twenty times over (each start is a few seconds of work)


def run(args) -> int:
    if not 2 <= args.starts <= MAX_STARTS:
        raise ValueError(f"--starts {args.starts}: from 2 (an SD needs two) to {MAX_STARTS}")
    with folder_lock(args.out, "vrscroll evaluate"):  # two runs into one folder would compute every record twice
        t0 = time.perf_counter()
        with make_backend(args.backend, args.workers) as backend:
            records = run_evaluation(args.out, args.shapes, args.starts, args.seed, backend=backend)
        wall = time.perf_counter() - t0
        rows = summarize([r for r in records if r["shape"] in args.shapes])
        md, csv_path = write_tables(rows, args.out, wall)
        method_bars(rows, list(METHODS), args.shapes, f"{args.out}/chart.png", paper_table())
    print(md.read_text())
    print(f"wrote {md}, {csv_path}, {args.out}/chart.png ({wall:.1f} s)")
    return 0
