"""docs/concepts/durability.md, The state store → After a kill -9: "the next CLI call starts a new server with the
options of the last `osmo server start`".

A server started with a fixed port, no local pool and its own cpu count is SIGKILLed; the
next plain CLI call starts a server like it, not a default one. A start with other options
says what changed. A damaged options file is an error that names it, never a default server.
"""

from __future__ import annotations

import json
import os
import signal
import stat
from pathlib import Path

from osmo.config import free_port
from tests.conftest import Osmo, wait_gone


def _flags(options: list[str]) -> list[str]:
    """Saved flags without the test fixture's environment.

    ``--runtime process`` (OSMO_RUNTIME) and ``--sandbox-share`` (OSMO_SANDBOX_SHARE).
    """
    out = list(options)
    for flag in ("--runtime", "--sandbox-share"):
        while flag in out:
            i = out.index(flag)
            del out[i:i + 2]
    return out


def _options_file(osmo: Osmo) -> Path:
    return osmo.home / "server-options.json"


def test_the_auto_start_after_kill9_keeps_the_options_of_the_last_start(osmo: Osmo) -> None:
    port = free_port(0)
    endpoint = f"tcp/127.0.0.1:{port}"
    osmo("server", "start", "--listen", endpoint, "--no-local-pool", "--cpus", "3",
         check=True)
    saved = _options_file(osmo)
    assert stat.S_IMODE(saved.stat().st_mode) == 0o600
    shown = osmo("server", "status", check=True).out
    assert f"--listen {endpoint}" in shown and "--no-local-pool" in shown, shown
    pid = osmo.server_pid()
    assert pid is not None
    os.kill(pid, signal.SIGKILL)
    wait_gone(pid)

    nodes = osmo("resource", "list", "--format", "json", check=True).json()  # auto-starts
    new_pid = osmo.server_pid()
    assert new_pid not in (None, pid)
    assert nodes == [], "the auto-started server has a local pool"
    info = json.loads((osmo.home / "server.json").read_text())
    assert endpoint in info["endpoints"], info  # listening where the last start asked
    status = osmo("server", "status", "--format", "json", check=True).json()
    assert isinstance(status, dict)
    assert _flags(status["options"]) == ["--listen", endpoint, "--cpus", "3.0", "--no-local-pool"]


def test_a_start_with_other_options_says_what_changed_and_keeps_the_new_ones(
        osmo: Osmo) -> None:
    osmo("server", "start", "--no-local-pool", "--cpus", "3", check=True)
    again = osmo("server", "start", "--cpus", "5", check=True)  # still running: not applied
    assert "already running" in again.out and "cpus: 3 → 5" in again.out, again.out
    osmo("server", "stop", check=True)
    changed = osmo("server", "start", "--cpus", "5", check=True)
    assert "cpus: 3 → 5" in changed.out and "local_pool: False → True" in changed.out, changed
    assert "saved" in changed.out
    osmo("server", "stop", check=True)
    osmo("list", check=True)  # an automatic start: the options of the last explicit one
    status = osmo("server", "status", "--format", "json", check=True).json()
    assert isinstance(status, dict) and _flags(status["options"]) == ["--cpus", "5.0"]
    unchanged = osmo("server", "stop", check=True)
    assert "changed" not in osmo("server", "start", "--cpus", "5", check=True).out, unchanged


def test_a_damaged_options_file_is_an_error_that_names_it(osmo: Osmo) -> None:
    osmo.home.mkdir(parents=True)
    for text in ("{not json", json.dumps({"argv": ["--cpus", "many"]}),
                 json.dumps({"argv": ["--rm-rf"]}), json.dumps([1, 2])):
        _options_file(osmo).write_text(text)
        r = osmo("list")
        assert r.code == 2, r
        assert "server-options.json" in r.err and "Traceback" not in r.err, r.err
        assert osmo.server_pid() is None
    r = osmo("server", "start", "--cpus", "2")  # an explicit start replaces it
    assert r.code == 0, r
    assert _flags(json.loads(_options_file(osmo).read_text())["argv"]) == ["--cpus", "2.0"]
