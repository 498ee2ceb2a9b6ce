"""Running the real CLI on a pseudo-terminal, as a person at a terminal sees it."""

from __future__ import annotations

import os
import pty
import subprocess
import sys
import time
from collections.abc import Callable

from tests.conftest import REPO


def in_pty(*args: str, env: dict[str, str], timeout: float = 120,
           seen: Callable[[str], None] | None = None) -> tuple[int, str]:
    """Run ``osmo ARGS`` with a pseudo-terminal as stdin, stdout and stderr.

    ``seen(output so far)`` is called after each read, to act while the command runs.

    Returns:
        its exit code and everything it wrote (escape sequences included).
    """
    master, slave = pty.openpty()
    proc = subprocess.Popen([sys.executable, "-m", "osmo", *args], stdin=slave, stdout=slave,
                            stderr=slave, env=dict(env, COLUMNS="160", TERM="xterm"), cwd=REPO,
                            close_fds=True)
    os.close(slave)
    chunks: list[bytes] = []
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            try:
                data = os.read(master, 65536)
            except OSError:  # EIO: the other side closed (the process ended)
                break
            if not data:
                break
            chunks.append(data)
            if seen is not None:
                seen(b"".join(chunks).decode(errors="replace"))
    finally:
        os.close(master)
        if proc.poll() is None and time.monotonic() >= deadline:
            proc.kill()
    return proc.wait(timeout=60), b"".join(chunks).decode(errors="replace")
