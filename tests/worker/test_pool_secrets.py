"""LocalPool and task credentials: secrets given or looked up, masked logs, removed files."""

from __future__ import annotations

import hashlib
from collections.abc import Iterator, Mapping
from pathlib import Path

import pytest

from osmo.layout import Home
from osmo.scheduler.types import (
    LOCAL_NODE,
    AttemptExited,
    AttemptStartFailed,
    KillAttempt,
    PrepareAttempt,
)
from osmo.spec.model import TaskSpec
from osmo.worker.pool import LocalPool
from tests.worker.test_pool import Events, attempt_dir, log_of, sh

SECRET = "s3cr3t-V4lue"
PAYLOAD = {"token": SECRET, "user": "robot-user"}
SCRIPT = (
    'echo "token=$TOKEN"; cat /etc/creds/token >&2; '
    'stat -c %a /etc/creds/token > {{output}}/mode; ls /etc/creds > {{output}}/keys; '
    'printf %s "$TOKEN" | sha256sum | cut -d" " -f1 > {{output}}/digest'
)


@pytest.fixture
def events() -> Events:
    return Events()


def cmd_of(task: TaskSpec) -> PrepareAttempt:
    return PrepareAttempt(f"wf-1:{task.name}:0", "wf-1", task.name, 0, "local", {}, {}, run=True)


def run(pool: LocalPool, events: Events, task: TaskSpec,
        secrets: Mapping[str, Mapping[str, str]] | None = None) -> AttemptExited | AttemptStartFailed:
    cmd = cmd_of(task)
    pool.prepare(cmd, task, secrets)
    return events.final(cmd.attempt_id)


def uses_secret(name: str = "api") -> TaskSpec:
    return sh(name, SCRIPT, credentials={"api": {"TOKEN": "token"}, "files": "/etc/creds"})


@pytest.fixture
def pool(tmp_path: Path, events: Events) -> Iterator[LocalPool]:
    store = {"api": PAYLOAD, "files": PAYLOAD}
    pool = LocalPool(home=Home(tmp_path / "home"), emit=events, task_secrets=store.get)
    yield pool
    pool.close()


def check_ran_with_secret(pool: LocalPool, final: AttemptExited | AttemptStartFailed) -> None:
    assert isinstance(final, AttemptExited) and final.exit_code == 0, final
    assert final.output is not None
    out = Path(final.output)
    assert (out / "digest").read_text().strip() == hashlib.sha256(SECRET.encode()).hexdigest()
    assert (out / "mode").read_text().strip() == "600"
    assert (out / "keys").read_text().split() == ["token", "user"]
    assert sorted(log_of(pool, final.attempt_id)) == [  # the file has no final newline
        ("osmo", "exit code 0"), ("stderr", "****"), ("stdout", "token=****")]
    folder = attempt_dir(pool, final.attempt_id)
    assert folder is not None
    assert not any((folder / "files" / "etc" / "creds").iterdir())  # deleted at the end
    for path in folder.rglob("*"):
        assert not path.is_file() or SECRET.encode() not in path.read_bytes(), path


def test_secrets_given_to_prepare(tmp_path: Path, events: Events) -> None:
    """The remote worker's path: the payloads come with the assignment, no lookup."""
    pool = LocalPool(home=Home(tmp_path / "home"), emit=events)
    try:
        final = run(pool, events, uses_secret(), {"api": PAYLOAD, "files": PAYLOAD})
        check_ran_with_secret(pool, final)
    finally:
        pool.close()


def test_secrets_looked_up_when_not_given(pool: LocalPool, events: Events) -> None:
    check_ran_with_secret(pool, run(pool, events, uses_secret()))


def test_task_without_credentials_gets_no_secret(pool: LocalPool, events: Events) -> None:
    final = run(pool, events, sh("plain", 'echo "[$TOKEN]"; ls /etc/creds 2>&1 | head -c 0'))
    assert isinstance(final, AttemptExited) and final.exit_code == 0
    assert log_of(pool, final.attempt_id)[0] == ("stdout", "[]")


def test_deleted_credential_fails_the_start(tmp_path: Path, events: Events) -> None:
    pool = LocalPool(home=Home(tmp_path / "home"), emit=events, task_secrets={"files": PAYLOAD}.get)
    try:
        final = run(pool, events, uses_secret())
    finally:
        pool.close()
    assert isinstance(final, AttemptStartFailed)
    assert final.message == (
        "task 'api': credential 'api' does not exist (deleted after the workflow was "
        "submitted?); store it again with `osmo credential set api --payload KEY=VALUE ...`")


def test_killed_before_start_removes_mounted_files(pool: LocalPool, events: Events) -> None:
    task = uses_secret()
    cmd = PrepareAttempt("wf-1:api:0", "wf-1", "api", 0, "local", {}, {})
    pool.prepare(cmd, task)
    events.wait_for(lambda e: getattr(e, "attempt_id", None) == cmd.attempt_id)
    pool.kill(KillAttempt(cmd.attempt_id, LOCAL_NODE, "cancelled"))
    final = events.final(cmd.attempt_id)
    assert isinstance(final, AttemptExited) and final.exit_code == 137
    folder = attempt_dir(pool, cmd.attempt_id)
    assert folder is not None
    assert not any((folder / "files" / "etc" / "creds").iterdir())
