"""Malformed API requests, sent raw to a real server: each is a usage error (exit 2) with one
log line, never an infrastructure error and never a traceback in ``server.log``.

The table covers every client verb with wrong types, missing fields, huge strings and nested
junk. Requests go through :class:`~osmo.transport.rpc.ApiClient` (JSON the client would never
send) or straight onto the zenoh key (bytes that are not JSON at all).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import pytest

from osmo.errors import OsmoError, SpecError, UsageError
from osmo.sdk.connect import Connection
from tests.conftest import Osmo, write
from tests.hostile.test_names_datasets import raw_api

HUGE = "x" * 100_000
JUNK: Any = {"a": [1, {"b": None}], "c": [[[]]]}
DEEP: Any = [[[[[[[[[[["deep"]]]]]]]]]]]
EMPTY = '{"entries": [], "version": 1}'  # a valid manifest of no files
HELLO = {"id": "w", "pool": "p", "address": "127.0.0.1"}  # what a hello needs, no more

CASES: list[Any] = [
    ("submit", {}),
    ("submit", {"spec": 5}),
    ("submit", {"spec": JUNK}),
    ("submit", {"spec": {"workflow": {"name": "x", "tasks": []}}, "pool": 7}),
    ("submit", {"source": "wf.yaml"}),
    ("submit", {"source": {"path": 1, "text": None}}),
    ("submit", {"source": {"path": "/x/wf.yaml", "text": "a: 1"}, "set_values": "n=1"}),
    ("submit", {"spec": {"workflow": {"name": "x"}}, "type_paths": [1, 2]}),
    ("submit", {"spec": {}, "reused": {"a": "/etc"}}),
    ("cancel", {}),
    ("cancel", {"workflow_id": 7}),
    ("cancel", {"workflow_id": HUGE}),
    ("restart", {"workflow_id": ["a"]}),
    ("get", {"workflow_id": None}),
    ("get", {"workflow_id": JUNK}),
    ("get", {"workflow_id": "wf-1\n\x1b[2J"}),
    ("status", {"workflow_id": HUGE}),
    ("list", {"statuses": "RUNNING"}),
    ("list", {"statuses": ["NOPE"]}),
    ("list", {"statuses": [JUNK]}),
    ("list", {"limit": 99999999999999999999}),
    ("list", {"limit": -1}),
    ("list", {"limit": "5"}),
    ("list", {"name": JUNK}),
    ("list", {"name": HUGE}),
    ("logs", {"workflow_id": "ok-1", "task": 5}),
    ("logs", {"workflow_id": "ok-1", "retry": "x"}),
    ("logs", {"workflow_id": "ok-1", "retry": -1}),
    ("logs", {"workflow_id": "ok-1", "cursor": "x"}),
    ("logs", {"workflow_id": "ok-1", "cursor": {"files": "x", "seq": "y"}}),
    ("logs", {"workflow_id": "ok-1", "cursor": {"files": {"a": "b"}, "seq": 0}}),
    ("logs", {"workflow_id": "ok-1", "cursor": {"files": {}, "seq": 99999999999999999999}}),
    ("logs", {"workflow_id": "ok-1", "tail": -1}),
    ("logs", {"workflow_id": "ok-1", "tail": "10"}),
    ("logs", {"workflow_id": "ok-1", "since": "10m"}),
    ("logs", {"workflow_id": "ok-1", "since": True}),
    ("logs", {"workflow_id": "ok-1", "stream": "secret"}),
    ("logs", {"workflow_id": "ok-1", "stream": JUNK}),
    ("spec", {"workflow_id": DEEP}),
    ("lineage", {}),
    ("lineage", {"target": 5}),
    ("lineage", {"target": HUGE}),
    ("lineage", {"target": "dataset:x:99999999999999999999999"}),
    ("lineage", {"target": "dataset:../x"}),
    ("lineage", {"target": "ok-1:a", "downstream": "yes"}),
    ("artifact_list", {"workflow_id": "ok-1", "task": ["a"]}),
    ("artifact_get", {}),
    ("artifact_get", {"target": JUNK}),
    ("dataset_list", {"name": 5}),
    ("dataset_info", {}),
    ("dataset_info", {"ref": None}),
    ("dataset_tag", {"ref": "ds:1"}),
    ("dataset_tag", {"ref": "ds:1", "tag": JUNK}),
    ("dataset_download", {"ref": "ds", "regex": "("}),
    ("dataset_download", {"ref": "ds", "regex": 5}),
    ("dataset_upload", {"name": "ds"}),
    ("dataset_upload", {"name": "ds", "manifest": "not json", "source": {}}),
    ("dataset_upload", {"name": "ds", "manifest": "{}", "source": "x"}),
    ("dataset_upload", {"name": "ds", "manifest": '{"entries": 5}', "source": {}}),
    ("dataset_upload", {"name": "ds", "manifest": '{"entries": []}', "source": {},
                         "metadata": [1]}),
    ("dataset_upload", {"name": "ds", "manifest": EMPTY, "source": {}}),
    ("dataset_upload", {"name": "ds", "manifest": EMPTY, "source": {"owner": "../x"}}),
    ("dataset_upload", {"name": "ds", "manifest": EMPTY,
                         "source": {"owner": "client-1", "host_id": 5}}),
    ("credential_set", {}),
    ("credential_set", {"name": "c", "payload": "x"}),
    ("credential_set", {"name": "c", "payload": {"k": JUNK}}),
    ("credential_set", {"name": HUGE, "payload": {"k": "v"}}),
    ("credential_delete", {}),
    ("credential_delete", {"name": JUNK}),
    ("no_such_verb", {}),
    ("worker_register", {**HELLO, "capacity": "junk"}),
    ("worker_register", {**HELLO, "capacity": {"cpu": "x"}}),
    ("worker_register", {**HELLO, "capacity": {"gpu": -1}}),
    ("worker_register", {**HELLO, "capacity": {"memory": 2**70}}),
    ("worker_register", {**HELLO, "labels": 5}),
    ("worker_register", {**HELLO, "labels": {"a": JUNK}}),
    ("worker_register", {**HELLO, "active": "wf-1:a:0"}),
    ("worker_register", {**HELLO, "finished": [5]}),
    ("worker_register", {**HELLO, "pool": JUNK}),
    ("worker_register", {**HELLO, "draining": "yes"}),
    ("worker_register", {"id": ["x"]}),
    ("worker_register", {"id": "w", "address": "127.0.0.1"}),  # no pool
    ("worker_register", {"id": "local"}),
    ("worker_register", {"id": "w\n2026-01-01 00:00:00 INFO fake log line"}),
    ("worker_register", {"id": "a/b"}),
    ("worker_drain", {}),
    ("worker_drain", {"id": 5}),
]
RAW_PAYLOADS = [b"not json", b"[1, 2]", b"1" * 5000, b'"a string"', b"[" * 100_000,
                b'{"workflow_id": ' + b"[" * 100_000, b"\xff\xfe"]


@pytest.fixture(scope="module")
def server(shared_osmo: Osmo, tmp_path_factory: pytest.TempPathFactory) -> Osmo:
    """A server with one finished workflow, ``ok-1`` (task ``a``)."""
    spec = write(tmp_path_factory.mktemp("wf") / "ok.yaml",
                 "workflow:\n  name: ok\n  tasks:\n  - name: a\n    command: [echo, hi]\n")
    shared_osmo("submit", str(spec), "--wait", check=True)
    return shared_osmo


@pytest.fixture
def raw(server: Osmo) -> Iterator[Connection]:
    yield from raw_api(server)


def _log(server: Osmo) -> str:
    return (server.home / "server.log").read_text(errors="replace")


def _check_log(server: Osmo, before: int) -> None:
    new = _log(server)[before:]
    assert "Traceback" not in new and "InfrastructureError" not in new, new[-3000:]
    assert len(new.splitlines()) <= 1, new[-3000:]  # one line, not a dump


@pytest.mark.parametrize("verb,request_", CASES, ids=[
    f"{case.values[0] if hasattr(case, 'values') else case[0]}-{i}"
    for i, case in enumerate(CASES)])
def test_malformed_request_is_a_usage_error(server: Osmo, raw: Connection, verb: str,
                                            request_: dict[str, Any]) -> None:
    before = len(_log(server))
    with pytest.raises(OsmoError) as info:
        raw.api.call(verb, request_)
    expected = (UsageError, SpecError) if verb == "submit" else (UsageError,)
    assert isinstance(info.value, expected), repr(info.value)
    assert info.value.exit_code == 2
    assert len(str(info.value)) < 2000  # a huge field is not echoed back whole
    _check_log(server, before)


@pytest.mark.parametrize("payload", RAW_PAYLOADS, ids=range(len(RAW_PAYLOADS)))
def test_non_json_request_is_a_usage_error(server: Osmo, raw: Connection,
                                           payload: bytes) -> None:
    before = len(_log(server))
    answer = raw.api.answer(raw.api.ask("api/get", payload, timeout=30))  # sealed: the body
    assert answer is not None and answer[0], answer  # is the junk, and the reply is sealed
    error = json.loads(answer[1])["error"]
    assert error["type"] == "UsageError" and error["exit_code"] == 2, error
    _check_log(server, before)


def test_the_server_still_works(server: Osmo, raw: Connection) -> None:
    assert raw.api.call("get", {"workflow_id": "ok-1"})["workflow"]["status"] == "COMPLETED"


@pytest.mark.parametrize("args,expected", [
    (["logs", "ok-1", "-t", "nosuchtask"], "no task 'nosuchtask' in ok-1"),
    (["logs", "ok-1", "-t", "a1"], "(did you mean 'a'?)"),
    (["logs", "ok-1", "-t", "a", "-r", "3"], "has no retry 3"),
    (["logs", "ok-1", "--tail", "-2"], "--tail -2"),
    (["logs", "ok-1", "--since", "yesterday"], "--since yesterday: give a duration"),
    (["logs", "ok-1", "--since", "0s"], "--since 0s"),
    (["list", "-s", "NOPE"], "COMPLETED"),
    (["list", "-c", "99999999999999999999"], "count"),
    (["list", "-c", "0"], "count"),
    (["query", "x" * 100_000], "workflow id"),
    (["cancel", "bad\x1b[2Jid"], "workflow id"),
])
def test_cli_exit_codes(server: Osmo, args: list[str], expected: str) -> None:
    r = server(*args)
    assert r.code == 2, r
    assert expected in r.err and "Traceback" not in r.err, r.err[-2000:]
    assert "\x1b" not in r.err


def test_cli_logs_of_a_real_task_still_work(server: Osmo) -> None:
    r = server("logs", "ok-1", "-t", "a")
    assert r.code == 0 and "hi" in r.out, r
    assert "hi" in server("logs", "ok-1", "--since", "2000-01-01T00:00", check=True).out
    assert "hi" not in server("logs", "ok-1", "--since", "2999-01-01", check=True).out


