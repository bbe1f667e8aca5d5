"""Sweep file (TOML) and sweep records (JSON lines): docs/formats.md "Sweep file", "Sweep records".

    spec = "models/vrscroll/spec.toml"        # optional: the base design (relative to this file)
    shapes = ["cylinder", "ellipsoid"]
    starts = 3                                # per shape, from the evaluation's seeded generator
    seed = 0
    methods = ["full", "refined"]

    [design]                                  # spec keys, in the unit the spec file gives them
    n_flaps = [5, 7, 9]                       # a list of values ...
    hinge_limit = { from = 90, to = 110, count = 3 }   # ... or a range (deg here, as in spec.toml)

    [plants]                                  # the nominal plant and `draws` drawn around it
    draws = 2
    seed = 0
    tolerance_pct = { no_load_speed = 20, gear_friction = 20 }

The designs are every combination of the [design] values; each is checked (twin.device.design) and
one the device cannot be is refused with the reason. Records: one JSON object per line, appended as
tasks finish, each with its `key`; a line cut short by an interruption is dropped on reading.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from pathlib import Path

import numpy as np
import tomlkit

from twin.checks import known_keys, number, parse_toml, read_text
from twin.paths import replacing
from twin.device.design import FIELDS, INTEGER_FIELDS, design_spec
from twin.device.spec import SPEC_PATH, load_spec
from twin.device.spec_toml import spec_units, value_in_si
from twin.formats.records import read_jsonl

TOP_KEYS = ("spec", "shapes", "starts", "seed", "methods", "design", "plants")
PLANT_KEYS = ("draws", "seed", "tolerance_pct")
RANGE_KEYS = ("from", "to", "count")
# sizes a sweep file may ask for, checked before anything is built (a count of 10^9 once filled 19.5 GB):
MAX_COUNT = 1000  # values in a range, starts per shape, plant draws
MAX_DESIGNS = 10_000  # the product of the design axes
MAX_RUNS = 1_000_000  # designs x shapes x starts x methods x plants


@dataclasses.dataclass
class Sweep:
    """A read sweep file: designs as (overrides in the spec file's units, overrides in SI), and the rest."""

    spec_path: Path
    designs: list[tuple[dict, dict]]
    units: dict  # design key -> its unit in the spec file
    shapes: list[str]
    starts: int
    seed: int
    methods: list[str]
    plant_draws: int = 0
    plant_seed: int = 0
    tolerance_pct: dict = dataclasses.field(default_factory=dict)  # spec key -> +- percent


def read_sweep(path, shapes: list[str], methods: list[str]) -> Sweep:
    """A sweep file, checked: ValueError naming the file, the key and the reason. shapes, methods: those known."""
    path = Path(path)
    doc = parse_toml(read_text(path), str(path))
    known_keys(doc, TOP_KEYS, str(path))
    if "spec" in doc and not isinstance(doc["spec"], str):
        raise ValueError(f"{path}: spec: expected the path of a spec file (a string), got {doc['spec']!r}")
    spec_path = (path.parent / doc["spec"]) if "spec" in doc else SPEC_PATH
    if not spec_path.is_file():
        raise ValueError(f"{path}: spec: no such file {spec_path}")
    base = load_spec(spec_path)
    units = spec_units(spec_path)
    chosen_shapes = _names(doc, "shapes", shapes, path, shapes)
    chosen_methods = _names(doc, "methods", methods, path, ["refined"])
    starts = _whole(doc.get("starts", 3), f"{path}: starts", 1)
    seed = _whole(doc.get("seed", 0), f"{path}: seed", 0, 2 ** 32 - 1)

    design = doc.get("design", {})
    if not isinstance(design, dict):
        raise ValueError(f"{path}: design: expected a [design] table of spec keys")
    axes = {}
    for key, given in design.items():
        where = f"{path}: [design] {key}"
        if key not in FIELDS:
            raise ValueError(f"{where}: not a spec key (the spec's are: {', '.join(FIELDS)})")
        axes[key] = _values(given, where)
    n_designs = math.prod(len(v) for v in axes.values())
    if n_designs > MAX_DESIGNS:
        raise ValueError(f"{path}: [design] makes {n_designs:,} designs; at most {MAX_DESIGNS:,}")
    designs = []
    for combo in itertools.product(*axes.values()):
        given = dict(zip(axes, combo))
        si = {k: value_in_si(v, units[k]) for k, v in given.items()}
        try:
            design_spec(base, si)
        except ValueError as exc:
            shown = ", ".join(f"{k} = {v:g}" for k, v in given.items())
            raise ValueError(f"{path}: [design] {shown}: {exc}") from None
        designs.append((given, si))

    plants = doc.get("plants", {})
    if not isinstance(plants, dict):
        raise ValueError(f"{path}: plants: expected a [plants] table")
    known_keys(plants, PLANT_KEYS, f"{path}: [plants]")
    draws = _whole(plants.get("draws", 0), f"{path}: [plants] draws", 0)
    tolerance = plants.get("tolerance_pct", {})
    if not isinstance(tolerance, dict):
        raise ValueError(f"{path}: [plants] tolerance_pct: expected {{ spec key = percent, ... }}")
    for key, pct in tolerance.items():
        where = f"{path}: [plants] tolerance_pct {key}"
        if key not in FIELDS:
            raise ValueError(f"{where}: not a spec key")
        if key in INTEGER_FIELDS:
            raise ValueError(f"{where}: {key} is a whole number, not a value a plant varies")
        if not 0 <= number(pct, where) < 100:
            raise ValueError(f"{where}: {pct!r} is not a percentage in [0, 100)")
    if draws and not tolerance:
        raise ValueError(f"{path}: [plants] draws = {draws} needs tolerance_pct (which values vary, by how much)")
    runs = n_designs * len(chosen_shapes) * starts * len(chosen_methods) * (draws + 1)
    if runs > MAX_RUNS:
        raise ValueError(f"{path}: {runs:,} runs (designs x shapes x starts x methods x plants); at most {MAX_RUNS:,}")
    return Sweep(spec_path, designs, {k: units[k] for k in axes}, chosen_shapes, starts, seed, chosen_methods,
                 draws, _whole(plants.get("seed", 0), f"{path}: [plants] seed", 0, 2 ** 32 - 1),
                 {k: float(v) for k, v in tolerance.items()})


def _names(doc, key, allowed, path, default) -> list[str]:
    names = doc.get(key, default)
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise ValueError(f"{path}: {key}: expected a list of names from {', '.join(allowed)}")
    for n in names:
        if n not in allowed:
            raise ValueError(f"{path}: {key}: unknown {n!r} (choose from {', '.join(allowed)})")
    if len(set(names)) != len(names):
        raise ValueError(f"{path}: {key}: a name is given twice")
    return names


def _whole(value, where: str, least: int, most: int = MAX_COUNT) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not least <= value <= most:
        raise ValueError(f"{where}: expected a whole number from {least} to {most:,}, got {value!r}")
    return value


def _values(given, where: str) -> list[float]:
    """A design key's values: a list of numbers, or a range { from, to, count } (count values, ends included)."""
    if isinstance(given, dict):
        known_keys(given, RANGE_KEYS, where)
        for k in RANGE_KEYS:
            if k not in given:
                raise ValueError(f"{where}: a range needs from, to and count; missing {k!r}")
        count = _whole(given["count"], f"{where}: count", 1)
        lo, hi = number(given["from"], f"{where}: from"), number(given["to"], f"{where}: to")
        values = [lo] if count == 1 else [float(v) for v in np.linspace(lo, hi, count)]
    elif isinstance(given, list) and given:
        checked = [number(v, f"{where}[{i}]") for i, v in enumerate(given)]
        values = [v if isinstance(v, int) else x for v, x in zip(given, checked)]  # whole numbers stay whole
    else:
        raise ValueError(f"{where}: expected a list of values or {{ from = ..., to = ..., count = ... }}, got {given!r}")
    if len(set(values)) != len(values):
        raise ValueError(f"{where}: a value is given twice")
    return values


def write_sweep(path, shapes: list[str], starts: int, seed: int, methods: list[str], design: dict,
                plants: dict | None = None) -> None:
    """Write a sweep file. design: spec key -> list of values (spec file units); plants: the [plants] table."""
    doc = tomlkit.document()
    doc.add(tomlkit.comment("vrscroll sweep file (docs/sweeps.md, docs/formats.md \"Sweep file\")"))
    for key, value in (("shapes", shapes), ("starts", starts), ("seed", seed), ("methods", methods)):
        doc[key] = value
    doc["design"] = design
    if plants:
        doc["plants"] = plants
    with replacing(path) as tmp:
        Path(tmp).write_text(tomlkit.dumps(doc))


# what summarize_designs takes from every record (the labels come from the sweep file)
REQUIRED = ("key", "msd_mm", "twin_msd_mm", "morph_time_s", "gate_range_ok", "gate_collision_ok")


def read_records(path) -> dict[str, dict]:
    """key -> record of a records file; a line cut short or not a record is skipped, a repeated key read once.
    ValueError naming the line for a record without REQUIRED or with a field that is not what a sweep writes
    (twin.formats.records)."""
    out = {}
    for record in read_jsonl(path, REQUIRED):
        out.setdefault(record["key"], record)
    return out

