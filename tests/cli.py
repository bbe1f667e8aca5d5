"""One way for the tests to run `vrscroll` as a user does: a subprocess of this interpreter, the same code
as the tests (twin.paths.cli_command / cli_env), output captured."""

from __future__ import annotations

import subprocess

from twin.paths import cli_command, cli_env


def vrscroll(*args: str, cwd=None, env: dict | None = None, timeout: float = 180) -> subprocess.CompletedProcess:
    """`vrscroll ARGS...` to completion; stdout and stderr as text."""
    return subprocess.run(cli_command(*map(str, args)), capture_output=True, text=True, timeout=timeout, cwd=cwd,
                          env=cli_env(env))
