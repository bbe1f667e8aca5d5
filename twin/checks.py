"""Checks shared by the readers: numbers, hinge angles, keys. Each raises ValueError naming where."""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import numpy as np


def number(value, where: str) -> float:
    """A JSON or TOML number as a finite float; ValueError naming `where` for a string (even "12": a number in
    quotes is a mistake the file's author should see), a bool, NaN or inf."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{where}: expected a number, got {_short(value)}")
    try:
        x = float(value)
    except OverflowError:  # an integer of hundreds of digits
        raise ValueError(f"{where}: {_short(value)} is not a finite number") from None
    return finite(x, value, where)


def _short(value) -> str:
    """repr of value, cut to 40 characters (a 400-digit number named in one line)."""
    text = repr(value)
    return text if len(text) <= 40 else f"{text[:20]}...{text[-8:]} ({len(text)} characters)"


def cell(text: str, where: str) -> float:
    """A CSV cell as a finite float; ValueError naming `where` for a word, NaN or inf."""
    try:
        x = float(text)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: expected a number, got {text!r}") from None
    return finite(x, text, where)


def finite(x: float, given, where: str) -> float:
    """x, or ValueError naming `where` and what was given when x is NaN or infinite."""
    if not math.isfinite(x):
        raise ValueError(f"{where}: {_short(given)} is not a finite number")
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


# m: the farthest any position the program takes (a start, a tracked pose or pen) may be from the target's
# origin: beyond any tracked room; farther ones are refused before compiled code sees them
REACH_M = 100.0
MAX_FILE_BYTES = 64 << 20  # a JSON or TOML file a reader takes (the largest the project writes is a few MB)


def regular_file(path, limit: int = MAX_FILE_BYTES) -> Path:
    """path, once it is a regular file (not a folder, a FIFO or a device: never waited on) of at most `limit`
    bytes; ValueError naming it otherwise."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: not a regular file" if path.exists() else f"{path}: no such file")
    size = path.stat().st_size
    if size > limit:
        raise ValueError(f"{path}: {size:,} bytes; at most {limit:,}")
    return path


def read_text(path, limit: int = MAX_FILE_BYTES) -> str:
    """A text file's content; ValueError naming the file for one over `limit` bytes, not a regular file (a
    folder, a FIFO: never waited on), or not UTF-8."""
    path = regular_file(path, limit)
    try:
        return path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start}); save it as UTF-8") from None


def parse_json(text, where: str):
    """JSON text (str or bytes) as Python values; ValueError naming `where` for bad JSON or nesting too deep."""
    try:
        return json.loads(text, object_pairs_hook=_unique_keys)
    except DuplicateKey as exc:
        raise ValueError(f"{where}: key {exc.args[0]!r} given twice (which one was meant?)") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{where}: not JSON ({exc})") from None
    except ValueError as exc:  # an integer over Python's 4300 digits
        raise ValueError(f"{where}: not JSON this project reads ({exc})") from None
    except RecursionError:
        raise ValueError(f"{where}: nested too deeply to be one of this project's files") from None


class DuplicateKey(ValueError):
    """A JSON object with one key twice: json keeps the last silently, so a later value could inject itself."""


def _unique_keys(pairs: list) -> dict:
    doc = {}
    for key, value in pairs:
        if key in doc:
            raise DuplicateKey(key)
        doc[key] = value
    return doc


def parse_toml(text: str, where: str) -> dict:
    """TOML text as a dict; ValueError naming `where` for bad TOML or nesting too deep."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{where}: not TOML ({exc})") from None
    except RecursionError:
        raise ValueError(f"{where}: nested too deeply to be one of this project's files") from None


def json_object(path: Path) -> dict:
    """A JSON file holding one object; ValueError naming the file if it is not JSON or not an object."""
    doc = parse_json(read_text(path), str(path))
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: expected a JSON object {{...}}, got {type(doc).__name__}")
    return doc
