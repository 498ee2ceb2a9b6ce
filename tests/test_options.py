"""Server and worker options: one definition each, parsed from flags and written back as flags
(how ``osmo server start`` hands them to the background server) without loss."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from osmo.config import DEFAULT_CLUSTER
from osmo.errors import UsageError
from osmo.options import ServerOptions
from osmo.worker.options import DEFAULT_POOL, WorkerOptions
from tests.conftest import Osmo


def _server(argv: list[str]) -> ServerOptions:
    parser = argparse.ArgumentParser()
    ServerOptions.add_arguments(parser)
    return ServerOptions.from_args(parser.parse_args(argv))


@pytest.mark.parametrize("options", [
    ServerOptions(),
    ServerOptions(listen=("tcp/0.0.0.0:7447", "tls/localhost:7448"), cluster="lab", cpus=1.5,
                  gpus=2, local_pool=False, reconnect_grace=3.0),
    ServerOptions(connect=("tcp/10.0.0.5:7447",), zenoh_config="/etc/osmo/zenoh.json5"),
    ServerOptions(runtime="container", container_engine="docker"),
    ServerOptions(runtime="process"),
    ServerOptions(log_limit=256 << 20),
])
def test_server_options_survive_the_command_line(options: ServerOptions) -> None:
    assert _server(options.to_argv()) == options


def test_no_flags_are_the_defaults() -> None:
    assert _server([]) == ServerOptions()
    assert ServerOptions().to_argv() == []
    assert ServerOptions().cluster == DEFAULT_CLUSTER


def _worker(argv: list[str]) -> WorkerOptions:
    parser = argparse.ArgumentParser()
    WorkerOptions.add_arguments(parser)
    return WorkerOptions.from_args(parser.parse_args(["--connect", "tcp/h:1", *argv]))


def test_worker_flags_and_defaults() -> None:
    assert _worker([]) == WorkerOptions(connect=("tcp/h:1",))
    assert _worker([]).pool == DEFAULT_POOL and _worker([]).cluster == DEFAULT_CLUSTER
    got = _worker(["--memory", "1Gi", "--label", "a=b", "--pool", "gpu"])
    assert (got.memory, got.labels, got.pool) == (1 << 30, {"a": "b"}, "gpu")
    assert _worker([]).log_limit == 64 << 20 == ServerOptions().log_limit
    assert _worker(["--log-limit", "2Gi"]).log_limit == 2 << 30


@pytest.mark.parametrize("value", ["lots", "512Ki", "-1"])
def test_a_log_limit_must_be_a_size_of_1mi_or_more(value: str,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        _server([f"--log-limit={value}"])
    assert exited.value.code == 2
    assert "--log-limit" in capsys.readouterr().err


@pytest.mark.parametrize(("argv", "message"), [
    (["--memory", "lots"], "--memory 'lots'"),
    (["--label", "novalue"], "--label 'novalue': write KEY=VALUE"),
])
def test_bad_worker_flags_say_what_to_write(argv: list[str], message: str) -> None:
    with pytest.raises(UsageError, match=message):
        _worker(argv)


@pytest.mark.parametrize("name", ["local", "server", "a/b", "-x", "w\nfake"])
def test_a_worker_refuses_a_name_it_cannot_have(tmp_path: Path, name: str) -> None:
    r = Osmo(tmp_path / "home")("worker", "--connect", "tcp/127.0.0.1:9", f"--name={name}",
                                "--home", str(tmp_path / "w"), timeout=60)
    assert r.code == 2, r
    assert "is not valid" in r.err and "Traceback" not in r.err, r.err
