"""Psychometric fitting of pen-redirection trials: detection ratios, f(x) = 1/(1+exp(a x + b)), CDT and DT.

Trials come from a trials CSV (twin.formats.trials, docs/formats.md). x is always in the file's
unit; a is then in 1/unit and b is dimensionless.

The fit is binomial maximum likelihood on the trials (the per-condition counts
carry the whole likelihood), by Newton's method, vectorised so the bootstrap's
thousands of refits are one call.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.special import expit
from scipy.stats import norm

from twin.formats.trials import Trials, by_surface

FIT_METHOD = "binomial maximum likelihood on the trials"


@dataclasses.dataclass(frozen=True)
class Fit:
    """a (1/unit) and b with standard errors from the observed information; all None and a note when degenerate."""

    a: float | None
    b: float | None
    a_se: float | None
    b_se: float | None
    degenerate: str | None  # why there is no finite fit, else None


def detected(natural, confidence, min_confidence: int) -> np.ndarray:
    """The paper's rule: a trial is detected when answered unnatural with confidence >= min_confidence."""
    return ~np.asarray(natural, bool) & (np.asarray(confidence) >= min_confidence)


def counts(condition, is_detected):
    """(x, n, k): the distinct conditions (sorted, unit of the file), trials and detections at each."""
    x, ci = np.unique(condition, return_inverse=True)
    return (x, np.bincount(ci, minlength=len(x)),
            np.bincount(ci, weights=np.asarray(is_detected, int), minlength=len(x)).astype(int))


def counts_by_participant(condition, is_detected, participant):
    """(n, k): trials and detections per participant (rows) and condition (columns, as in `counts`)."""
    _, ci = np.unique(condition, return_inverse=True)
    _, pi = np.unique(participant, return_inverse=True)
    n = np.zeros((pi.max() + 1, ci.max() + 1), int)
    k = np.zeros_like(n)
    np.add.at(n, (pi, ci), 1)
    np.add.at(k, (pi, ci), np.asarray(is_detected, int))
    return n, k


def wilson_interval(k, n, level: float = 0.95):
    """Wilson score interval of a binomial proportion k/n: (low, high)."""
    k, n = np.asarray(k, float), np.asarray(n, float)
    z = norm.ppf(0.5 + level / 2)
    p = k / n
    centre = (p + z**2 / (2 * n)) / (1 + z**2 / n)
    half = z / (1 + z**2 / n) * np.sqrt(p * (1 - p) / n + z**2 / (4 * n**2))
    return np.clip(centre - half, 0, 1), np.clip(centre + half, 0, 1)


def curve(x, a: float, b: float):
    """f(x) = 1/(1+exp(a x + b)), the detection probability at x."""
    return expit(-(a * np.asarray(x, float) + b))


def threshold(a, b, level: float):
    """x where f(x) = level, in the unit of x: (log(1/level - 1) - b) / a."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return (math.log(1 / level - 1) - np.asarray(b, float)) / np.asarray(a, float)


def separation(x, k, n):
    """(finite, step) per row of counts k, n (rows x conditions).

    finite: a finite maximum-likelihood fit exists (detected and undetected trials overlap in x).
    step, where it does not: +inf when nothing was detected, -inf when everything was, else the
    midpoint of the conditions between which detection jumps from none to all (an infinitely
    steep curve, whose every threshold lies in that jump).
    """
    k, n = np.atleast_2d(k), np.atleast_2d(n)
    det, non = k > 0, (n - k) > 0
    lo_det = np.where(det, x, np.inf).min(-1)
    hi_det = np.where(det, x, -np.inf).max(-1)
    lo_non = np.where(non, x, np.inf).min(-1)
    hi_non = np.where(non, x, -np.inf).max(-1)
    finite = (hi_non > lo_det) & (hi_det > lo_non)
    with np.errstate(invalid="ignore"):
        step = np.where(~det.any(-1), np.inf, np.where(~non.any(-1), -np.inf,
                        np.where(hi_non <= lo_det, (hi_non + lo_det) / 2, (hi_det + lo_non) / 2)))
    return finite, step


def fit_many(x, k, n, iterations: int = 100):
    """Maximum-likelihood (a, b) for each row of counts k, n (rows x conditions); NaN where there is none.

    Newton's method on x standardised to mean 0 and SD 1, from a flat 0.5 curve, steps capped at 10.
    NaN: no finite fit (see `separation`) or Newton did not converge.
    """
    x = np.asarray(x, float)
    k, n = np.atleast_2d(k).astype(float), np.atleast_2d(n).astype(float)
    finite = separation(x, k, n)[0]
    k, n = k[finite], n[finite]
    m, s = x.mean(), x.std()
    z = (x - m) / s
    a, b = np.zeros(len(k)), np.zeros(len(k))
    for _ in range(iterations):
        q = expit(a[:, None] * z + b[:, None])  # 1 - f
        r = n * (1 - q) - k  # d log-likelihood / d(a z + b)
        w = n * q * (1 - q)
        ga, gb = (r * z).sum(-1), r.sum(-1)
        iaa, iab, ibb = (w * z * z).sum(-1), (w * z).sum(-1), w.sum(-1)
        det = iaa * ibb - iab**2
        da, db = (ibb * ga - iab * gb) / det, (iaa * gb - iab * ga) / det
        scale = np.minimum(1, 10 / np.maximum(np.abs(da), np.abs(db)).clip(1e-300))
        a, b = a + scale * da, b + scale * db
        converged = np.abs(da) + np.abs(db) < 1e-10
        if converged.all():
            break
    a_out, b_out = np.full(len(finite), np.nan), np.full(len(finite), np.nan)
    a_out[finite] = np.where(converged, a / s, np.nan)
    b_out[finite] = np.where(converged, b - a * m / s, np.nan)
    return a_out, b_out


def fit(x, k, n) -> Fit:
    """Maximum-likelihood fit of f to per-condition counts; standard errors from the inverse observed information."""
    x, k, n = np.asarray(x, float), np.asarray(k, float), np.asarray(n, float)
    finite, step = separation(x, k, n)
    if not finite[0]:
        if step[0] == np.inf:
            why = "no trial detected"
        elif step[0] == -np.inf:
            why = "every trial detected"
        else:
            det, non = x[k > 0], x[n - k > 0]
            x1, x2 = (non.max(), det.min()) if non.max() <= det.min() else (det.max(), non.min())
            where = f"at {x1:g}" if x1 == x2 else f"between {x1:g} and {x2:g}"
            why = f"detection jumps from none to all {where} (the slope is unbounded)"
        return Fit(None, None, None, None, why)
    a, b = (float(v[0]) for v in fit_many(x, k, n))
    if not math.isfinite(a):
        return Fit(None, None, None, None, "the fit did not converge")
    q = expit(a * x + b)
    w = n * q * (1 - q)
    cov = np.linalg.inv([[(w * x * x).sum(), (w * x).sum()], [(w * x).sum(), w.sum()]])
    return Fit(a, b, math.sqrt(cov[0, 0]), math.sqrt(cov[1, 1]), None)


def bootstrap(x, n, k, levels, resamples: int, rng, by_participant: bool) -> np.ndarray:
    """Thresholds at each of `levels` from refits of `resamples` resampled data sets (levels x resamples).

    Unit of x; +-inf or a jump's midpoint where a resample has no finite fit (see `separation`), NaN
    where Newton failed. by_participant: n, k are (participants x conditions) and whole participants
    are resampled (a cluster bootstrap); otherwise n, k are per condition and trials are resampled
    within each condition.
    """
    if by_participant:
        pick = rng.integers(len(n), size=(resamples, len(n)))
        nb, kb = n[pick].sum(1), k[pick].sum(1)
    else:
        nb = np.broadcast_to(n, (resamples, len(n)))
        kb = rng.binomial(nb, k / n)
    a, b = fit_many(x, kb, nb)
    finite, step = separation(x, kb, nb)
    return np.array([np.where(finite, threshold(a, b, level), step) for level in levels])


def position(value: float, lo: float, hi: float) -> str:
    """'inside', 'above' or 'below' the tested range [lo, hi]."""
    return "above" if value > hi else "below" if value < lo else "inside"


def _number(v):
    """A float for JSON; None for +-inf and NaN."""
    return float(v) if v is not None and math.isfinite(v) else None


def threshold_report(f: Fit, x, k, n, level: float, unit: str) -> dict:
    """Where f reaches `level`: inside the tested range [x.min(), x.max()] as value_<unit>, or which side.

    Outside the range the value is never given as a threshold: it goes to extrapolated_<unit>.
    """
    lo, hi = float(np.min(x)), float(np.max(x))
    value = threshold(f.a, f.b, level) if f.degenerate is None else separation(x, k, n)[1][0]
    side = position(value, lo, hi)
    if f.degenerate and side == "inside":
        statement = f"not estimable: {f.degenerate}"
    elif side == "inside":
        statement = f"{value:.2f} {unit}"
    else:
        bound = f"> {hi:g} {unit}" if side == "above" else f"< {lo:g} {unit}"
        why = f.degenerate or f"extrapolated {value:.3g} {unit}"
        statement = f"{side} the tested range ({bound}); {why}"
    inside = side == "inside" and not f.degenerate
    return {"level": level, "position": side, f"value_{unit}": float(value) if inside else None,
            f"extrapolated_{unit}": None if inside or f.degenerate else _number(value), "statement": statement}


def bootstrap_report(thresholds, lo: float, hi: float, ci_level: float, unit: str) -> dict:
    """Percentile CI (null bound: unbounded) and the fraction of resamples inside [lo, hi], of bootstrap thresholds."""
    t = thresholds[~np.isnan(thresholds)]
    ci = np.quantile(t, [0.5 - ci_level / 2, 0.5 + ci_level / 2], method="nearest")
    return {f"ci_{unit}": [_number(c) for c in ci], "ci_level": ci_level,
            "inside_fraction": float(((t >= lo) & (t <= hi)).mean()), "resamples_failed": len(thresholds) - len(t)}


def analyse(trials: Trials, rule: dict, resamples: int = 2000, seed: int = 0, ci_level: float = 0.95) -> list[dict]:
    """One report per surface: counts and ratios per condition, the fit, CDT and DT with bootstrap CIs.

    rule: twin.perception.thresholds.detection_rule(). Numbers carry the file's unit in their key names.
    The bootstrap resamples participants when there are two or more, else trials within each condition.
    """
    u = trials.unit
    rng = np.random.default_rng(seed)
    reports = []
    for name, group in by_surface(trials):
        det = detected(group.natural, group.confidence, rule["min_confidence"])
        x, n, k = counts(group.condition, det)
        low, high = wilson_interval(k, n, ci_level)
        rows = [{f"condition_{u}": float(xi), "n": int(ni), "detected": int(ki), "ratio": float(ki / ni),
                 "ratio_ci": [float(l_), float(h_)]} for xi, ni, ki, l_, h_ in zip(x, n, k, low, high)]
        f = fit(x, k, n)
        clusters = group.participant is not None and len(np.unique(group.participant)) >= 2
        boot = counts_by_participant(group.condition, det, group.participant) if clusters else (n, k)
        levels = {"cdt": rule["cdt_level"], "dt": rule["dt_level"]}
        thresholds = {key: threshold_report(f, x, k, n, level, u) for key, level in levels.items()}
        if f.degenerate is None and resamples > 0:
            boot_t = bootstrap(x, *boot, levels.values(), resamples, rng, clusters)
            for key, t in zip(levels, boot_t):
                thresholds[key] |= bootstrap_report(t, x[0], x[-1], ci_level, u)
        reports.append({
            "surface": name, "trials": len(det),
            "participants": None if group.participant is None else len(np.unique(group.participant)),
            "conditions": rows,
            "fit": {"method": FIT_METHOD, f"a_per_{u}": f.a, f"a_se_per_{u}": f.a_se, "b": f.b, "b_se": f.b_se,
                    "degenerate": f.degenerate},
            "thresholds": thresholds,
            "bootstrap": {"resamples": resamples, "seed": seed,
                          "by": "participant" if clusters else "trials within condition"}
            if f.degenerate is None and resamples > 0 else None,
        })
    return reports


def simulate_trials(a: float, b: float, conditions, participants: int, repeats: int, rng,
                    min_confidence: int = 3) -> list[dict]:
    """Trials whose detection is drawn from f(x), answered consistently with the detection rule.

    Detected: unnatural with confidence min_confidence..5. Not detected: half natural with any confidence,
    half unnatural with confidence below min_confidence. Rows: participant, condition, natural, confidence.
    """
    rows = []
    for p in range(1, participants + 1):
        for x in conditions:
            for _ in range(repeats):
                if rng.random() < curve(x, a, b):
                    natural, confidence = False, rng.integers(min_confidence, 6)
                elif rng.random() < 0.5:
                    natural, confidence = True, rng.integers(1, 6)
                else:
                    natural, confidence = False, rng.integers(1, min_confidence)
                rows.append({"participant": f"P{p:02d}", "condition": float(x), "natural": bool(natural),
                             "confidence": int(confidence)})
    return rows
