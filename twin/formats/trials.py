"""Trials CSV (docs/formats.md "Trials CSV"): redirection trials for psychometric fitting.

A header and one row per trial: `condition_<unit>` (the redirection, e.g. `condition_mm` or
`condition_deg`), `natural` (yes/no, true/false, 1/0, natural/unnatural), `confidence` (1-5) and
optionally `participant` and `surface`. Blank lines and #-lines are skipped.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import re
from pathlib import Path

import numpy as np

from twin.checks import read_text
from twin.paths import replacing

ANSWERS = {"yes": True, "true": True, "1": True, "natural": True,
           "no": False, "false": False, "0": False, "unnatural": False}
CONDITION_COLUMN = re.compile(r"condition_([a-z][a-z0-9]*)")
# surfaces one trials file may hold: each is fitted and bootstrapped on its own and drawn as a panel of one row
# of psychometric.png (5.5 in at 110 dpi: 16 make 9,680 px; 5,000 once asked for a figure 3 million px wide);
# the paper's studies have 4
MAX_SURFACES = 16


@dataclasses.dataclass(frozen=True)
class Trials:
    """One row per trial; condition in `unit`; participant and surface are None when the file has no such column."""

    condition: np.ndarray  # float
    natural: np.ndarray  # bool
    confidence: np.ndarray  # int, 1-5
    participant: np.ndarray | None  # str
    surface: np.ndarray | None  # str
    unit: str

    def subset(self, mask: np.ndarray) -> Trials:
        def pick(v):
            return None if v is None else v[mask]

        return Trials(self.condition[mask], self.natural[mask], self.confidence[mask],
                      pick(self.participant), pick(self.surface), self.unit)


def read_trials(path) -> Trials:
    """Read a trials CSV; ValueError naming the file and line for anything wrong. Blank and #-lines are skipped."""
    path = Path(path)
    lines = [(i, line) for i, line in enumerate(read_text(path).splitlines(keepends=True), start=1)
             if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise ValueError(f"{path}: empty file (expected a header: condition_<unit>,natural,confidence)")
    try:
        header_line, *rows = zip(lines, csv.reader(line for _, line in lines))
    except csv.Error as exc:  # a field over the csv module's limit, a NUL byte
        raise ValueError(f"{path}: not a trials CSV ({exc})") from None
    columns = [c.strip().lower() for c in header_line[1]]
    where = f"{path}:{header_line[0][0]}"
    units = [m.group(1) for c in columns if (m := CONDITION_COLUMN.fullmatch(c))]
    if "condition" in columns and not units:
        raise ValueError(f"{where}: name the unit of column 'condition' in the header: condition_mm or condition_deg")
    if len(units) != 1:
        raise ValueError(f"{where}: expected one column condition_<unit> (e.g. condition_mm or condition_deg), "
                         f"got {len(units)}")
    missing = [c for c in ("natural", "confidence") if c not in columns]
    if missing:
        raise ValueError(f"{where}: missing column(s) {', '.join(missing)}")
    col = {name: columns.index(name) for name in ("natural", "confidence", "participant", "surface") if name in columns}
    col["condition"] = columns.index(f"condition_{units[0]}")
    if not rows:
        raise ValueError(f"{path}: no trials after the header")
    values = {name: [] for name in col}
    surfaces = set()
    for (lineno, _), cells in rows:
        where = f"{path}:{lineno}"
        if len(cells) != len(columns):
            raise ValueError(f"{where}: {len(cells)} fields, the header has {len(columns)}")
        cell = {name: cells[i].strip() for name, i in col.items()}
        try:
            x = float(cell["condition"])
        except ValueError:
            x = math.nan
        if not math.isfinite(x):
            raise ValueError(f"{where}: condition {cell['condition']!r} is not a number")
        answer = ANSWERS.get(cell["natural"].lower())
        if answer is None:
            raise ValueError(f"{where}: natural {cell['natural']!r} is not one of {', '.join(ANSWERS)}")
        if not re.fullmatch(r"[1-5]", cell["confidence"]):
            raise ValueError(f"{where}: confidence {cell['confidence']!r} is not an integer 1-5")
        for name in ("participant", "surface"):
            if name in cell and not cell[name]:
                raise ValueError(f"{where}: empty {name}")
        values["condition"].append(x)
        values["natural"].append(answer)
        values["confidence"].append(int(cell["confidence"]))
        for name in ("participant", "surface"):
            if name in cell:
                values[name].append(cell[name])
        if "surface" in cell and cell["surface"] not in surfaces:
            surfaces.add(cell["surface"])
            if len(surfaces) > MAX_SURFACES:
                raise ValueError(f"{where}: surface {cell['surface']!r:.40} is the {len(surfaces)}th; a trials file "
                                 f"holds at most {MAX_SURFACES} (MAX_SURFACES: a fit and a plot panel each)")
    trials = Trials(np.array(values["condition"]), np.array(values["natural"]), np.array(values["confidence"]),
                    np.array(values["participant"]) if "participant" in col else None,
                    np.array(values["surface"]) if "surface" in col else None, units[0])
    for name, group in by_surface(trials):
        if len(np.unique(group.condition)) < 2:
            of = f" (surface {name!r})" if name is not None else ""
            raise ValueError(f"{path}: fewer than 2 distinct conditions{of}; a curve needs at least two")
    return trials


def by_surface(trials: Trials) -> list[tuple[str | None, Trials]]:
    """[(surface, its trials)] in order of first appearance, or [(None, trials)] without a surface column."""
    if trials.surface is None:
        return [(None, trials)]
    names = list(dict.fromkeys(trials.surface.tolist()))
    return [(name, trials.subset(trials.surface == name)) for name in names]


def write_trials(path, rows: list[dict], unit: str) -> None:
    """Write trials (participant, condition, natural, confidence[, surface]) as a trials CSV in `unit`."""
    surface = any("surface" in r for r in rows)
    with replacing(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["participant", *(["surface"] if surface else []), f"condition_{unit}", "natural", "confidence"])
        for r in rows:
            w.writerow([r["participant"], *([r["surface"]] if surface else []), f"{r['condition']:.10g}",
                        "yes" if r["natural"] else "no", r["confidence"]])
