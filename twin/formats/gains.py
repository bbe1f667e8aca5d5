"""Gains file (JSON, docs/formats.md "Gains file"): one PID gain set per hinge, in the firmware's units.

    {"format": "vrscroll-gains/1", "units": {...},
     "hinges": [{"hinge": k, "kp", "ki", "kd", "derivative_cutoff_hz", "integral_limit",
                 "deadband_duty", "hold_band_counts"}, ...], "meta": {...}}

Every value is checked against the bounds the firmware takes (`controllers.pid.GAIN_BOUNDS`,
docs/protocol.md "Gain bounds"), so a gains file that reads is one the device accepts. Read and written whole as
the record twin.records.gains.Gains (the gains per hinge and the file's "meta").
"""

from __future__ import annotations

import json
from pathlib import Path

from controllers.pid import GAIN_BOUNDS, PidGains
from twin.checks import json_object, known_keys, number, required_keys
from twin.paths import replacing
from twin.records.gains import Gains

GAINS_FORMAT = "vrscroll-gains/1"
# file key -> PidGains field
KEYS = {"kp": "kp", "ki": "ki", "kd": "kd", "derivative_cutoff_hz": "derivative_cutoff",
        "integral_limit": "integral_limit", "deadband_duty": "deadband_duty", "hold_band_counts": "hold_band"}
UNITS = {"kp": "duty/count", "ki": "duty/(count*s)", "kd": "duty/(count/s)", "derivative_cutoff_hz": "Hz",
         "integral_limit": "duty", "deadband_duty": "duty", "hold_band_counts": "count"}


def check_gains(gains, where: str = "gains") -> None:
    """ValueError naming the hinge and the gain for the first value outside GAIN_BOUNDS (or not finite).

    gains: one PidGains per hinge, or {hinge: PidGains}."""
    for k, g in (gains.items() if isinstance(gains, dict) else enumerate(gains)):
        for key, field in KEYS.items():
            v = number(getattr(g, field), f"{where}: hinge {k}: {key}")
            lo, hi = GAIN_BOUNDS[field]
            if not lo <= v <= hi:
                raise ValueError(f"{where}: hinge {k}: {key} = {v:g} is outside the bounds the firmware takes "
                                 f"[{lo:g}, {hi:g}] (docs/protocol.md, Gain bounds)")


def write_gains(path, gains: Gains) -> None:
    """Write the gains record as a gains file, atomically (checked against the firmware's bounds first)."""
    check_gains(gains.hinges, str(path))
    doc = {
        "format": GAINS_FORMAT,
        "units": UNITS,
        "hinges": [{"hinge": k, **{key: (int(getattr(g, f)) if key == "hold_band_counts" else getattr(g, f))
                                   for key, f in KEYS.items()}} for k, g in enumerate(gains.hinges)],
        **({"meta": gains.meta} if gains.meta else {}),
    }
    with replacing(path) as tmp:
        tmp.write_text(json.dumps(doc, indent=2) + "\n")


def read_gains(path, n: int | None = None) -> Gains:
    """The gains record of a gains file (n: the hinges it must hold); ValueError naming the file, hinge and key for
    anything wrong."""
    path = Path(path)
    doc = json_object(path)
    if doc.get("format") != GAINS_FORMAT:
        raise ValueError(f"{path}: not a {GAINS_FORMAT} gains file (no \"format\": \"{GAINS_FORMAT}\")")
    known_keys(doc, ("format", "units", "hinges", "meta"), str(path))
    if not isinstance(doc.get("meta", {}), dict):
        raise ValueError(f"{path}: \"meta\" must be an object")
    hinges = doc.get("hinges")
    if not isinstance(hinges, list) or not hinges:
        raise ValueError(f"{path}: \"hinges\" must be a list with one entry per hinge")
    entries = {}
    for i, h in enumerate(hinges):
        where = f"{path}: hinges[{i}]"
        if not isinstance(h, dict):
            raise ValueError(f"{where}: expected an object with hinge, {', '.join(KEYS)}")
        known_keys(h, ("hinge", *KEYS), where)
        required_keys(h, ("hinge", *KEYS), where)
        k = h["hinge"]
        if isinstance(k, bool) or not isinstance(k, int) or k < 0 or k in entries:
            raise ValueError(f"{where}: hinge {k!r} is not a new hinge index")
        values = {f: number(h[key], f"{where}: {key}") for key, f in KEYS.items()}
        if values["hold_band"] != int(values["hold_band"]):
            raise ValueError(f"{where}: hold_band_counts = {h['hold_band_counts']!r} is not a whole number of counts")
        values["hold_band"] = int(values["hold_band"])
        entries[k] = PidGains(**values)
    if sorted(entries) != list(range(len(entries))):
        raise ValueError(f"{path}: hinge indices {sorted(entries)} are not 0..{len(entries) - 1}")
    out = [entries[k] for k in range(len(entries))]
    if n is not None and len(out) != n:
        raise ValueError(f"{path}: gains for {len(out)} hinges, the device has {n}")
    check_gains(out, str(path))
    return Gains(out, doc.get("meta", {}))
