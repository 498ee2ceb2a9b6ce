"""Shared fixtures: an isolated OSMO_HOME with a real server process, and a CLI runner.

Servers are started through the real CLI (``osmo server start``) on loopback with a free
port, and stopped by PID at the end (never by name).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@dataclass
class Result:
    """A finished CLI run."""

    code: int
    out: str
    err: str

    def json(self) -> object:
        return json.loads(self.out)


class Osmo:
    """Runs the real ``osmo`` CLI against one OSMO_HOME."""

    def __init__(self, home: Path) -> None:
        self.home = home
        self.env = dict(os.environ, OSMO_HOME=str(home), PYTHONUNBUFFERED="1")
        self.env.pop("OSMO_SERVER", None)

    def __call__(self, *args: str, timeout: float = 180, check: bool = False) -> Result:
        proc = subprocess.run([sys.executable, "-m", "osmo", *args], env=self.env,
                              capture_output=True, text=True, timeout=timeout, cwd=REPO)
        result = Result(proc.returncode, proc.stdout, proc.stderr)
        if check and result.code != 0:
            raise AssertionError(f"osmo {' '.join(args)} exited {result.code}\n"
                                 f"stdout:\n{result.out}\nstderr:\n{result.err}")
        return result

    def submit(self, spec: Path | str, *args: str) -> str:
        """Submit and return the workflow id (asserts success)."""
        r = self("submit", str(spec), *args, check=True)
        line = [ln for ln in r.out.splitlines() if ln.startswith("Workflow ID - ")][0]
        return line.split(" - ", 1)[1].strip()

    def query(self, wf_id: str) -> dict:
        return self("query", wf_id, "--format", "json", check=True).json()  # type: ignore[return-value]

    def wait_for(self, wf_id: str, predicate, timeout: float = 120) -> dict:  # type: ignore[no-untyped-def]
        """Re-query until ``predicate(info)`` holds (event waits are in the SDK; this is a test)."""
        deadline = time.monotonic() + timeout
        while True:
            info = self.query(wf_id)
            if predicate(info):
                return info
            if time.monotonic() > deadline:
                raise AssertionError(f"condition not reached; last state: {info}")
            time.sleep(0.1)

    def server_pid(self) -> int | None:
        try:
            return int(json.loads((self.home / "server.json").read_text())["pid"])
        except (OSError, ValueError, KeyError):
            return None

    def stop_server(self) -> None:
        """Stop this home's server by PID (SIGTERM, then SIGKILL)."""
        pid = self.server_pid()
        if pid is None:
            return
        try:
            os.kill(pid, signal.SIGTERM)
        except ProcessLookupError:
            return
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                return
            time.sleep(0.05)
        os.kill(pid, signal.SIGKILL)


def write(path: Path, text: str) -> Path:
    """Write ``text`` to ``path`` (creating parents) and return the path."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


@pytest.fixture
def osmo(tmp_path: Path) -> Iterator[Osmo]:
    """A CLI bound to a fresh OSMO_HOME; its server (auto-started on use) is stopped after."""
    runner = Osmo(tmp_path / "home")
    yield runner
    runner.stop_server()


@pytest.fixture(scope="module")
def shared_osmo(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Osmo]:
    """One server shared by a test module (for tests that do not kill it)."""
    runner = Osmo(tmp_path_factory.mktemp("osmo") / "home")
    runner("server", "start", check=True)
    yield runner
    runner.stop_server()
