"""The paper's Table 1, reproducible: CBS, no_hcevf, full and ours (refined) from the same seeded starts.

`run_evaluation` farms (shape, start) tasks to worker processes; each result
record (one per shape, start and method) is appended to `results.jsonl` and
flushed as it arrives, so an interrupted run keeps what finished and a rerun
with the same settings resumes where it stopped. `summarize` turns the records
into mean ± SD per shape and method, beside the paper's printed values.

Two columns only a twin gives, per record: the MSD where the twin actually ended
(the method's pose, the morph from flat through the gate: `check_move` on a Twin
held at that root pose, firmware in the loop, gravity, settled and held), with the
gate's range and collision verdicts; and the share of the touch surface whose pen
redirection, from the shape the twin reached, is within the perception thresholds
(twin.morphpatch.redirection.threshold_summary). Both from twin.evaluation.morph_outcome, the one
`vrscroll demo` reports too.
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
import statistics
from pathlib import Path

import mujoco
import numpy as np
from tqdm import tqdm

from twin.checks import json_object
from twin.device.spec import load_spec
from twin.evaluation.backends import LocalBackend
from twin.evaluation.cbs import CbsSimulator
from twin.evaluation.morph_outcome import morph_outcome
from twin.evaluation.starts import approach_starts
from twin.formats.records import RecordLog, read_jsonl
from twin.morphpatch.approximation import approximate, measured
from twin.morphpatch.fields import build_fields, exact_signed_distance
from twin.morphpatch.resting import resting
from twin.morphpatch.shapes import load_shape
from twin.paths import MODELS_DIR
from twin.sim.twin import Twin

METHODS = ("cbs", "no_hcevf", "full", "refined")
PAPER_TABLE = MODELS_DIR / "shapes" / "paper_table1.csv"

_CONTEXT: dict = {}  # per worker process: shape -> (mesh, fields, CBS simulator, starts)


def _context(shape: str, n_starts: int, seed: int):
    key = (shape, n_starts, seed)
    if key not in _CONTEXT:
        spec = load_spec()
        mesh = load_shape(shape)
        _CONTEXT[key] = (spec, mesh, build_fields(mesh), CbsSimulator(spec, mesh), Twin(spec),
                         approach_starts(mesh, n_starts, seed=_shape_seed(seed, shape)))
    return _CONTEXT[key]


def _shape_seed(seed: int, shape: str) -> int:
    """Each shape its own stream, the same whichever shapes are chosen."""
    return seed * 1000 + sum(map(ord, shape))


def evaluate_start(task: tuple[str, int, int, int]) -> list[dict]:
    """All methods from one start: a record each with msd_mm, hd_mm, inside_percent, inside_depth_mm and
    inside_over_2mm_percent (the touch surface inside the target: twin.morphpatch.surface_metrics, and the
    share deeper than twin.morphpatch.resting.DEEP), angles_deg, time_ms, the anchor's depth in the target,
    for ours whether its search found a pose resting from outside (`rests`: `approximate` refuses one that
    did not), and what the twin made of it (see the module docstring)."""

    shape, index, n_starts, seed = task
    spec, mesh, fields, cbs, twin, starts = _context(shape, n_starts, seed)
    pose = starts[index]
    results = {"cbs": cbs.run(pose)}
    for variant in METHODS[1:]:
        results[variant] = approximate(fields, pose, spec, variant)
    records = []
    for method, r in results.items():
        r = measured(spec, mesh, r)
        depth = -float(exact_signed_distance(mesh, r.root_pose[None, :3, 3])[0][0])
        deep = resting(spec, mesh, None, r, through=False).deep_share
        records.append({"shape": shape, "start": index, "method": method, "msd_mm": r.msd * 1e3,
                        "hd_mm": r.hd * 1e3, "inside_percent": r.inside * 100, "inside_depth_mm": r.depth * 1e3,
                        "inside_over_2mm_percent": deep * 100, **({} if r.rests is None else {"rests": r.rests}),
                        "angles_deg": np.degrees(r.angles).round(3).tolist(),
                        "time_ms": r.time * 1e3, "anchor_depth_mm": round(depth * 1e3, 4),
                        **twin_outcome(spec, mesh, fields, twin, r)})
    return records


def twin_outcome(spec, mesh, fields, twin, result) -> dict:
    """The morph to a result on the twin held at its root pose (twin.evaluation.morph_outcome): MSD (mm) where
    it came to rest, the gate's range and collision verdicts, the share of the touch surface within the
    perception thresholds, and the morph time (s, the last hinge's settle time; None where a hinge did not
    settle or the range was refused)."""
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(result.root_pose[:3, :3]).ravel())
    twin.set_root_pose(result.root_pose[:3, 3], quat)
    out = morph_outcome(spec, mesh, fields, result, twin)
    verdict = {c.name: c.passed for c in out.gate.checks}  # collision is not checked once range fails
    return {"twin_msd_mm": out.end.msd * 1e3, "gate_range_ok": verdict["range"],
            "gate_collision_ok": verdict.get("collision", False), "share_within": out.redirection["share_within"],
            "morph_time_s": None if math.isnan(out.settle_time) else round(out.settle_time, 4)}


def run_evaluation(out_dir, shapes, n_starts: int = 50, seed: int = 0, workers: int = 2, progress=True,
                   backend=None) -> list[dict]:
    """Evaluate every (shape, start) not yet in out_dir/results.jsonl on `backend` (twin.evaluation.backends;
    default a local pool of `workers` processes); returns all records."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    settings = {"starts": n_starts, "seed": seed, "methods": list(METHODS)}
    meta = out / "settings.json"
    if meta.exists():
        old = json_object(meta)
        if old != settings:
            raise ValueError(f"{out} holds a run with {old}; use another --out for {settings}")
    else:
        meta.write_text(json.dumps(settings))
    log = out / "results.jsonl"
    records = read_records(log)
    done = {(r["shape"], r["start"]) for r in records if r["method"] == METHODS[-1]}
    tasks = [(s, i, n_starts, seed) for s in shapes for i in range(n_starts) if (s, i) not in done]
    if not tasks:
        return records

    bar = tqdm(total=len(tasks), desc="evaluate", unit="start", disable=not progress)
    with RecordLog(log) as f, LocalBackend(workers) if backend is None else contextlib.nullcontext(backend) as pool:
        for _, batch in pool.map(evaluate_start, tasks):
            for r in batch:
                f.write(r)
            records.extend(batch)
            bar.update(1)
    bar.close()
    return records


REQUIRED = ("shape", "start", "method", "msd_mm", "hd_mm", "time_ms")  # what summarize takes from every record
# ... and what it takes together where a record has any of them (records written before a group was measured lack it)
TOGETHER = (("inside_percent", "inside_depth_mm"),
            ("twin_msd_mm", "share_within", "gate_range_ok", "gate_collision_ok", "anchor_depth_mm"))


def read_records(path) -> list[dict]:
    """Records of a results.jsonl: each (shape, start, method) once (the first written), and only the starts
    whose every method is there; a start cut short is computed again. ValueError naming the line for a record
    without REQUIRED, with part of a TOGETHER group, or with a field that is not what evaluate_start writes
    (twin.formats.records)."""
    first = {}
    for r in read_jsonl(path, REQUIRED, TOGETHER):
        key = (r.get("shape"), r.get("start"), r.get("method"))
        first.setdefault(key, r)
    by_start = {}
    for (shape, start, method), r in first.items():
        by_start.setdefault((shape, start), {})[method] = r
    return [r for methods in by_start.values() if set(METHODS) <= set(methods) for r in methods.values()]


def paper_table() -> dict[tuple[str, str], dict]:
    """(shape, method) -> the paper's Table 1 row (mm)."""
    with open(PAPER_TABLE) as f:
        rows = csv.DictReader(line for line in f if not line.startswith("#"))
        return {(r["shape"], r["method"]): {k: float(v) for k, v in r.items() if k.endswith("mm")} for r in rows}


def summarize(records: list[dict]) -> list[dict]:
    """Mean and SD (mm) of MSD and HD per shape and method, with the paper's values and full/CBS ratios."""
    paper = paper_table()
    rows = []
    shapes = list(dict.fromkeys(r["shape"] for r in records))
    for shape in shapes:
        means = {}
        for method in METHODS:
            sel = [r for r in records if r["shape"] == shape and r["method"] == method]
            if not sel:
                continue
            msd, hd = [r["msd_mm"] for r in sel], [r["hd_mm"] for r in sel]
            row = {"shape": shape, "method": method, "n": len(sel),
                   "msd_mean_mm": statistics.fmean(msd), "msd_sd_mm": statistics.stdev(msd) if len(sel) > 1 else 0.0,
                   "hd_mean_mm": statistics.fmean(hd), "hd_sd_mm": statistics.stdev(hd) if len(sel) > 1 else 0.0,
                   "time_median_ms": statistics.median(r["time_ms"] for r in sel)}
            if all("inside_percent" in r for r in sel):  # (records written before it was measured lack it)
                row.update({"inside_mean_percent": statistics.fmean(r["inside_percent"] for r in sel),
                            "inside_depth_max_mm": max(r["inside_depth_mm"] for r in sel)})
            if all("twin_msd_mm" in r for r in sel):
                twin_msd = [r["twin_msd_mm"] for r in sel]
                row.update({"twin_msd_mean_mm": statistics.fmean(twin_msd),
                            "twin_msd_sd_mm": statistics.stdev(twin_msd) if len(sel) > 1 else 0.0,
                            "share_within_mean": statistics.fmean(r["share_within"] for r in sel),
                            "gate_ok_share": statistics.fmean(r["gate_range_ok"] and r["gate_collision_ok"]
                                                              for r in sel),
                            "anchor_depth_max_mm": max(r["anchor_depth_mm"] for r in sel)})
            ref = paper.get((shape, method), {})
            row.update({f"paper_{k}": v for k, v in ref.items()})
            means[method] = row
            rows.append(row)
        if "full" in means and "cbs" in means:
            means["full"]["msd_ratio_full_to_cbs"] = _ratio(means["full"]["msd_mean_mm"], means["cbs"]["msd_mean_mm"])
            if (shape, "full") in paper:
                means["full"]["paper_msd_ratio_full_to_cbs"] = (paper[(shape, "full")]["msd_mean_mm"]
                                                                / paper[(shape, "cbs")]["msd_mean_mm"])
        if "full" in means and "refined" in means:
            for key in ("msd", "hd"):
                means["refined"][f"{key}_drop_from_full"] = 1 - _ratio(means["refined"][f"{key}_mean_mm"],
                                                                        means["full"][f"{key}_mean_mm"])
            pairs = {(r["start"], r["method"]): r["msd_mm"] for r in records if r["shape"] == shape}
            means["refined"]["msd_worst_over_full_mm"] = max(pairs[(i, "refined")] - pairs[(i, "full")]
                                                             for i, m in pairs if m == "full")
    return rows


def _ratio(a: float, b: float) -> float:
    """a / b, NaN where b is 0 (every start fitted exactly: no ratio to show)."""
    return a / b if b else math.nan


def write_tables(rows: list[dict], out_dir, wall_s: float | None = None) -> tuple[Path, Path]:
    """table.md (ours beside the paper's, and the full/CBS MSD ratios) and table.csv."""
    out = Path(out_dir)
    cols = ["shape", "method", "n", "msd_mean_mm", "msd_sd_mm", "hd_mean_mm", "hd_sd_mm", "time_median_ms",
            "inside_mean_percent", "inside_depth_max_mm", "paper_msd_mean_mm", "paper_msd_sd_mm", "paper_hd_mean_mm", "paper_hd_sd_mm",
            "msd_ratio_full_to_cbs", "paper_msd_ratio_full_to_cbs", "twin_msd_mean_mm", "twin_msd_sd_mm",
            "share_within_mean", "gate_ok_share", "anchor_depth_max_mm", "msd_drop_from_full", "hd_drop_from_full",
            "msd_worst_over_full_mm"]
    with open(out / "table.csv", "w", newline="") as f:
        w = csv.DictWriter(f, cols, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()})

    def pm(r, key):
        return f"{r[key + '_mean_mm']:.2f} ± {r[key + '_sd_mm']:.2f}" if key + "_mean_mm" in r else "–"

    def paper_pm(r, key):
        k = f"paper_{key}_mean_mm"
        return f"{r[k]:.2f} ± {r[f'paper_{key}_sd_mm']:.2f}" if k in r else "–"

    lines = ["# Surface approximation: ours beside the paper's Table 1", "",
             "MSD and HD in mm, mean ± SD over starts; the paper's from its Table 1. Shapes' sizes and the",
             "start generator are ours (the paper publishes neither), so absolute values compare loosely;",
             "the ordering and the ratios between methods are what carry over.", ""]
    if wall_s is not None:
        lines += [f"Wall time of this run: {wall_s:.1f} s.", ""]
    lines += ["The twin's columns: MSD where the twin ended after the morph to the method's pose (firmware,",
              "gravity, settled), and the share of the touch surface whose pen redirection from that shape is",
              "within the perception thresholds (mean over starts). refined is ours, beyond the paper.",
              "Inside: the share of the touch surface more than 0.5 mm inside the target (mean over starts) and",
              "the deepest any start's went (mm): where a row of flat flaps cannot follow the surface.", "",
              "| shape | method | n | MSD | paper MSD | HD | paper HD | inside (deepest mm) | MSD on the twin | "
              "within thresholds | median time (ms) |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        twin = f"{r['twin_msd_mean_mm']:.2f} ± {r['twin_msd_sd_mm']:.2f}" if "twin_msd_mean_mm" in r else "–"
        share = f"{r['share_within_mean']:.1%}" if "share_within_mean" in r else "–"
        inside = (f"{r['inside_mean_percent']:.1f} % ({r['inside_depth_max_mm']:.1f})" if "inside_mean_percent" in r
                  else "–")
        lines.append(f"| {r['shape']} | {r['method']} | {r['n']} | {pm(r, 'msd')} | {paper_pm(r, 'msd')} | "
                     f"{pm(r, 'hd')} | {paper_pm(r, 'hd')} | {inside} | {twin} | {share} | {r['time_median_ms']:.2f} |")
    lines += ["", "Full method's MSD relative to CBS's:", "", "| shape | ours | paper |", "|---|---|---|"]
    for r in rows:
        if "msd_ratio_full_to_cbs" in r:
            paper_ratio = r.get("paper_msd_ratio_full_to_cbs")
            lines.append(f"| {r['shape']} | {r['msd_ratio_full_to_cbs']:.2f} | "
                         f"{'–' if paper_ratio is None else f'{paper_ratio:.2f}'} |")
    ours = [r for r in rows if "msd_drop_from_full" in r]
    if ours:
        lines += ["", "Ours (refined) against full: how much lower the mean MSD and HD are, and the most any one",
                  "start's MSD is above full's (mm):", "", "| shape | MSD lower | HD lower | worst start over full |",
                  "|---|---|---|---|"]
        for r in ours:
            lines.append(f"| {r['shape']} | {r['msd_drop_from_full']:.0%} | {r['hd_drop_from_full']:.0%} | "
                         f"{r['msd_worst_over_full_mm']:+.2f} |")
        lines.append(f"| mean over shapes | {statistics.fmean(r['msd_drop_from_full'] for r in ours):.0%} | "
                     f"{statistics.fmean(r['hd_drop_from_full'] for r in ours):.0%} | "
                     f"{max(r['msd_worst_over_full_mm'] for r in ours):+.2f} |")
    md = out / "table.md"
    md.write_text("\n".join(lines) + "\n")
    return md, out / "table.csv"
