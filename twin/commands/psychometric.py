"""`vrscroll psychometric DATA.csv`: detection ratios, the fit f(x) = 1/(1+exp(a x + b)), CDT and DT.

DATA has one row per trial: condition_<unit> (e.g. condition_mm, condition_deg), natural
(yes/no, true/false, 1/0, natural/unnatural), confidence (1-5), optionally participant and
surface (each surface is fitted on its own); see docs/redirection-perception.md. A trial is
detected when answered unnatural with confidence >= 3 (models/perception/perception.toml).
Thresholds outside the tested conditions are reported as outside, with the extrapolated
value labelled as such. `--example SURFACE` writes a sample DATA drawn from the paper's curve.
"""

from __future__ import annotations

import json
from pathlib import Path

from twin.commands.options import add_json, json_to_stdout, write_json
from twin.errors import UserError
from twin.formats.trials import read_trials
from twin.perception.fit_report import fit_result, paper_fit, report_text, write_example
from twin.perception.thresholds import paper_fits
from viz.charts import psychometric_curves

EXAMPLE = "trials.csv"  # what `--example` writes when no file is named
MAX_BOOTSTRAP = 100_000  # resamples: CIs stable to well below a percent; each holds the trials in memory


def add_arguments(p) -> None:
    surfaces = [f.surface for f in paper_fits()]
    p.add_argument("data", metavar="DATA.csv", nargs="?",
                   help=f"trials CSV (with --example: the file to write, default {EXAMPLE})")
    p.add_argument("--out", metavar="DIR", help="write DIR/fit.json and DIR/psychometric.png")
    p.add_argument("--bootstrap", type=int, default=2000, metavar="N",
                   help="bootstrap resamples for the threshold CIs (default 2000; 0: none)")
    p.add_argument("--seed", type=int, default=0, help="seed of the bootstrap (and of --example) (default 0)")
    p.add_argument("--level-ci", type=float, default=0.95, metavar="P", help="confidence level of the CIs (default 0.95)")
    add_json(p, "the result")
    p.add_argument("--compare-paper", choices=surfaces, metavar="SURFACE",
                   help=f"overlay the paper's printed curve for SURFACE ({', '.join(surfaces)})")
    p.add_argument("--example", choices=surfaces, metavar="SURFACE", nargs="?", const=surfaces[0],
                   help=f"instead of fitting, write DATA: trials drawn from the paper's curve for SURFACE "
                        f"(default {surfaces[0]!r})")


def run(args) -> int:
    if args.example:
        print(write_example(Path(args.data or EXAMPLE), args.example, args.seed))
        return 0
    if args.data is None:
        raise UserError("name the trials file to fit (DATA.csv), or write one with --example")
    path = Path(args.data)
    if not 0 <= args.bootstrap <= MAX_BOOTSTRAP:
        raise UserError(f"--bootstrap {args.bootstrap}: from 0 to {MAX_BOOTSTRAP:,} resamples")
    if not 0 < args.level_ci < 1:
        raise UserError("--level-ci must be between 0 and 1, e.g. 0.95")
    trials = read_trials(path)
    paper = paper_fit(args.compare_paper) if args.compare_paper else None
    if paper and paper["unit"] != trials.unit:
        raise UserError(f"--compare-paper {args.compare_paper!r} is in {paper['unit']}, {path} in {trials.unit}")
    result = fit_result(trials, str(path), args.bootstrap, args.seed, args.level_ci, paper)
    text = json.dumps(result, indent=2)
    write_json(args.json, result)
    if not json_to_stdout(args):
        print(report_text(result))
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "fit.json").write_text(text + "\n")
        psychometric_curves(result["surfaces"], trials.unit, out / "psychometric.png",
                            paper and {"label": f"paper ({paper['surface']})",
                                       "a": paper[f"a_per_{trials.unit}"], "b": paper["b"]})
        if not json_to_stdout(args):
            print(f"\nwrote {out / 'fit.json'}, {out / 'psychometric.png'}")
    return 0
