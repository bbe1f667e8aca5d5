"""Matplotlib charts (files, no screen): the evaluation's bar chart."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def method_bars(rows: list[dict], methods: list[str], shapes: list[str], path, paper: dict | None = None) -> None:
    """Bars of MSD and HD (mean ± SD, mm) per shape and method; paper's means as black ticks.

    rows: dicts with shape, method, msd_mean_mm, msd_sd_mm, hd_mean_mm, hd_sd_mm.
    paper: (shape, method) -> the paper's row, same keys.
    """
    by = {(r["shape"], r["method"]): r for r in rows}
    fig, axes = plt.subplots(2, 1, figsize=(max(8, 1.4 * len(shapes)), 7), sharex=True)
    x = np.arange(len(shapes))
    w = 0.8 / len(methods)
    for ax, metric in zip(axes, ("msd", "hd")):
        for j, method in enumerate(methods):
            mean = [by.get((s, method), {}).get(f"{metric}_mean_mm", np.nan) for s in shapes]
            sd = [by.get((s, method), {}).get(f"{metric}_sd_mm", np.nan) for s in shapes]
            pos = x + (j - (len(methods) - 1) / 2) * w
            ax.bar(pos, mean, w, yerr=sd, capsize=2, label=method)
            if paper:
                ref = [paper.get((s, method), {}).get(f"{metric}_mean_mm", np.nan) for s in shapes]
                ax.scatter(pos, ref, marker="_", s=200, color="black", zorder=3,
                           label="paper" if j == 0 else None)
        ax.set_ylabel(f"{metric.upper()} (mm)")
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(ncol=len(methods) + 1, fontsize=8)
    axes[1].set_xticks(x, shapes, rotation=20)
    axes[0].set_title("Surface approximation: mean ± SD over starts (paper's means as black ticks)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
