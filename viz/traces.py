"""Per-hinge trace plots a person can read: angle with its target, the error on its own axis, duty and current.

One function serves the HIL report (device and twin, the error device - twin), `compare` (several runs)
and the step responses of `simulate` and `demo` (the twin alone, the error target - angle against the
settle band: `step_figure`, the one both draw). Series are traces (twin.records.trace.Trace), a twin's or a device's: their angle is the
encoder's, the one the settle band is about and the one both have, so device and twin compare like with like.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the off-screen backend)
import numpy as np  # noqa: E402

ROWS = ("angle", "error", "duty", "current")
COLOURS = ("tab:red", "tab:blue", "tab:green", "tab:purple", "tab:orange", "tab:brown")


def hinge_figure(path, title: str, series: list[tuple[str, object]], hinges, band_deg: float,
                 settle: dict[str, list[float]] | None = None, column_width: float = 4.0) -> Path:
    """A PNG with one column per hinge in `hinges` and four rows sharing time: angle (deg, the first series'
    target dashed), error (deg: the first series minus each later one, at the first's sample times, where
    there are several (device - twin); else target - angle, with the settle band shaded), duty (-1..1) and current (A). settle: label -> per-hinge settle
    time (s, NaN: not settled), drawn as a dotted line on the angle row."""
    hinges = list(hinges)
    fig, axes = plt.subplots(len(ROWS), len(hinges), figsize=(max(9.0, column_width * len(hinges)), 9.5),
                             sharex="col", squeeze=False)
    ref_label, ref = series[0]
    t0 = float(ref.time[0])
    for c, k in enumerate(hinges):
        ax_angle, ax_err, ax_duty, ax_cur = axes[:, c]
        ax_angle.plot(ref.time - t0, np.degrees(ref.target[:, k]), "k--", lw=0.9, label="target")
        for i, (label, s) in enumerate(series):
            colour = COLOURS[i % len(COLOURS)]
            t = s.time - t0
            ax_angle.plot(t, np.degrees(s.angle[:, k]), color=colour, lw=1.2, label=label)
            ax_duty.plot(t, s.duty[:, k], color=colour, lw=0.9, label=label)
            ax_cur.plot(t, s.current[:, k], color=colour, lw=0.9, label=label)
            ts = (settle or {}).get(label)
            if ts is not None and math.isfinite(ts[k]):
                ax_angle.axvline(ts[k], color=colour, ls=":", lw=1.0)
            if len(series) == 1:
                ax_err.plot(t, np.degrees(s.target[:, k] - s.angle[:, k]), color=colour, lw=1.0)
            elif i > 0:
                other = np.interp(ref.time, s.time, s.angle[:, k])
                ax_err.plot(ref.time - t0, np.degrees(ref.angle[:, k] - other), color=colour, lw=1.0,
                            label=f"{ref_label} - {label}")
        if len(series) == 1:
            ax_err.axhspan(-band_deg, band_deg, color="0.85", label=f"settle band ±{band_deg:.2f} deg")
        ax_err.axhline(0.0, color="0.5", lw=0.6)
        ax_angle.set_title(f"hinge {k}")
        ax_cur.set_xlabel("time (s)")
        if c == 0:
            ax_angle.set_ylabel("angle (deg)")
            ax_err.set_ylabel(f"{'target - angle' if len(series) == 1 else 'difference'} (deg)")
            ax_duty.set_ylabel("duty (-1..1)")
            ax_cur.set_ylabel("current (A)")
            ax_angle.legend(loc="best", fontsize=8)
            ax_err.legend(loc="best", fontsize=8)
        for ax in axes[:, c]:
            ax.grid(True, lw=0.3)
    fig.suptitle(title + ("; dotted: settle time (docs/device.md)" if settle else ""), fontsize=11)
    # fixed margins (in): room for the tick labels and titles, not measured from a draw as tight_layout does, which
    # draws every axis once more before the PNG's own draw: half the figure's time (1.1 -> 0.5 s for six hinges)
    width, height = fig.get_size_inches()
    fig.subplots_adjust(left=0.8 / width, right=1 - 0.15 / width, bottom=0.55 / height, top=1 - 0.75 / height,
                        hspace=0.22, wspace=0.28)
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def step_figure(path, title: str, spec, trace, settle_time) -> Path:
    """The twin's step response as `simulate` and `demo` draw it (`hinge_figure` of the twin alone): every hinge's
    angle and target, target - angle against the spec's settle band (deg), duty and current; settle_time: per
    hinge, s (NaN: not settled), dotted on the angle row."""
    return hinge_figure(path, title, [("twin", trace)], range(spec.n_hinges),
                        math.degrees(spec.settle_band * spec.rad_per_count), settle={"twin": settle_time})


def runs_figure(path, runs: list[tuple[str, object]], table: dict[str, list[dict]], n_hinges: int) -> Path:
    """Runs side by side: per hinge, grouped bars of device-twin RMSE per run (deg, top) and each run's
    device - twin over time (deg, below, one axis per hinge). runs: (label, twin.formats.run.Run);
    table: label -> compare() rows."""
    fig = plt.figure(figsize=(max(10.0, 3.2 * n_hinges), 7.5))
    grid = fig.add_gridspec(2, n_hinges, height_ratios=(1, 1.3))
    bars = fig.add_subplot(grid[0, :])
    width = 0.8 / len(runs)
    for i, (label, _) in enumerate(runs):
        rmse = [r["rmse_deg"] for r in table[label]]
        bars.bar(np.arange(n_hinges) + (i - (len(runs) - 1) / 2) * width, rmse, width, label=label,
                 color=COLOURS[i % len(COLOURS)])
    bars.set_xticks(range(n_hinges), [f"hinge {k}" for k in range(n_hinges)])
    bars.set_ylabel("RMSE device - twin (deg)")
    bars.legend(fontsize=8)
    bars.grid(True, axis="y", lw=0.3)
    for k in range(n_hinges):
        ax = fig.add_subplot(grid[1, k])
        for i, (label, run) in enumerate(runs):
            dev, tw = run.device, run.twin
            diff = np.degrees(dev.angle[:, k] - np.interp(dev.time, tw.time, tw.angle[:, k]))
            ax.plot(dev.time - dev.time[0], diff, color=COLOURS[i % len(COLOURS)], lw=0.9)
        ax.axhline(0.0, color="0.5", lw=0.6)
        ax.set_title(f"hinge {k}", fontsize=9)
        ax.set_xlabel("time (s)")
        if k == 0:
            ax.set_ylabel("device - twin (deg)")
        ax.grid(True, lw=0.3)
    fig.suptitle("runs side by side: device against twin", fontsize=11)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
