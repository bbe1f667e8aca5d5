"""Perception constants of pen redirection, read from models/perception/perception.toml.

`THRESHOLDS` are what MorphPatch keeps redirection under (SI: m and rad);
`paper_fits()` are the paper's four psychometric curves, for comparison and tests.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib

from twin.paths import MODELS_DIR

PERCEPTION_PATH = MODELS_DIR / "perception" / "perception.toml"


@dataclasses.dataclass(frozen=True)
class Thresholds:
    """Largest redirection that users still find natural: position (m) and rotation (rad)."""

    position: float
    rotation: float


@dataclasses.dataclass(frozen=True)
class PaperFit:
    """One of the paper's fits f(x) = 1/(1+exp(a x + b)); x in `unit` (mm or deg)."""

    surface: str
    unit: str
    a: float
    b: float
    cdt: float | None  # None where the paper reports "not reached"
    dt: float | None
    conditions: tuple[float, ...]
    participants: int
    repeats: int


def _load() -> dict:
    with open(PERCEPTION_PATH, "rb") as f:
        return tomllib.load(f)


def load_thresholds() -> Thresholds:
    t = _load()["thresholds"]
    return Thresholds(position=t["position"]["value"] / 1e3, rotation=math.radians(t["rotation"]["value"]))


def detection_rule() -> dict:
    """{'min_confidence': int, 'cdt_level': float, 'dt_level': float}."""
    d = _load()["detection"]
    return {"min_confidence": int(d["answer_unnatural_min_confidence"]["value"]),
            "cdt_level": float(d["cdt_level"]["value"]), "dt_level": float(d["dt_level"]["value"])}


def paper_fits() -> list[PaperFit]:
    def number(v):
        return float(v) if isinstance(v, (int, float)) else None

    return [PaperFit(f["surface"], f["unit"], f["a"], f["b"], number(f["cdt"]), number(f["dt"]),
                     tuple(float(c) for c in f["conditions"]), f["participants"], f["repeats"])
            for f in _load()["fit"]]
