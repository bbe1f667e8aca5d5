"""Checks shared by the readers: numbers, hinge angles, keys. Each raises ValueError naming where."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np


def number(value, where: str) -> float:
    """value as a finite float; ValueError naming `where` for a word, a bool, NaN or inf."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise ValueError(f"{where}: expected a number, got {value!r}")
    try:
        x = float(value)
    except ValueError:
        raise ValueError(f"{where}: expected a number, got {value!r}") from None
    if not math.isfinite(x):
        raise ValueError(f"{where}: {value!r} is not a finite number")
    return x


def numbers(values, where: str, count: int | None = None) -> np.ndarray:
    """A list of finite numbers (of `count` items when given) as a float array."""
    if not isinstance(values, (list, tuple)):
        raise ValueError(f"{where}: expected a list of numbers, got {values!r}")
    if count is not None and len(values) != count:
        raise ValueError(f"{where}: expected {count} numbers, got {len(values)}")
    return np.array([number(v, f"{where}[{i}]") for i, v in enumerate(values)], float)


def hinge_angles(values_deg, n: int, limit: float, where: str, limit_name: str = "the hinge range") -> np.ndarray:
    """n hinge angles given in degrees, each finite and within +-limit (rad, called `limit_name` in
    messages); returned in rad."""
    if not isinstance(values_deg, (list, tuple)) or len(values_deg) != n:
        got = len(values_deg) if isinstance(values_deg, (list, tuple)) else repr(values_deg)
        raise ValueError(f"{where}: expected {n} hinge angles in degrees, got {got}")
    deg = numbers(values_deg, where)
    limit_deg = math.degrees(limit)
    for k, a in enumerate(deg):
        if abs(a) > limit_deg + 1e-9:
            raise ValueError(f"{where}: hinge {k} at {a:g} deg is outside {limit_name} +-{limit_deg:g} deg")
    return np.radians(deg)


def known_keys(doc: dict, allowed, where: str) -> None:
    """ValueError naming the first key of doc that is not in `allowed`."""
    unknown = [k for k in doc if k not in allowed]
    if unknown:
        raise ValueError(f"{where}: unknown key {unknown[0]!r} (expected {', '.join(sorted(allowed))})")


def required_keys(doc: dict, needed, where: str) -> None:
    """ValueError naming the first key of `needed` that doc lacks."""
    missing = [k for k in needed if k not in doc]
    if missing:
        raise ValueError(f"{where}: missing key {missing[0]!r}")


def json_object(path: Path) -> dict:
    """A JSON file holding one object; ValueError naming the file if it is not JSON or not an object."""
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: expected a JSON object {{...}}, got {type(doc).__name__}")
    return doc
