"""The psychometric fit as `vrscroll psychometric` reports it: its result (JSON, in the trials' unit), the paper's
printed fit beside it, the text, and example trials drawn from the paper's curve (docs/redirection-perception.md)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from twin.errors import UserError
from twin.formats.trials import Trials, write_trials
from twin.perception.psychometric import FIT_METHOD, analyse, simulate_trials, threshold
from twin.perception.thresholds import detection_rule, paper_fits


def fit_result(trials: Trials, source: str, resamples: int, seed: int, ci_level: float, paper: dict | None) -> dict:
    """The trials (read from `source`) fitted per surface under the paper's detection rule, with `resamples`
    bootstrap resamples (seed) for CIs at ci_level; paper: `paper_fit`'s, shown beside it (None: none)."""
    rule = detection_rule()
    return {"file": source, "unit": trials.unit, "rule": rule,
            "model": f"f(x) = 1/(1+exp(a x + b)), x in {trials.unit}",
            "surfaces": analyse(trials, rule, resamples, seed, ci_level), **({"paper": paper} if paper else {})}


def paper_fit(surface: str) -> dict:
    """The paper's printed fit for a surface; printed thresholds null where it says 'not reached'."""
    f = next(f for f in paper_fits() if f.surface == surface)
    return {"surface": f.surface, "unit": f.unit, f"a_per_{f.unit}": f.a, "b": f.b,
            f"cdt_printed_{f.unit}": f.cdt, f"dt_printed_{f.unit}": f.dt}


def example_trials(surface: str, seed: int):
    """(trial rows drawn from the paper's curve for `surface`, as its experiment ran them; the paper's fit)."""
    f = next(f for f in paper_fits() if f.surface == surface)
    return simulate_trials(f.a, f.b, f.conditions, f.participants, f.repeats, np.random.default_rng(seed),
                           detection_rule()["min_confidence"]), f


def write_example(path: Path, surface: str, seed: int) -> str:
    """Write example trials (example_trials) to a new file at path; what was written, in a line. UserError where
    the file exists (it is not overwritten)."""
    if path.exists():
        raise UserError(f"{path} exists; --example writes a new file and does not overwrite")
    rows, f = example_trials(surface, seed)
    write_trials(path, rows, f.unit)
    return (f"wrote {path}: {len(rows)} trials drawn from the paper's {surface} curve "
            f"(a = {f.a} /{f.unit}, b = {f.b}; {f.participants} participants x {f.repeats} repeats, seed {seed})")


def report_text(result: dict) -> str:
    """The fit result (`fit_result`) as the command prints it, in the trials' unit."""
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
