"""A server and remote workers as real processes on loopback, for the remote-worker tests.

The server is started through the real CLI with ``--listen`` on a free loopback port and no
local pool; each worker is ``osmo worker --connect ...`` in its own process and folder, with
its own worker token bound to its pool (``osmo token create NAME --role worker --pool POOL``,
made through the server home's admin CLI). All of them are stopped by PID at the end (never by name).
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from osmo.config import free_port
from osmo.transport.rpc import ApiClient
from osmo.transport.zenoh_link import Link
from tests.conftest import REPO, Osmo

_LOG_TIME = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d),(\d{3}) ")


class Cluster:
    """One server (home ``root/server``) plus workers (homes ``root/<name>``)."""

    def __init__(self, root: Path, *, server_args: tuple[str, ...] = (),
                 env: dict[str, str] | None = None, open_router: bool = False,
                 router_config: Path | None = None) -> None:
        self.root = root
        self.port = free_port(0)
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.osmo = Osmo(root / "server")
        self.osmo.env.update(env or {})
        # open_router: a bare zenoh router with no access control at ``endpoint`` (in this
        # process), which the server joins: what is left when the router's wall is off
        # router_config: the same, configured by that zenoh file (its users, its access control)
        self.router: Link | None = (
            Link.router([self.endpoint], config_file=str(router_config)) if router_config
            else Link.router([self.endpoint]) if open_router else None)
        where = (("--connect", self.endpoint) if self.router is not None
                 else ("--listen", self.endpoint))
        self.server_args = (*where, "--no-local-pool", *server_args)
        self.workers: dict[str, subprocess.Popen[bytes]] = {}
        self.env = env or {}
        self.tokens: dict[str, str] = {}

    def token(self, name: str, role: str = "worker", pool: str = "default") -> str:
        """A token ``name`` with ``role`` (made once, through the admin CLI); a worker's
        serves ``pool``."""
        if name not in self.tokens:
            pools = ("--pool", pool) if role == "worker" else ()
            self.tokens[name] = self.osmo("token", "create", name, "--role", role, *pools,
                                          check=True).out.strip()
        return self.tokens[name]

    def start_server(self) -> None:
        self.osmo("server", "start", *self.server_args, check=True)

    @classmethod
    @contextlib.contextmanager
    def started(cls, root: Path) -> Iterator[Cluster]:
        """A cluster whose server runs for the ``with`` block; everything stopped after."""
        cluster = cls(root)
        try:
            cluster.start_server()
            yield cluster
        finally:
            cluster.stop()

    def start_worker(self, name: str, *args: str, pool: str = "default",
                     host: str | None = None, env: dict[str, str] | None = None,
                     wait: bool = True, connect: str | None = None,
                     token: str | None = None) -> subprocess.Popen[bytes]:
        """Start ``osmo worker`` as its own process; wait until the server lists it.

        Its token is ``token``, else one made for it (named after it, role worker).
        """
        worker_env = dict(os.environ, OSMO_HOME=str(self.root / name), PYTHONUNBUFFERED="1",
                          **self.env, **(env or {}))
        worker_env.pop("OSMO_SERVER", None)
        worker_env.setdefault("OSMO_SANDBOX_SHARE", str(self.root))  # as tests.conftest.Osmo
        worker_env["OSMO_TOKEN"] = token if token is not None else self.token(name, pool=pool)
        if host is not None:
            worker_env["OSMO_HOST_ID"] = host
        log = open(self.root / f"{name}.log", "ab")
        proc = subprocess.Popen(
            [sys.executable, "-m", "osmo", "worker", "--connect", connect or self.endpoint,
             "--name", name, "--pool", pool, *args],
            env=worker_env, stdout=log, stderr=log, cwd=REPO, start_new_session=True)
        log.close()
        self.workers[name] = proc
        if wait:
            self.wait_online(name)
        return proc

    @contextlib.contextmanager
    def fake_worker(self, hello: dict[str, Any]) -> Iterator[ApiClient]:
        """A peer with a worker token of its own, registered as ``hello`` and holding its
        liveliness token: a worker that says only what the test makes it say."""
        link = Link.client([self.endpoint], "local")
        try:
            fake = ApiClient(link, timeout=10, token=self.token(hello["id"]))
            fake.call("worker_register", hello)
            alive = link.token(link.key("alive", "worker", hello["id"]))
            try:
                yield fake
            finally:
                alive.close()
        finally:
            link.close()

    def nodes(self) -> dict[str, dict]:
        r = self.osmo("resource", "list", "--format", "json", check=True)
        return {n["node"]: n for n in json.loads(r.out)}

    def wait_online(self, name: str, timeout: float = 30) -> None:
        deadline = time.monotonic() + timeout
        while self.nodes().get(name, {}).get("status") != "online":
            if time.monotonic() > deadline:
                raise AssertionError(f"worker {name} never came online:\n{self.worker_log(name)}")
            time.sleep(0.1)

    def worker_log(self, name: str) -> str:
        return (self.root / f"{name}.log").read_text(errors="replace")

    def server_log_line(self, *texts: str, timeout: float = 30) -> tuple[float, str]:
        """Wait for the first server.log line containing one of ``texts``; return its
        wall-clock time (``time.time()`` scale, from the line's timestamp) and the line."""
        log = self.osmo.home / "server.log"
        deadline = time.monotonic() + timeout
        while True:
            for line in log.read_text(errors="replace").splitlines():
                found = _LOG_TIME.match(line)
                if any(text in line for text in texts) and found is not None:
                    at = datetime.datetime.strptime(found.group(1), "%Y-%m-%d %H:%M:%S")
                    return at.timestamp() + int(found.group(2)) / 1000, line
            if time.monotonic() > deadline:
                raise AssertionError(f"server.log never said {texts!r}:\n{log.read_text()}")
            time.sleep(0.02)

    def signal(self, name: str, sig: int) -> None:
        os.kill(self.workers[name].pid, sig)

    def stop(self) -> None:
        for proc in self.workers.values():
            if proc.poll() is None:
                try:
                    os.kill(proc.pid, signal.SIGCONT)
                    os.kill(proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            proc.wait(timeout=30)
        self.osmo.stop_server()
        if self.router is not None:
            self.router.close()
