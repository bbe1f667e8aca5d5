"""Spec TOML (docs/formats.md "Spec TOML"): the device's constants, each with its unit and source.

    [section]
    name = { value = 310.0, unit = "rpm", source = "datasheet: ..." }

Values are converted to SI on reading (deg -> rad, rpm -> rad/s; every other unit is SI already)
and back on writing. The writer edits a template with tomlkit, so the file keeps its comments,
layout and every other value's source. Imports only twin.checks from the project:
twin.device.spec reads the spec through this module.
"""

from __future__ import annotations

import math
from pathlib import Path

import tomlkit

from twin.checks import known_keys, number, parse_toml, read_text, required_keys
from twin.paths import replacing

_RPM = 2.0 * math.pi / 60.0
TO_SI = {"deg": math.radians, "rpm": lambda v: v * _RPM}
FROM_SI = {"deg": math.degrees, "rpm": lambda v: v / _RPM}
ENTRY_KEYS = ("value", "unit", "source")

# TOML [section] key -> DeviceSpec field, where the names differ
FIELD = {
    ("mass", "total"): "mass_total",
    ("mass", "motor"): "mass_motor",
    ("mass", "electronics"): "mass_electronics",
}


def read_spec_toml(path, fields, fallback: dict | None = None) -> tuple[dict, dict]:
    """(field -> value in SI, field -> source) from a spec TOML whose entries are exactly `fields`; fallback
    (field -> SI) stands in for entries the file lacks (a device profile written before they were added).

    ValueError naming the file and the key for a missing, unknown or repeated entry, a word where a
    number goes, NaN or inf, or an entry without its unit or source.
    """
    path = Path(path)
    raw = parse_toml(read_text(path), str(path))
    values, sources = {}, {}
    for section, entries in raw.items():
        if not isinstance(entries, dict):
            raise ValueError(f"{path}: {section}: expected a [{section}] table of entries")
        for key, entry in entries.items():
            where = f"{path}: [{section}] {key}"
            if not isinstance(entry, dict):
                raise ValueError(f"{where}: expected {{ value = ..., unit = \"...\", source = \"...\" }}")
            known_keys(entry, ENTRY_KEYS, where)
            required_keys(entry, ENTRY_KEYS, where)
            field = FIELD.get((section, key), key)
            if field in values:
                raise ValueError(f"{where}: {field} is given twice")
            value = entry["value"]
            number(value, f"{where}: value")
            values[field] = value_in_si(value, entry["unit"])
            sources[field] = str(entry["source"])
    for field in (set(fields) - values.keys()) & (fallback or {}).keys():
        values[field], sources[field] = fallback[field], "the spec's: this file was written before it had this entry"
    missing, unknown = set(fields) - values.keys(), values.keys() - set(fields)
    if missing or unknown:
        raise ValueError(f"{path}: missing {sorted(missing)}, unknown {sorted(unknown)}")
    return values, sources


def value_in_si(value, unit: str):
    """A value given in a spec TOML unit, in SI (deg -> rad, rpm -> rad/s; every other unit is SI)."""
    return TO_SI.get(unit, lambda v: v)(value)


def value_in_unit(value, unit: str):
    """A value in SI, in a spec TOML unit (rad -> deg, rad/s -> rpm where the unit says so)."""
    return FROM_SI.get(unit, lambda v: v)(value)


def shown(value, unit: str, fmt: str = ".4g") -> str:
    """A value in SI as text in a spec TOML unit, the unit after it (none for "1" or no unit)."""
    return f"{value_in_unit(value, unit):{fmt}}" + (f" {unit}" if unit not in ("", "1") else "")


def shown_range(low, high, unit: str, fmt: str = ".4g") -> str:
    """Two values in SI as "low .. high unit" in a spec TOML unit (as `shown`)."""
    return f"{value_in_unit(low, unit):{fmt}} .. {shown(high, unit, fmt)}"


def spec_units(path) -> dict[str, str]:
    """DeviceSpec field -> the unit a spec TOML (one read_spec_toml accepts) gives its value in."""
    raw = parse_toml(read_text(path), str(path))
    return {FIELD.get((section, key), key): entry["unit"] for section, entries in raw.items()
            for key, entry in entries.items()}


def write_spec_toml(path, template, values: dict, source: str | dict, header: str = "") -> None:
    """Write the template spec TOML with `values` (field -> SI) and their source (one for all, or field ->
    source) replaced, in the file's units; comments and every other entry stay as they are. `header`: comment
    lines put on top."""
    doc = tomlkit.parse(Path(template).read_text())
    entries = {FIELD.get((s, k), k): doc[s][k] for s in doc for k in doc[s]}
    for field, value in values.items():
        if field not in entries:
            raise ValueError(f"{template}: no entry for {field}")
        entry = entries[field]
        v = value_in_unit(value, entry["unit"])
        entry["value"] = int(round(v)) if isinstance(entry["value"].unwrap(), int) else float(f"{v:.6g}")
        entry["source"] = source[field] if isinstance(source, dict) else source
    text = tomlkit.dumps(doc)
    with replacing(path) as tmp:
        Path(tmp).write_text("".join(f"# {line}\n" for line in header.splitlines()) + text)
