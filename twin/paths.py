"""Where the project's files are: its data (the `models` package, read through importlib.resources so an
installed wheel finds it as a source checkout does), the cache folder, and how to start the command
line in a subprocess. The one home of each; imports nothing from the project."""

from __future__ import annotations

import contextlib
import os
import sys
from importlib import resources
from pathlib import Path

import models

# the data folder (spec, generated MJCF, shapes, perception constants): a real folder in a checkout, an
# editable install and a wheel alike (the package is never zipped)
MODELS_DIR = Path(str(resources.files(models)))


def cache_dir(kind: str) -> Path:
    """Where cached files of one kind live: $VRSCROLL_CACHE/<kind>, default ~/.cache/vrscroll/<kind>
    (`~` expanded in both)."""
    return Path(os.environ.get("VRSCROLL_CACHE", "~/.cache/vrscroll")).expanduser() / kind


@contextlib.contextmanager
def replacing(path):
    """`with replacing(path) as tmp:` write tmp (beside path, path + ".part"); it replaces path when the block
    ends, and is removed if the block fails (a full disk, a check of what was written): path is then as it was,
    and no .part is left behind."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def cli_command(*args: str) -> list[str]:
    """argv that runs `vrscroll ARGS...` in a subprocess with this interpreter."""
    return [sys.executable, "-m", "twin.cli", *args]


def cli_env(env: dict | None = None) -> dict:
    """The environment for `cli_command`: the caller's (or `env`), with the folder that holds this `twin`
    package first on PYTHONPATH, so the subprocess runs the same code as its parent from any working folder."""
    out = dict(os.environ if env is None else env)
    here = str(Path(__file__).resolve().parents[1])
    out["PYTHONPATH"] = os.pathsep.join(p for p in (here, out.get("PYTHONPATH", "")) if p)
    return out
