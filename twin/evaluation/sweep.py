"""Design sweeps: designs x shapes x starts x methods x plants, on a backend, resumable (docs/sweeps.md).

A task is one (design, shape, start, method, plant): the method approximates the shape from the start
with the design (twin.morphpatch.approximation, or CBS), then the design's twin morphs to the result
with the plant's physics under the design's firmware (twin.evaluation.table1.twin_outcome: the gate's
run from flat, held at the result's root pose), and the record gets the fit (MSD, HD), the morph time,
the MSD where the twin ended and the design's mass. Each record carries `key`, a hash of everything
its task depends on (the base spec's values included), and is appended to records.jsonl as it comes:
a second run computes only the keys not there, so an interrupted sweep resumes, and a sweep grown by a
design or a shape computes only what is new.
"""

from __future__ import annotations

import collections
import csv
import dataclasses
import hashlib
import json
import statistics
from pathlib import Path

import numpy as np
from tqdm import tqdm

from twin.device.design import design_spec
from twin.device.spec import DeviceSpec, load_spec
from twin.device.variation import drawn_scales, scaled
from twin.evaluation.cbs import CbsSimulator
from twin.evaluation.starts import approach_starts
from twin.evaluation.table1 import _shape_seed, twin_outcome
from twin.formats.records import RecordLog
from twin.formats.sweep import Sweep, read_records
from twin.morphpatch.approximation import approximate, measured
from twin.morphpatch.fields import build_fields
from twin.morphpatch.shapes import load_shape
from twin.sim.twin import Twin

RECORDS = "records.jsonl"
_TARGETS: dict = {}  # per worker process: (shape, starts, seed) -> (mesh, fields, starts)
_TWINS: collections.OrderedDict = collections.OrderedDict()  # per worker: (design, plant) -> Twin (its firmware, physics)
_CBS: collections.OrderedDict = collections.OrderedDict()  # per worker process: (design, shape) -> CbsSimulator
# twins (about 12 MB each) and CBS simulators a worker keeps, the least recently used dropped first: 300 drawn
# plants once grew a worker from 0.9 to 3.7 GB (issue 40); plants are the innermost loop, so a design's plants
# beyond this are built again for each shape and start
MAX_CACHED = 16


def cached(cache: collections.OrderedDict, key, make):
    """cache[key], made by make() when absent; at most MAX_CACHED entries, the least recently used dropped."""
    if key in cache:
        cache.move_to_end(key)
        return cache[key]
    cache[key] = value = make()
    while len(cache) > MAX_CACHED:
        cache.popitem(last=False)
    return value


@dataclasses.dataclass(frozen=True)
class Task:
    """What a worker gets (small and picklable: the design's spec travels whole, ~2 kB)."""

    key: str
    spec: DeviceSpec  # the design's
    shape: str
    start: int
    starts: int
    seed: int
    method: str
    plant: tuple  # ((spec key, scale on the design's value), ...); () is the nominal


def design_label(given: dict) -> str:
    """A design's name in tables and plots: its overrides, 'base' for none."""
    return " ".join(f"{k}={v:g}" for k, v in given.items()) or "base"


def with_unit(key: str, unit: str) -> str:
    """A design value's name where it leaves the program: the spec key and its spec file unit (hinge_limit_deg)."""
    return key if unit == "1" else f"{key}_{unit.replace('*', '').replace('/', '_per_').replace('^', '')}"


def sweep_plants(sweep: Sweep) -> list[dict]:
    """Per plant, spec key -> scale on the design's value: the nominal ({}) first, then the draws, each key
    scaled uniformly within +-its tolerance (twin.device.variation.drawn_scales: draw i depends on the seed
    and i only)."""
    tolerance = {k: pct / 100 for k, pct in sweep.tolerance_pct.items()}
    return [{}] + [drawn_scales(tolerance, sweep.plant_seed, i) for i in range(1, sweep.plant_draws + 1)]


def sweep_tasks(sweep: Sweep) -> tuple[list[Task], list[dict]]:
    """Every task of a sweep, designs outermost, and per task the labels its record starts with."""
    base = load_spec(sweep.spec_path)
    fingerprint = hashlib.sha256(json.dumps(dataclasses.asdict(base), sort_keys=True).encode()).hexdigest()[:16]
    tasks, labels = [], []
    for d, (given, si) in enumerate(sweep.designs):
        spec = design_spec(base, si)
        for shape in sweep.shapes:
            for start in range(sweep.starts):
                for method in sweep.methods:
                    for p, plant in enumerate(sweep_plants(sweep)):
                        what = {"base": fingerprint, "design": given, "shape": shape, "start": start,
                                "starts": sweep.starts, "seed": sweep.seed, "method": method, "plant": plant}
                        key = hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:20]
                        tasks.append(Task(key, spec, shape, start, sweep.starts, sweep.seed, method,
                                          tuple(sorted(plant.items()))))
                        labels.append({"key": key, "design": design_label(given), "design_index": d,
                                       "design_values": {with_unit(k, sweep.units[k]): v for k, v in given.items()},
                                       "shape": shape, "start": start, "method": method, "plant": p,
                                       "plant_scales": plant, "mass_g": round(spec.mass_total * 1e3, 3)})
    return tasks, labels


def _target(shape: str, starts: int, seed: int):
    key = (shape, starts, seed)
    if key not in _TARGETS:
        mesh = load_shape(shape)
        _TARGETS[key] = (mesh, build_fields(mesh), approach_starts(mesh, starts, seed=_shape_seed(seed, shape)))
    return _TARGETS[key]


def run_task(task: Task) -> dict:
    """One task's results (a backend task): fit, morph and where the twin ended; see the module docstring."""
    spec = task.spec
    mesh, fields, starts = _target(task.shape, task.starts, task.seed)
    # the plant differs only in physical values: its MJCF and its drive model (the tuner's rule)
    twin = cached(_TWINS, (spec, task.plant), lambda: Twin(scaled(spec, dict(task.plant))))
    if task.method == "cbs":
        result = cached(_CBS, (spec, task.shape), lambda: CbsSimulator(spec, mesh)).run(starts[task.start])
    else:
        result = approximate(fields, starts[task.start], spec, task.method)
    result = measured(spec, mesh, result)
    return {"msd_mm": result.msd * 1e3, "hd_mm": result.hd * 1e3, "time_ms": result.time * 1e3,
            "angles_deg": np.degrees(result.angles).round(3).tolist(),
            **twin_outcome(spec, mesh, fields, twin, result)}


def run_sweep(out_dir, sweep: Sweep, backend, progress=True) -> list[dict]:
    """Run every task of the sweep whose key is not yet in out_dir/records.jsonl on `backend`
    (twin.evaluation.backends); returns the sweep's records, in task order."""

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tasks, labels = sweep_tasks(sweep)
    done = read_records(out / RECORDS)
    todo = [i for i, t in enumerate(tasks) if t.key not in done]
    with RecordLog(out / RECORDS) as log, tqdm(total=len(tasks), initial=len(tasks) - len(todo), desc="sweep",
                                                unit="task", disable=not progress) as bar:
        for index, result in backend.map(run_task, [tasks[i] for i in todo]):
            record = {**labels[todo[index]], **result}
            log.write(record)
            done[record["key"]] = record
            bar.update(1)
    return [{**done[t.key], **label} for t, label in zip(tasks, labels)]  # this sweep's labels (design_index)


def summarize_designs(records: list[dict]) -> list[dict]:
    """Per design and method: mass (g), mean fit and twin MSD (mm), mean and worst morph time (s), the share of
    morphs that settled and passed the gate, and whether the row is on the Pareto front of twin MSD, morph
    time and mass (no other row at least as good in all three and better in one)."""
    rows = []
    groups: dict = {}
    for r in records:
        groups.setdefault((r["design_index"], r["method"]), []).append(r)
    for (_, method), sel in groups.items():
        times = [r["morph_time_s"] for r in sel if r["morph_time_s"] is not None]
        rows.append({"design": sel[0]["design"], **sel[0]["design_values"],
                     "method": method, "n": len(sel), "mass_g": sel[0]["mass_g"],
                     "msd_mean_mm": statistics.fmean(r["msd_mm"] for r in sel),
                     "twin_msd_mean_mm": statistics.fmean(r["twin_msd_mm"] for r in sel),
                     "morph_time_mean_s": statistics.fmean(times) if times else None,
                     "morph_time_max_s": max(times) if times else None,
                     "settled_share": len(times) / len(sel),
                     "gate_ok_share": statistics.fmean(r["gate_range_ok"] and r["gate_collision_ok"] for r in sel)})
    objectives = [(r["twin_msd_mean_mm"], r["morph_time_max_s"], r["mass_g"]) for r in rows]
    for r, a in zip(rows, objectives):
        r["pareto"] = a[1] is not None and not any(
            b[1] is not None and all(y <= x for x, y in zip(a, b)) and b != a for b in objectives)
    return rows


def write_table(records: list[dict], path_stem) -> Path:
    """The records as one table, a row per task (list and dict fields flattened): Parquet where pyarrow is
    installed, CSV otherwise. Returns the path written."""
    rows = [_flat(r) for r in records]
    columns = list(dict.fromkeys(k for r in rows for k in r))
    try:
        import pyarrow
        import pyarrow.parquet
    except ImportError:
        return write_csv(rows, Path(f"{path_stem}.csv"), columns)
    path = Path(f"{path_stem}.parquet")
    pyarrow.parquet.write_table(pyarrow.table({c: [r.get(c) for r in rows] for c in columns}), path)
    return path


def write_csv(rows: list[dict], path: Path, columns: list[str] | None = None) -> Path:
    """Rows as a CSV with the given columns (default: every key, in order of appearance)."""

    columns = columns or list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, columns)
        w.writeheader()
        for r in rows:
            w.writerow({k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()})
    return path


def _flat(record: dict) -> dict:
    out = {}
    for k, v in record.items():
        if isinstance(v, dict):
            out.update({f"{k}.{kk}": vv for kk, vv in v.items()})
        elif isinstance(v, list):
            out.update({f"{k}.{i}": vv for i, vv in enumerate(v)})
        else:
            out[k] = v
    return out

