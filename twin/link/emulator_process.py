"""`vrscroll emulate` in a subprocess, for tests and benchmarks: its pty, its command log, a kill switch."""

from __future__ import annotations

import json
import signal
import subprocess
from pathlib import Path

from twin.paths import cli_command, cli_env


class EmulatorProcess:
    """`vrscroll emulate --log LOG ARGS` in a subprocess; `port` is its pty, `log` its JSON-lines command log.
    code: a folder holding another `twin` package to emulate with (another version, to compare against)."""

    def __init__(self, log, *args: str, code=None):
        self.log = Path(log)
        self._stderr = open(self.log.with_suffix(".stderr"), "w")
        self.proc = subprocess.Popen(cli_command("emulate", "--log", str(self.log), *args), cwd=code,
                                     stdout=subprocess.PIPE, stderr=self._stderr, text=True, env=cli_env(code=code))
        line = self.proc.stdout.readline().strip()  # the pty path, printed once the device is running
        if not line.startswith("/dev/"):
            self.stop()
            raise RuntimeError(f"emulator did not start: {line!r} {self.log.with_suffix('.stderr').read_text()}")
        self.port = line

    def events(self, kind: str | None = None) -> list[dict]:
        """The emulator's log so far (every line must be valid JSON)."""
        if not self.log.exists():
            return []
        rows = [json.loads(x) for x in self.log.read_text().splitlines() if x.strip()]
        return [r for r in rows if kind is None or r["event"] == kind]

    def kill(self) -> None:
        """Pull the plug: SIGKILL, the pty vanishes."""
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(5)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self.proc.stdout.close()
        self._stderr.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
