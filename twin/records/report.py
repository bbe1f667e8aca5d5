"""The report record: what a command says of its result, once as data and once in words."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class Report:
    """A command's result: `doc` its --json document (JSON types, the units in the keys' names) and `lines` its
    report for a reader (deg, mm and the spec file's units, as the command prints them)."""

    doc: dict
    lines: list[str]
