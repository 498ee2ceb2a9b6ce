"""A registry stand-in on loopback: it asks for Basic auth and records what each pull sent.

No image registry is reachable here. This one answers the distribution API's first step
(``GET /v2/``: 401 with a Basic challenge until the right credential comes) and says every
manifest is unknown, so a pull fails after showing what credential it carried. Manifest
requests wait until ``release`` is set (at most ``HOLD`` seconds): a test sees what the
pull printed while the pull is still under way. While a
request is being answered it also looks, like ``ps e`` would, at every process's argv and
environment for the password (``seen_in_processes``).

podman talks plain HTTP to it when ``registries.conf`` marks it insecure
(:meth:`FakeRegistry.registries_conf`, handed over with ``CONTAINERS_REGISTRIES_CONF``).
"""

from __future__ import annotations

import base64
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

HOLD = 60.0  # s: the longest a manifest request waits for ``release``


class FakeRegistry:
    """The stand-in's state: ``host`` (``127.0.0.1:PORT``), what came, what leaked."""

    def __init__(self, password: str) -> None:
        self.password = password
        self.host = ""
        self.authorizations: list[str] = []  # every Authorization header, decoded
        self.paths: list[str] = []
        self.seen_in_processes: list[str] = []
        self.release = threading.Event()
        self.release.set()  # clear it to hold manifest requests

    def registries_conf(self, folder: Path, *others: FakeRegistry) -> Path:
        """A ``registries.conf`` marking this registry (and ``others``) insecure (HTTP)."""
        path = folder / "registries.conf"
        path.write_text("".join(f'[[registry]]\nlocation = "{r.host}"\ninsecure = true\n\n'
                                for r in (self, *others)))
        return path

    def _scan_processes(self) -> None:
        needle = self.password.encode()
        for proc in Path("/proc").iterdir():
            if not proc.name.isdigit():
                continue
            for part in ("cmdline", "environ"):
                try:
                    if needle in (proc / part).read_bytes():
                        self.seen_in_processes.append(f"{proc.name}/{part}")
                except OSError:
                    continue  # gone, or another user's


@contextmanager
def fake_registry(password: str) -> Iterator[FakeRegistry]:
    """Serve a :class:`FakeRegistry` on a free loopback port while the block runs."""
    state = FakeRegistry(password)

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - the http.server API
            state.paths.append(self.path)
            header = self.headers.get("Authorization", "")
            if header.startswith("Basic "):
                state.authorizations.append(base64.b64decode(header[6:]).decode(errors="replace"))
            state._scan_processes()
            if "/manifests/" in self.path:
                state.release.wait(HOLD)
            if not header:
                self.send_response(401)
                self.send_header("WWW-Authenticate", 'Basic realm="osmo-test"')
                self.send_header("Content-Length", "0")
                self.end_headers()
                return
            body = b'{"errors":[{"code":"MANIFEST_UNKNOWN","message":"manifest unknown"}]}'
            self.send_response(200 if self.path == "/v2/" else 404)
            self.send_header("Content-Type", "application/json")
            self.send_header("Docker-Distribution-API-Version", "registry/2.0")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            if self.command != "HEAD":
                self.wfile.write(body)

        do_HEAD = do_GET  # noqa: N815

        def log_message(self, format: str, *args: object) -> None:  # noqa: A002
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    state.host = f"127.0.0.1:{server.server_address[1]}"
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield state
    finally:
        server.shutdown()
        server.server_close()
        thread.join()
