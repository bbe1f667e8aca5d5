"""`vrscroll serve` in a subprocess, for the session player, the tests and the benchmark."""

from __future__ import annotations

import re
import signal
import subprocess
from pathlib import Path

from twin.paths import cli_command, cli_env


class ServiceProcess:
    """`python -m twin.cli serve --listen 0 ARGS...`; `url` once it is serving, `pid`, `stderr_path`."""

    def __init__(self, *args: str, stderr_path=None, code=None):
        """code: a folder holding another `twin` package to serve with (another version, to compare against);
        default this one."""
        self.stderr_path = Path(stderr_path) if stderr_path else None
        self._stderr = open(self.stderr_path, "w") if self.stderr_path else subprocess.DEVNULL
        self.proc = subprocess.Popen(cli_command("serve", "--listen", "0", *args), cwd=code,
                                     stdout=subprocess.PIPE, stderr=self._stderr, text=True, env=cli_env(code=code))
        self.banner = ""
        for line in self.proc.stdout:  # a token line may come first; the banner names the URL
            self.banner += line
            found = re.search(r"ws://\S+:(\d+)", line)
            if found:
                self.url = found.group(0)
                self.port = int(found.group(1))
                break
        else:
            self.stop()
            why = self.stderr_path.read_text() if self.stderr_path else ""
            raise RuntimeError(f"vrscroll serve did not start: {self.banner!r} {why}")

    @property
    def pid(self) -> int:
        return self.proc.pid

    def rss_bytes(self) -> int:
        """The service process's resident memory (Linux /proc)."""
        for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
        raise RuntimeError("no VmRSS in /proc status")

    def stop(self) -> int:
        """SIGTERM (the service closes the device link and its worker), then wait; the exit status."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self.proc.stdout.close()
        if self.stderr_path:
            self._stderr.close()
        return self.proc.returncode

    def __enter__(self) -> "ServiceProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
