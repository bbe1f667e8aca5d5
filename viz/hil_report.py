"""The HIL run report: per hinge a figure (angle, device - twin on its own axis, duty, current) and report.md
with the metrics, each column defined."""

from __future__ import annotations

import json
import math
from pathlib import Path

from twin.device.spec import DeviceSpec
from twin.formats.run import read_run
from twin.hil.compare import METRICS, compare
from viz.traces import hinge_figure


def metrics_table(rows: list[dict]) -> list[str]:
    """Markdown lines: the metrics table (compare's rows) and, under it, what each column means."""
    lines = ["| hinge | " + " | ".join(label for _, label, _ in METRICS) + " |",
             "|---:|" + "---:|" * len(METRICS)]
    for r in rows:
        lines.append(f"| {r['hinge']} | " + " | ".join(f"{r[key]:.{3 if key != 'lag_s' else 4}f}"
                                                     for key, _, _ in METRICS) + " |")
    lines += [""] + [f"- **{label}**: {meaning}" for _, label, meaning in METRICS]
    return lines


def write_report(spec: DeviceSpec, run_dir, rows: list[dict] | None = None) -> Path:
    """A figure per hinge (hinge{k}.png) and report.md with the metrics table; returns report.md."""
    run = read_run(run_dir, spec, incomplete=True)
    d, dev, tw, meta = run.dir, run.device, run.twin, run.meta
    changes_t = [t for t, _ in run.changes] or [0.0]
    rows = rows or compare(spec, dev, tw, changes_t)
    lines = [f"# HIL run: {run.scenario}", "",
             f"Status: {run.status}; device rows {len(dev.time)}, twin rows {len(tw.time)}; "
             f"port {meta.get('port')}; device profile {meta.get('device_profile', 'not recorded')}. Angles are "
             f"encoder angles (counts x {math.degrees(spec.rad_per_count):.4f} deg).", ""]
    lines += metrics_table(rows) + [""]
    band = math.degrees(spec.settle_band * spec.rad_per_count)
    for k in range(dev.n_hinges):
        name = f"hinge{k}.png"
        hinge_figure(d / name, f"{run.scenario}: hinge {k}, device and twin",
                     [("device", dev), ("twin", tw)], [k], band, column_width=10.0)
        lines += [f"![hinge {k}]({name})", ""]
    (d / "metrics.json").write_text(json.dumps(rows, indent=2) + "\n")
    path = d / "report.md"
    path.write_text("\n".join(lines))
    return path
