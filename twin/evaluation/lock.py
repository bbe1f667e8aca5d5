"""One writer per output folder: an exclusive lock on a file in the folder.

`fcntl.flock` on FOLDER/.lock; the kernel drops it when the holder's file is closed or its
process dies, so a crashed run never leaves the folder locked.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path

LOCK_NAME = ".lock"


@contextlib.contextmanager
def folder_lock(folder, what: str):
    """Hold FOLDER/.lock while the block runs; ValueError at once if another process holds it.

    what: the job, for the message (e.g. "vrscroll evaluate")."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK_NAME
    with open(path, "a+") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "another process"
            raise ValueError(f"{folder}: another {what} is writing to this folder ({holder}); wait for it to end "
                             "or use another folder") from None
        f.seek(0)
        f.truncate()
        f.write(f"pid {os.getpid()}\n")
        f.flush()
        yield
