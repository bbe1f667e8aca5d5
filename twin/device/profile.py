"""Where device profiles live and which one is selected (docs/formats.md "Device profile").

A device profile is a folder named for the device, under the profiles folder:
$VRSCROLL_DEVICES if set, else $XDG_CONFIG_HOME/vrscroll/devices (~/.config/vrscroll/devices).
The selected profile's name is kept in the file `default` there; no such file means the spec's
defaults (models/vrscroll/spec.toml and its gains). What a profile folder holds, and reading
it, is twin.formats.profile's.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from twin.paths import replacing

ENV = "VRSCROLL_DEVICES"
DEFAULT_FILE = "default"
# `vrscroll device select none` means the spec's defaults, and `default` is the file that keeps the selection
# (a profile folder of that name broke selecting one): no profile can be called either
RESERVED = ("none", DEFAULT_FILE)
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


def profiles_dir() -> Path:
    """The folder holding every profile."""
    if os.environ.get(ENV):
        return Path(os.environ[ENV])
    config = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(config) / "vrscroll" / "devices"


def check_name(name: str) -> str:
    """name, if it can name a profile folder (letters, digits, '_', '.', '-'; 64 at most); else ValueError."""
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise ValueError(f"device profile name {name!r}: use letters, digits, '_', '.' or '-' (64 at most), "
                         "starting with a letter or digit")
    if name.lower() in RESERVED or name.lower().endswith(".part"):
        raise ValueError(f"device profile name {name!r} is reserved (`none` means the spec's defaults, `default` "
                         "keeps the selection, NAME.part is a file being written): choose another")
    return name


def profile_dir(name: str) -> Path:
    """The folder of the profile called name (which need not exist)."""
    return profiles_dir() / check_name(name)


def profile_names() -> list[str]:
    """The profiles there are, sorted by name."""
    root = profiles_dir()
    return sorted(p.name for p in root.iterdir() if p.is_dir() and _NAME.fullmatch(p.name)) if root.is_dir() else []


def default_name() -> str | None:
    """The selected profile's name, or None for the spec's defaults. ValueError if the file is damaged."""
    path = profiles_dir() / DEFAULT_FILE
    if not path.is_file():
        return None
    name = path.read_text().strip()
    try:
        return check_name(name)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def set_default(name: str | None) -> None:
    """Select the profile called name for the commands that follow (None: the spec's defaults)."""
    path = profiles_dir() / DEFAULT_FILE
    if name is None:
        path.unlink(missing_ok=True)
        return
    check_name(name)
    path.parent.mkdir(parents=True, exist_ok=True)
    with replacing(path) as tmp:
        tmp.write_text(name + "\n")
