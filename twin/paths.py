"""Where the project's files are: its data (the `models` package, read through importlib.resources so an
installed wheel finds it as a source checkout does), the cache folder, and how to start the command
line in a subprocess. The one home of each; imports nothing from the project."""

from __future__ import annotations

import contextlib
import errno
import os
import stat
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
    and no .part is left behind. The one way every output file is written.

    What is not a regular file is never replaced by one (issue 40: `--trace /dev/null` once renamed a regular
    file over /dev/null): a character device (/dev/null, a terminal) or a FIFO with a reader is written in
    place (tmp is path); a FIFO nobody reads, a folder, a block device or a socket is refused (ValueError, one
    line) before anything is written, never waited on."""
    path = Path(path)
    held = _special_output(path)
    if held is not None:
        try:
            yield path
        finally:
            if held >= 0:
                os.close(held)
        return
    tmp = path.with_name(path.name + ".part")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _special_output(path: Path) -> int | None:
    """None for no file or a regular file at path; for a special file to write in place, a file descriptor to
    close once it is written (-1: none): a FIFO's, opened here without waiting and held open, so that its reader
    does not see the end of its input before the writer's own open; ValueError for one that cannot be an output."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return None
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISCHR(mode):
        return -1
    if stat.S_ISFIFO(mode):
        try:  # opening a FIFO to write waits for a reader: without one, refuse now rather than wait forever
            return os.open(path, os.O_WRONLY | os.O_NONBLOCK)
        except OSError as exc:
            if exc.errno == errno.ENXIO:
                raise ValueError(f"{path} is a FIFO that nobody reads: start its reader first, or give a file") from None
            raise
    kind = "a folder" if stat.S_ISDIR(mode) else "a block device" if stat.S_ISBLK(mode) else "a socket"
    raise ValueError(f"{path} is {kind}, not a file to write: give a file name")


def cli_command(*args: str) -> list[str]:
    """argv that runs `vrscroll ARGS...` in a subprocess with this interpreter."""
    return [sys.executable, "-m", "twin.cli", *args]


def cli_env(env: dict | None = None, code=None) -> dict:
    """The environment for `cli_command`: the caller's (or `env`), with the folder that holds this `twin`
    package first on PYTHONPATH, so the subprocess runs the same code as its parent from any working folder;
    code: a folder holding another `twin` package (another version, to compare against), put before it (run the
    subprocess with that folder as its working folder too: `python -m` puts that before the path)."""
    out = dict(os.environ if env is None else env)
    here = str(Path(__file__).resolve().parents[1])
    first = () if code is None else (str(Path(code).resolve()),)
    out["PYTHONPATH"] = os.pathsep.join(p for p in (*first, here, out.get("PYTHONPATH", "")) if p)
    return out
