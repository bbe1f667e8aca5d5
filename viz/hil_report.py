"""The HIL run report: an overlay per hinge (target, device, twin) and report.md with the metrics."""

from __future__ import annotations

import json
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the off-screen backend)
import numpy as np  # noqa: E402

from twin.device.spec import DeviceSpec  # noqa: E402
from twin.formats.run import read_run  # noqa: E402
from twin.hil.compare import compare  # noqa: E402


def write_report(spec: DeviceSpec, run_dir, rows: list[dict] | None = None) -> Path:
    """Overlay PNG per hinge (target, device, twin) and report.md with the metrics table; returns report.md."""
    run = read_run(run_dir, spec, incomplete=True)
    d, dev, tw, meta = run.dir, run.device, run.twin, run.meta
    changes_t = [t for t, _ in run.changes] or [0.0]
    rows = rows or compare(spec, dev, tw, changes_t)
    lines = [f"# HIL run: {run.scenario}", "",
             f"Status: {run.status}; device rows {len(dev.time)}, twin rows {len(tw.time)}; "
             f"port {meta.get('port')}; device profile {meta.get('device_profile', 'not recorded')}. Angles are encoder angles (counts x {math.degrees(spec.rad_per_count):.4f} "
             "deg); error = device - twin; lag > 0: the device is later.", "",
             "| hinge | RMSE deg | largest error deg | lag s | settle device s | settle twin s |",
             "|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['hinge']} | {r['rmse_deg']:.3f} | {r['max_error_deg']:.3f} | {r['lag_s']:.4f} | "
                     f"{r['settle_device_s']:.3f} | {r['settle_twin_s']:.3f} |")
    lines.append("")
    for k in range(dev.n_hinges):
        fig, ax = plt.subplots(figsize=(7, 3))
        ax.plot(tw.time, np.degrees(tw.target[:, k]), "k--", lw=0.8, label="target")
        ax.plot(dev.time, np.degrees(dev.angle[:, k]), lw=1.2, label="device")
        ax.plot(tw.time, np.degrees(tw.angle[:, k]), lw=1.0, label="twin")
        ax.set_xlabel("time (s)")
        ax.set_ylabel(f"hinge {k} angle (deg)")
        ax.legend(loc="best", fontsize=8)
        fig.tight_layout()
        name = f"hinge{k}.png"
        fig.savefig(d / name, dpi=90)
        plt.close(fig)
        lines.append(f"![hinge {k}]({name})")
        lines.append("")
    (d / "metrics.json").write_text(json.dumps(rows, indent=2) + "\n")
    path = d / "report.md"
    path.write_text("\n".join(lines))
    return path
