"""Matplotlib charts (files, no screen): the evaluation's bar chart, psychometric curves, a sweep's designs and
Pareto front."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def method_bars(rows: list[dict], methods: list[str], shapes: list[str], path, paper: dict | None = None) -> None:
    """Bars of MSD, HD and the MSD where the twin ended (mean ± SD, mm) per shape and method; the paper's
    means as black ticks. The twin's panel is left out when no row has it.

    rows: dicts with shape, method, msd_mean_mm, msd_sd_mm, hd_mean_mm, hd_sd_mm (and twin_msd_mean_mm,
    twin_msd_sd_mm). paper: (shape, method) -> the paper's row, same keys.
    """
    by = {(r["shape"], r["method"]): r for r in rows}
    panels = [("msd", "MSD (mm)"), ("hd", "HD (mm)")]
    if any("twin_msd_mean_mm" in r for r in rows):
        panels.append(("twin_msd", "MSD on the twin\nafter the morph (mm)"))
    fig, axes = plt.subplots(len(panels), 1, figsize=(max(8, 1.4 * len(shapes)), 3.5 * len(panels)), sharex=True)
    x = np.arange(len(shapes))
    w = 0.8 / len(methods)
    for ax, (metric, label) in zip(axes, panels):
        for j, method in enumerate(methods):
            mean = [by.get((s, method), {}).get(f"{metric}_mean_mm", np.nan) for s in shapes]
            sd = [by.get((s, method), {}).get(f"{metric}_sd_mm", np.nan) for s in shapes]
            pos = x + (j - (len(methods) - 1) / 2) * w
            ax.bar(pos, mean, w, yerr=sd, capsize=2, label=method)
            if paper and metric != "twin_msd":
                ref = [paper.get((s, method), {}).get(f"{metric}_mean_mm", np.nan) for s in shapes]
                ax.scatter(pos, ref, marker="_", s=200, color="black", zorder=3,
                           label="paper" if j == 0 else None)
        ax.set_ylabel(label)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(ncol=len(methods) + 1, fontsize=8)
    axes[-1].set_xticks(x, shapes, rotation=20)
    axes[0].set_title("Surface approximation: mean ± SD over starts (paper's means as black ticks)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def psychometric_curves(reports: list[dict], unit: str, path, paper: dict | None = None) -> None:
    """Detection ratio per condition (Wilson CI bars, dot area ~ trials) and the fit f, one panel per surface.

    reports: twin.perception.psychometric.analyse's, x in `unit`. Dotted lines at the CDT and DT levels; vertical
    lines at the thresholds inside the tested range. paper: {'label', 'a', 'b'}, drawn dashed.
    """
    fig, axes = plt.subplots(1, len(reports), figsize=(5.5 * len(reports), 4), squeeze=False)
    for ax, r in zip(axes[0], reports):
        x = np.array([c[f"condition_{unit}"] for c in r["conditions"]])
        ratio = np.array([c["ratio"] for c in r["conditions"]])
        lo, hi = np.array([c["ratio_ci"] for c in r["conditions"]]).T
        n = np.array([c["n"] for c in r["conditions"]])
        ax.errorbar(x, ratio, yerr=np.clip([ratio - lo, hi - ratio], 0, None), fmt="none", ecolor="gray", capsize=3)
        ax.scatter(x, ratio, s=20 + 80 * n / n.max(), color="C0", zorder=3, label="detection ratio (CI)")
        xs = np.linspace(x.min(), x.max(), 200)
        fit = r["fit"]
        if not fit["degenerate"]:
            ax.plot(xs, 1 / (1 + np.exp(fit[f"a_per_{unit}"] * xs + fit["b"])), color="C0",
                    label=f"fit: a = {fit[f'a_per_{unit}']:.3f}, b = {fit['b']:.2f}")
        if paper:
            ax.plot(xs, 1 / (1 + np.exp(paper["a"] * xs + paper["b"])), "k--", lw=1,
                    label=f"{paper['label']}: a = {paper['a']}, b = {paper['b']}")
        for name, t in r["thresholds"].items():
            ax.axhline(t["level"], color="gray", ls=":", lw=0.8)
            value = t[f"value_{unit}"]
            if value is not None:
                ax.axvline(value, color="C3", ls="-.", lw=0.8)
                ax.annotate(f"{name.upper()} {value:.1f}", (value, t["level"]), xytext=(4, -12),
                            textcoords="offset points", fontsize=8, color="C3")
        ax.set_ylim(-0.03, 1.03)
        ax.set_xlabel(f"redirection ({unit})")
        ax.set_ylabel("detection ratio")
        ax.set_title(r["surface"] or "all trials")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def design_bars(rows: list[dict], path) -> None:
    """Per design, bars of the fit (mean MSD and MSD on the twin, mm) and the morph time (mean, with the worst as
    a tick, s), one bar per method. rows: twin.evaluation.sweep.summarize_designs's."""
    designs = list(dict.fromkeys(r["design"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    by = {(r["design"], r["method"]): r for r in rows}
    panels = [("msd_mean_mm", "MSD (mm)"), ("twin_msd_mean_mm", "MSD on the twin\nafter the morph (mm)"),
              ("morph_time_mean_s", "morph time (s)\nmean, worst as a tick")]
    fig, axes = plt.subplots(len(panels), 1, figsize=(max(7, 1.3 * len(designs)), 3.2 * len(panels)), sharex=True)
    x = np.arange(len(designs))
    w = 0.8 / len(methods)
    for ax, (key, label) in zip(axes, panels):
        for j, method in enumerate(methods):
            pos = x + (j - (len(methods) - 1) / 2) * w
            value = [by.get((d, method), {}).get(key) for d in designs]
            ax.bar(pos, [np.nan if v is None else v for v in value], w, label=method)
            if key == "morph_time_mean_s":
                worst = [by.get((d, method), {}).get("morph_time_max_s") for d in designs]
                ax.scatter(pos, [np.nan if v is None else v for v in worst], marker="_", s=150, color="black", zorder=3)
        ax.set_ylabel(label)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(ncol=len(methods), fontsize=8)
    axes[-1].set_xticks(x, designs, rotation=20, ha="right")
    axes[0].set_title("Designs: fit and morph time, means over shapes, starts and plants")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def pareto_front(rows: list[dict], path) -> None:
    """MSD on the twin against the worst morph time and against the mass, a point per design and method, the
    Pareto front of the three (rows' `pareto`) ringed and named. rows: summarize_designs's."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), sharey=True)
    timed = [r for r in rows if r["morph_time_max_s"] is not None]
    for ax, key, label in ((axes[0], "morph_time_max_s", "worst morph time (s)"), (axes[1], "mass_g", "mass (g)")):
        pts = ax.scatter([r[key] for r in timed], [r["twin_msd_mean_mm"] for r in timed],
                         c=[r["mass_g"] for r in timed], cmap="viridis", s=30, zorder=2)
        front = [r for r in timed if r["pareto"]]
        ax.scatter([r[key] for r in front], [r["twin_msd_mean_mm"] for r in front], s=140, facecolors="none",
                   edgecolors="red", linewidths=1.5, zorder=3, label="Pareto front (fit, morph time, mass)")
        for r in front:
            ax.annotate(f"{r['design']} {r['method']}", (r[key], r["twin_msd_mean_mm"]), fontsize=7,
                        xytext=(4, 4), textcoords="offset points")
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("mean MSD on the twin (mm)")
    axes[0].legend(fontsize=8)
    fig.colorbar(pts, ax=axes, label="mass (g)")
    fig.suptitle("Which design: fit against morph time and mass (lower is better in all three)")
    fig.savefig(path, dpi=110)
    plt.close(fig)
