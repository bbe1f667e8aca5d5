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

import numpy as np

from twin.commands.options import add_json, json_to_stdout, write_json
from twin.errors import UserError
from twin.formats.trials import read_trials, write_trials
from twin.perception.psychometric import FIT_METHOD, analyse, simulate_trials, threshold
from twin.perception.thresholds import detection_rule, paper_fits
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


def _paper(surface: str) -> dict:
    """The paper's printed fit for a surface; printed thresholds null where it says 'not reached'."""
    f = next(f for f in paper_fits() if f.surface == surface)
    return {"surface": f.surface, "unit": f.unit, f"a_per_{f.unit}": f.a, "b": f.b,
            f"cdt_printed_{f.unit}": f.cdt, f"dt_printed_{f.unit}": f.dt}


def write_example(path: Path, surface: str, seed: int) -> None:
    if path.exists():
        raise UserError(f"{path} exists; --example writes a new file and does not overwrite")
    f = next(f for f in paper_fits() if f.surface == surface)
    rows = simulate_trials(f.a, f.b, f.conditions, f.participants, f.repeats, np.random.default_rng(seed),
                           detection_rule()["min_confidence"])
    write_trials(path, rows, f.unit)
    print(f"wrote {path}: {len(rows)} trials drawn from the paper's {surface} curve "
          f"(a = {f.a} /{f.unit}, b = {f.b}; {f.participants} participants x {f.repeats} repeats, seed {seed})")


def _text(result: dict) -> str:
    u, rule = result["unit"], result["rule"]
    lines = [f"{result['file']}: detected = unnatural with confidence >= {rule['min_confidence']}; "
             f"f(x) = 1/(1+exp(a x + b)), x in {u}, {FIT_METHOD}"]
    for r in result["surfaces"]:
        who = f", {r['participants']} participants" if r["participants"] else ""
        lines += ["", f"{r['surface'] or 'all trials'}: {r['trials']} trials{who}",
                  f"  {'condition_' + u:>14} {'n':>5} {'detected':>8} {'ratio':>6}  {'CI':>14}"]
        for c in r["conditions"]:
            lo, hi = c["ratio_ci"]
            lines.append(f"  {c['condition_' + u]:>14g} {c['n']:>5} {c['detected']:>8} {c['ratio']:>6.3f}"
                         f"  [{lo:.3f}, {hi:.3f}]")
        fit = r["fit"]
        if fit["degenerate"]:
            lines.append(f"  no fit: {fit['degenerate']}")
        else:
            lines.append(f"  a = {fit['a_per_' + u]:.4f} ± {fit['a_se_per_' + u]:.4f} /{u}, "
                         f"b = {fit['b']:.3f} ± {fit['b_se']:.3f} (± 1 SE)")
        for name, t in r["thresholds"].items():
            line = f"  {name.upper():<3} (f = {t['level']:.2f}): {t['statement']}"
            if "ci_level" in t:
                lo, hi = (f"{v:.1f}" if v is not None else "unbounded" for v in t[f"ci_{u}"])
                line += (f"; {t['ci_level']:.0%} CI [{lo}, {hi}] {u}, inside the tested range in "
                         f"{t['inside_fraction']:.1%} of {r['bootstrap']['resamples']} resamples "
                         f"(by {r['bootstrap']['by']})")
            lines.append(line)
    if "paper" in result:
        p = result["paper"]
        a, b = p[f"a_per_{u}"], p["b"]
        printed = ", ".join(f"{k.upper()} {v if v is not None else 'not reached'}"
                            for k, v in (("cdt", p[f"cdt_printed_{u}"]), ("dt", p[f"dt_printed_{u}"])))
        lines += ["", f"paper, {p['surface']}: a = {a} /{u}, b = {b}; printed {printed} ({u}); from the rounded "
                  f"a, b: CDT {threshold(a, b, rule['cdt_level']):.2f}, DT {threshold(a, b, rule['dt_level']):.2f}"]
    return "\n".join(lines)


def run(args) -> int:
    if args.example:
        write_example(Path(args.data or EXAMPLE), args.example, args.seed)
        return 0
    if args.data is None:
        raise UserError("name the trials file to fit (DATA.csv), or write one with --example")
    path = Path(args.data)
    if not 0 <= args.bootstrap <= MAX_BOOTSTRAP:
        raise UserError(f"--bootstrap {args.bootstrap}: from 0 to {MAX_BOOTSTRAP:,} resamples")
    if not 0 < args.level_ci < 1:
        raise UserError("--level-ci must be between 0 and 1, e.g. 0.95")
    trials = read_trials(path)
    paper = _paper(args.compare_paper) if args.compare_paper else None
    if paper and paper["unit"] != trials.unit:
        raise UserError(f"--compare-paper {args.compare_paper!r} is in {paper['unit']}, {path} in {trials.unit}")
    rule = detection_rule()
    result = {"file": str(path), "unit": trials.unit, "rule": rule,
              "model": f"f(x) = 1/(1+exp(a x + b)), x in {trials.unit}",
              "surfaces": analyse(trials, rule, args.bootstrap, args.seed, args.level_ci),
              **({"paper": paper} if paper else {})}
    text = json.dumps(result, indent=2)
    write_json(args.json, result)
    if not json_to_stdout(args):
        print(_text(result))
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
