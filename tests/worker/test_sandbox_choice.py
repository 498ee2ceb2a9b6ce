"""Choosing the sandbox: ``--sandbox auto|on|off`` on the server and the worker, and a pool's
answer when bubblewrap is missing (the probe is redone with a PATH that lacks it)."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.errors import InfrastructureError
from osmo.layout import Home
from osmo.options import ServerOptions
from osmo.runtime.process import sandbox
from osmo.worker.options import WorkerOptions
from osmo.worker.pool import LocalPool
from tests.conftest import Osmo


@pytest.fixture
def no_bwrap(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    sandbox._probe_result.cache_clear()
    monkeypatch.setenv("PATH", "/nonexistent")
    yield
    monkeypatch.undo()
    sandbox._probe_result.cache_clear()


def test_the_flag_survives_the_command_line() -> None:
    parser = argparse.ArgumentParser()
    ServerOptions.add_arguments(parser)
    off = ServerOptions(sandbox="off")
    assert ServerOptions.from_args(parser.parse_args(off.to_argv())) == off
    assert ServerOptions().to_argv() == []  # auto, the default, is not written
    worker = argparse.ArgumentParser()
    WorkerOptions.add_arguments(worker)
    got = WorkerOptions.from_args(worker.parse_args(["--connect", "tcp/h:1", "--sandbox", "on"]))
    assert got.sandbox == "on"


def test_a_pool_says_whether_it_sandboxes(tmp_path: Path) -> None:
    pool = LocalPool(home=Home(tmp_path), emit=lambda _e: None)
    try:
        assert pool.sandbox is not None and pool.node().labels == {"sandbox": "bwrap"}
    finally:
        pool.close()
    off = LocalPool(home=Home(tmp_path), emit=lambda _e: None, sandbox="off")
    try:
        assert off.sandbox is None and off.node().labels == {"sandbox": "none"}
    finally:
        off.close()


def test_without_bubblewrap_auto_runs_unsandboxed_and_on_refuses(tmp_path: Path,
                                                                 no_bwrap: None) -> None:
    pool = LocalPool(home=Home(tmp_path), emit=lambda _e: None)
    try:
        assert pool.sandbox is None and pool.node().labels == {"sandbox": "none"}
    finally:
        pool.close()
    with pytest.raises(InfrastructureError, match="install the 'bubblewrap' package") as err:
        LocalPool(home=Home(tmp_path), emit=lambda _e: None, sandbox="on")
    assert err.value.exit_code == 3


def test_a_bad_mode_is_a_usage_error(tmp_path: Path) -> None:
    r = Osmo(tmp_path / "home")("server", "start", "--sandbox", "maybe")
    assert r.code == 2 and "invalid choice: 'maybe'" in r.err, r


def test_server_start_with_sandbox_on_and_no_bubblewrap_says_which_package(
        tmp_path: Path) -> None:
    osmo = Osmo(tmp_path / "home")
    osmo.env["PATH"] = "/nonexistent"  # the CLI and the server run by full path
    r = osmo("server", "start", "--sandbox", "on", timeout=60)
    assert r.code == 3, r
    assert "install the 'bubblewrap' package" in r.err and "Traceback" not in r.err, r.err


def test_read_only_shares_survive_the_command_line_and_the_environment(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """``DIR:ro`` on the flag; in OSMO_SANDBOX_SHARE a ``ro`` after a folder (the list is
    ``:``-separated); a server restarted with its options keeps both kinds."""
    monkeypatch.setenv("OSMO_SANDBOX_SHARE", "/scratch:/data:ro:/envs:ro")
    parser = argparse.ArgumentParser()
    ServerOptions.add_arguments(parser)
    got = ServerOptions.from_args(parser.parse_args(["--sandbox-share", "/models:ro"]))
    assert got.sandbox_share == ("/scratch", "/data:ro", "/envs:ro", "/models:ro")
    assert ServerOptions.from_args(parser.parse_args(got.to_argv())).sandbox_share == \
        got.sandbox_share
    assert [sandbox.parse_share(s) for s in got.sandbox_share] == [
        ("/scratch", True), ("/data", False), ("/envs", False), ("/models", False)]
