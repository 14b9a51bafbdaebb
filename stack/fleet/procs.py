"""The fleet's child processes: start one with its log, signal it, stop it (SIGTERM, then SIGKILL)."""

from __future__ import annotations

import signal
import socket
import subprocess
import time
from pathlib import Path


class Proc:
    """One child process (router, world or agent) in its own session, its output in ``log_path``."""

    def __init__(self, name: str, argv: list[str], log_path: Path, env: dict):
        self.name = name
        self.log_path = log_path
        self.log_file = open(log_path, "wb")
        self.p = subprocess.Popen(argv, stdout=self.log_file, stderr=subprocess.STDOUT, env=env, start_new_session=True)
        self.asked_to_stop = False
        """We stopped it (its exit is no crash)."""
        self.killed_at: float | None = None
        """Sim time of a ``--kill`` (or the kill before a ``--restart``)."""
        self.frozen = False
        """SIGSTOPped by a ``--freeze`` and not let go since."""
        self.exited_at: float | None = None
        """Wall time (monotonic) we first saw it ended with code 0 before the world was done."""

    def poll(self) -> int | None:
        return self.p.poll()

    def wait(self, timeout: float) -> int:
        """Its exit code; ``subprocess.TimeoutExpired`` if it runs on past ``timeout``."""
        return self.p.wait(timeout)

    def signal(self, sig: int) -> None:
        if self.p.poll() is None:
            try:
                self.p.send_signal(sig)
            except ProcessLookupError:
                pass

    def kill(self) -> None:
        """SIGKILL (let go first if frozen) and wait for it."""
        if self.frozen:
            self.signal(signal.SIGCONT)
        self.signal(signal.SIGKILL)
        self.wait(5)

    def stop(self, timeout: float = 5.0) -> int | None:
        """SIGTERM, then SIGKILL after ``timeout``."""
        self.asked_to_stop = True
        self.signal(signal.SIGTERM)
        try:
            return self.wait(timeout)
        except subprocess.TimeoutExpired:
            self.signal(signal.SIGKILL)
            return self.wait(5)

    def tail(self, n: int = 5) -> str:
        """Its log's last ``n`` lines on one line."""
        try:
            lines = self.log_path.read_text(errors="replace").strip().splitlines()
        except OSError:
            return ""
        return " | ".join(lines[-n:])

    def close(self) -> None:
        self.log_file.close()


def stop_all(procs: list, timeout: float) -> None:
    """SIGTERM every running process at once (agents: zero velocity on the way out), then wait; SIGKILL stragglers.
    A frozen (SIGSTOPped) agent is let go on first, so it can command its zero too."""
    running = [pr for pr in procs if pr.poll() is None]
    for pr in running:
        pr.asked_to_stop = True
        if pr.frozen:
            pr.signal(signal.SIGCONT)
            pr.frozen = False
        pr.signal(signal.SIGTERM)
    deadline = time.monotonic() + timeout  # one deadline for all: n stragglers cost ``timeout``, not n times it
    for pr in running:
        try:
            pr.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pr.signal(signal.SIGKILL)
            pr.wait(5)


def wait_port(endpoint: str, timeout: float = 10.0, process: Proc | None = None) -> None:
    """Wait until a TCP endpoint (``tcp/HOST:PORT``) accepts connections; TimeoutError if it does not,
    or at once if ``process`` (the router meant to open it) exits."""
    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process is not None and process.poll() is not None:
            raise TimeoutError(f"router exited with code {process.poll()} before opening {endpoint}")
        try:
            with socket.create_connection((host.strip("[]"), int(port)), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise TimeoutError(f"router did not open {endpoint} within {timeout:.0f} s")
