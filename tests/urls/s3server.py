"""A real S3-compatible server for tests: s3rver (npm), installed on first use, run on loopback.

s3rver is installed with npm into ``<repo>/.cache/s3rver`` (git-ignored) the first time a test
needs it, under a file lock so parallel sessions install once. Each server runs as a child
``node`` process on 127.0.0.1 with a free port and its own data folder, and is stopped by its
PID. It accepts the access key ``S3RVER``; it checks SigV2 signatures but, in 3.7.1, not SigV4
ones (only the key id), so signature correctness is tested against AWS's published examples.
Node runs with ``--openssl-legacy-provider`` because s3rver's ListObjectsV2 continuation tokens
use DES, which OpenSSL 3 (node >= 17) only offers through its legacy provider.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
CACHE = REPO / ".cache" / "s3rver"
VERSION = "3.7.1"
ACCESS_KEY = "S3RVER"
SECRET_KEY = "S3RVER"


class Unavailable(Exception):
    """s3rver cannot be installed or started here; the message says why."""


def install() -> Path:
    """Return s3rver's entry script, installing it with npm into :data:`CACHE` if missing.

    Raises:
        Unavailable: node or npm is missing, or ``npm install`` failed.
    """
    script = CACHE / "node_modules" / "s3rver" / "bin" / "s3rver.js"
    if script.exists():
        return script
    npm = shutil.which("npm")
    if shutil.which("node") is None or npm is None:
        raise Unavailable("node and npm are needed to install s3rver (the S3 test server)")
    CACHE.mkdir(parents=True, exist_ok=True)
    with open(CACHE / ".install.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not script.exists():
            proc = subprocess.run(
                [npm, "install", "--prefix", str(CACHE), "--no-audit", "--no-fund",
                 "--no-save", "--loglevel=error", f"s3rver@{VERSION}"],
                capture_output=True, text=True, timeout=600, cwd=CACHE)
            if proc.returncode != 0 or not script.exists():
                raise Unavailable(f"npm install s3rver@{VERSION} failed "
                                  f"(exit {proc.returncode}): {proc.stderr[-2000:]}")
    return script


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@contextmanager
def s3rver(data: Path, timeout: float = 30.0) -> Iterator[str]:
    """Run s3rver on loopback with ``data`` as its folder; yield its endpoint URL.

    Raises:
        Unavailable: it could not be installed, or did not start within ``timeout`` seconds.
    """
    script = install()
    port = free_port()
    data.mkdir(parents=True, exist_ok=True)
    log = open(data.parent / f"s3rver-{port}.log", "wb")
    proc = subprocess.Popen(
        ["node", "--openssl-legacy-provider", str(script), "-d", str(data), "-a", "127.0.0.1", "-p", str(port), "--silent",
         "--no-vhost-buckets"], stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        _wait_listening(proc, port, timeout, Path(log.name))
        yield f"http://127.0.0.1:{port}"
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGTERM)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait()
        log.close()


def _wait_listening(proc: subprocess.Popen[bytes], port: int, timeout: float,
                    log: Path) -> None:
    """Return once ``port`` accepts connections; raise :class:`Unavailable` if it never does."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise Unavailable(f"s3rver exited {proc.returncode}: {log.read_text()[-2000:]}")
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return
        except OSError:
            time.sleep(0.05)
    raise Unavailable(f"s3rver did not listen on port {port} within {timeout}s")
