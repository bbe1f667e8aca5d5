"""One way for the tests to run `vrscroll` as a user does: a subprocess of this interpreter, the same code
as the tests (twin.paths.cli_command / cli_env), output captured."""

from __future__ import annotations

import subprocess
import tempfile

from twin.paths import cli_command, cli_env


# where a command runs unless a test says: what it writes by default (simulate.png, demo.png) lands there,
# never in the repository
WORK = tempfile.mkdtemp(prefix="vrscroll-test-cwd-")


def vrscroll(*args: str, cwd=None, env: dict | None = None, timeout: float = 180) -> subprocess.CompletedProcess:
    """`vrscroll ARGS...` to completion, in WORK unless cwd says; stdout and stderr as text."""
    return subprocess.run(cli_command(*map(str, args)), capture_output=True, text=True, timeout=timeout,
                          cwd=cwd or WORK, env=cli_env(env))
