"""Attempt folders: layout, private file mapping, tokens, environment, promotion."""

from __future__ import annotations

import base64
import json
import os
import sys
from pathlib import Path

import pytest

from osmo.errors import OsmoError
from osmo.layout import Home
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import FileSpec, InputSpec, ResolvedType, TaskSpec
from osmo.worker.launch import osmo_paths
from osmo.worker.workdir import PrepareError, prepare, promote, remove_secret_files


def command(
    task: str = "t",
    retry: int = 0,
    inputs: dict[str, str] | None = None,
    hosts: dict[str, str] | None = None,
) -> PrepareAttempt:
    return PrepareAttempt(
        f"wf-1:{task}:{retry}", "wf-1", task, retry, "local", inputs or {}, hosts or {}
    )


def prep(
    home: Path, task: TaskSpec, cmd: PrepareAttempt | None = None, env: dict[str, str] | None = None
):
    cmd = cmd or command(task.name)
    dirs = Home(home).attempt(cmd.workflow_id, cmd.task, cmd.retry)
    return dirs, prepare(dirs, cmd, task, env or {"BASE": "1"})


def test_layout(tmp_path: Path) -> None:
    dirs, launch = prep(tmp_path, TaskSpec(name="t", command=("true",)), command("t", 2))
    assert dirs.root == tmp_path / "runs" / "wf-1" / "t" / "2"
    for folder in (dirs.work, dirs.output_partial):
        assert folder.is_dir()
    assert not dirs.files.exists()  # made only for a task that declares files
    assert not dirs.output.exists()
    assert dirs.log == dirs.root / "log.txt"
    assert launch.cwd == dirs.work
    assert launch.argv == ("true",)


def test_environment(tmp_path: Path) -> None:
    task = TaskSpec(
        name="t",
        command=("true",),
        environment={"A": "x", "OUT": "{{output}}/f", "OSMO_TASK": "override", "BASE": "task"},
    )
    dirs, launch = prep(tmp_path, task, command("t", 1), {"BASE": "server", "KEEP": "k"})
    env = launch.env
    assert env["KEEP"] == "k"
    assert env["BASE"] == "task"
    assert env["A"] == "x"
    assert env["OUT"] == f"{dirs.output_partial}/f"
    assert env["OSMO_WORKFLOW_ID"] == "wf-1"
    assert env["OSMO_TASK"] == "t"  # osmo's variables cannot be overridden
    assert env["OSMO_RETRY"] == "1"
    assert env["OSMO_OUTPUT"] == str(dirs.output_partial)
    assert env["OSMO_FILES_ROOT"] == str(dirs.files)


def test_tokens(tmp_path: Path) -> None:
    task = TaskSpec(
        name="t",
        command=("echo", "{{ output }}", "{{input:0}}", "{{input:1}}", "{{input:b}}"),
        args=("{{workflow_id}}", "{{host:peer}}", "{{uuid}}", "{{uuid}}"),
        inputs=(InputSpec(task="a"), InputSpec(task="b")),
    )
    cmd = command(inputs={"a": "/ref/a", "b": "/ref/b"}, hosts={"peer": "10.0.0.7"})
    dirs, launch = prep(tmp_path, task, cmd)
    argv = launch.argv
    assert argv[:5] == ("echo", str(dirs.output_partial), "/ref/a", "/ref/b", "/ref/b")
    assert argv[5:7] == ("wf-1", "10.0.0.7")
    assert len(argv[7]) == 32 and int(argv[7], 16) >= 0
    assert argv[7] == argv[8]  # one uuid per attempt


def test_input_of_another_workflow(tmp_path: Path) -> None:
    task = TaskSpec(
        name="t", command=("echo", "{{input:0}}"), inputs=(InputSpec(task="a", workflow="old-3"),)
    )
    _, launch = prep(tmp_path, task, command(inputs={"old-3:a": "/ref/old"}))
    assert launch.argv[1] == "/ref/old"


@pytest.mark.parametrize("token", ["{{input:5}}", "{{input:zz}}", "{{host:nobody}}"])
def test_unresolvable_token_fails(tmp_path: Path, token: str) -> None:
    task = TaskSpec(name="t", command=("echo", token), inputs=(InputSpec(task="a"),))
    with pytest.raises(PrepareError, match="cannot resolve"):
        prep(tmp_path, task, command(inputs={"a": "/ref/a"}))


def test_files_are_private_and_paths_rewritten(tmp_path: Path) -> None:
    task = TaskSpec(
        name="t",
        command=("/tmp/run.sh", "--config=/tmp/conf.yaml"),
        args=("/tmp/run.sh.bak", "/x/tmp/run.sh", "/tmp/run.sh/", "/tmp/run"),
        environment={"CONF": "/tmp/conf.yaml"},
        files=(
            FileSpec("/tmp/run.sh", "#!/bin/sh\ncat /tmp/conf.yaml\n"),
            FileSpec("/tmp/conf.yaml", "out: {{output}}\n"),
            FileSpec("rel/data.txt", "x"),
        ),
    )
    dirs, launch = prep(tmp_path, task)
    run = dirs.files / "tmp" / "run.sh"
    conf = dirs.files / "tmp" / "conf.yaml"
    assert launch.argv == (
        str(run),
        f"--config={conf}",
        "/tmp/run.sh.bak",
        "/x/tmp/run.sh",
        f"{run}/",
        "/tmp/run",
    )
    assert launch.env["CONF"] == str(conf)
    assert run.read_text() == f"#!/bin/sh\ncat {conf}\n"
    assert conf.read_text() == f"out: {dirs.output_partial}\n"
    assert (dirs.work / "rel" / "data.txt").read_text() == "x"
    assert run.stat().st_mode & 0o777 == 0o755
    assert conf.stat().st_mode & 0o777 == 0o644


def test_longest_declared_path_wins(tmp_path: Path) -> None:
    task = TaskSpec(
        name="t",
        command=("cat", "/a/b", "/a/b/c"),
        files=(FileSpec("/a/b/c", "1"), FileSpec("/a/b", "2")),
    )
    with pytest.raises(PrepareError):  # /a/b cannot be both a file and a folder
        prep(tmp_path, task)
    task = TaskSpec(
        name="t",
        command=("cat", "/a/b", "/a/bc"),
        files=(FileSpec("/a/bc", "1"), FileSpec("/a/b", "2")),
    )
    dirs, launch = prep(tmp_path, task)
    assert launch.argv[1:] == (str(dirs.files / "a/b"), str(dirs.files / "a/bc"))


def test_base64_files_are_decoded_verbatim(tmp_path: Path) -> None:
    script = b"#!/bin/sh\necho /tmp/x {{output}}\n"
    blob = bytes(range(256))
    task = TaskSpec(
        name="t",
        command=("true",),
        files=(
            FileSpec("/tmp/x", base64.b64encode(script).decode(), base64=True),
            FileSpec("blob.bin", base64.b64encode(blob).decode(), base64=True),
        ),
    )
    dirs, _ = prep(tmp_path, task)
    written = dirs.files / "tmp" / "x"
    assert written.read_bytes() == script
    assert written.stat().st_mode & 0o777 == 0o755
    assert (dirs.work / "blob.bin").read_bytes() == blob


def test_invalid_base64_fails(tmp_path: Path) -> None:
    task = TaskSpec(name="t", command=("true",), files=(FileSpec("/x", "a", base64=True),))
    with pytest.raises(PrepareError, match="base64"):
        prep(tmp_path, task)


@pytest.mark.parametrize("path", ["../escape", "a/../../escape", "/", ""])
def test_unusable_file_paths_fail(tmp_path: Path, path: str) -> None:
    task = TaskSpec(name="t", command=("true",), files=(FileSpec(path, "x"),))
    with pytest.raises(PrepareError):
        prep(tmp_path, task)


def test_absolute_dotdot_stays_inside_files_root(tmp_path: Path) -> None:
    task = TaskSpec(name="t", command=("true",), files=(FileSpec("/../../etc/x", "x"),))
    dirs, _ = prep(tmp_path, task)
    assert (dirs.files / "etc" / "x").read_text() == "x"


def test_task_without_command_fails(tmp_path: Path) -> None:
    with pytest.raises(PrepareError, match="no command"):
        prep(tmp_path, TaskSpec(name="t"))


def test_typed_task_runs_the_runner_on_its_context_file(tmp_path: Path) -> None:
    task = TaskSpec(name="t", type="mod:fn", params={"n": 1}, inputs=(InputSpec(task="up"),),
                    resolved=ResolvedType("3", paths=("/src",)))
    cmd = command("t", inputs={"up": "/runs/up/output"})
    dirs, launch = prep(tmp_path, task, cmd, {"PYTHONPATH": "/old"})
    context = dirs.root / "task.json"
    assert launch.argv == (sys.executable, "-m", "osmo.tasktypes.runner", str(context))
    assert launch.env["PYTHONPATH"] == os.pathsep.join(["/src", "/old", *osmo_paths()])
    data = json.loads(context.read_text())
    assert (data["type"], data["type_version"], data["params"], data["paths"]) == (
        "mod:fn", "3", {"n": 1}, ["/src"])
    assert data["inputs"] == [{"name": "up", "path": "/runs/up/output"}]
    assert data["output"] == str(dirs.output_partial) and data["attempt_id"] == cmd.attempt_id


def test_preparing_again_starts_clean(tmp_path: Path) -> None:
    task = TaskSpec(name="t", command=("true",))
    dirs, _ = prep(tmp_path, task)
    (dirs.output_partial / "stale").write_text("old")
    dirs, _ = prep(tmp_path, task)
    assert list(dirs.output_partial.iterdir()) == []


def test_promote(tmp_path: Path) -> None:
    dirs, _ = prep(tmp_path, TaskSpec(name="t", command=("true",)))
    (dirs.output_partial / "result.txt").write_text("42")
    ref = promote(dirs)
    assert ref == str(dirs.output) and os.path.isabs(ref)
    assert (dirs.output / "result.txt").read_text() == "42"
    assert not dirs.output_partial.exists()
    with pytest.raises(OSError):
        promote(dirs)  # nothing left to promote


# ---------------------------------------------------------------- credentials


def test_credentials_as_environment_and_files(tmp_path: Path) -> None:
    task = TaskSpec(
        name="t",
        command=("sh", "-c", "cat /etc/creds/password"),
        args=("/etc/creds", "/etc/creds/user"),
        environment={"A": "/etc/creds/user"},
        credentials={"db": "/etc/creds", "api": {"TOKEN": "token", "OSMO_TASK": "token"}},
    )
    cmd = command("t")
    dirs = Home(tmp_path).attempt(cmd.workflow_id, cmd.task, cmd.retry)
    secrets = {"db": {"user": "alice", "password": "pa55word"}, "api": {"token": "tok-123"}}
    launch = prepare(dirs, cmd, task, {"TOKEN": "server"}, secrets)
    mount = dirs.files / "etc" / "creds"
    assert launch.argv == ("sh", "-c", f"cat {mount}/password", str(mount), f"{mount}/user")
    assert launch.env["A"] == f"{mount}/user"
    assert launch.env["TOKEN"] == "tok-123"  # a credential overrides the server's environment
    assert launch.env["OSMO_TASK"] == "t"  # and never osmo's own variables
    for key, value in secrets["db"].items():
        assert (mount / key).read_text() == value
        assert (mount / key).stat().st_mode & 0o777 == 0o600
    assert sorted(launch.secret_files) == [mount / "password", mount / "user"]
    assert sorted(launch.secrets) == ["alice", "pa55word", "tok-123"]
    assert "tok-123" not in repr(launch) and "pa55word" not in repr(launch)
    remove_secret_files(launch)
    assert not any(mount.iterdir())
    remove_secret_files(launch)  # already gone: fine


def test_relative_credential_mount_is_under_work(tmp_path: Path) -> None:
    task = TaskSpec(name="t", command=("true",), credentials={"db": "creds"})
    cmd = command("t")
    dirs = Home(tmp_path).attempt(cmd.workflow_id, cmd.task, cmd.retry)
    launch = prepare(dirs, cmd, task, {}, {"db": {"k": "v"}})
    assert launch.secret_files == (dirs.work / "creds" / "k",)


def test_task_without_credentials_gets_no_secret(tmp_path: Path) -> None:
    dirs, launch = prep(tmp_path, TaskSpec(name="t", command=("true",)))
    assert launch.secrets == () and launch.secret_files == ()


@pytest.mark.parametrize(("credentials", "secrets", "message"), [
    ({"db": {"PW": "password"}}, {}, "task 't': credential 'db' was not given to this worker; "
     "store it again with `osmo credential set db --payload KEY=VALUE ...`"),
    ({"db": {"PW": "pw"}}, {"db": {"user": "u", "password": "p"}},
     "task 't': credential 'db' has no key 'pw' (for $PW); its keys: password, user"),
    ({"db": "/etc/db"}, {"db": {"a/b": "v"}},
     "task 't': credential 'db' is mounted at /etc/db but its key 'a/b' contains '/' or a NUL "
     "character; rename the key"),
    ({"db": "/"}, {"db": {"k": "v"}}, "credential mount path '/' names no mount"),
    ({"db": "../x"}, {"db": {"k": "v"}}, "credential mount path '../x' leaves the working folder"),
])
def test_unusable_credentials_fail(tmp_path: Path, credentials: dict[str, object],
                                   secrets: dict[str, dict[str, str]], message: str) -> None:
    task = TaskSpec(name="t", command=("true",), credentials=credentials)
    cmd = command("t")
    dirs = Home(tmp_path).attempt(cmd.workflow_id, cmd.task, cmd.retry)
    with pytest.raises(OsmoError) as info:
        prepare(dirs, cmd, task, {}, secrets)
    assert str(info.value) == message


def test_failed_mount_leaves_no_secret(tmp_path: Path) -> None:
    task = TaskSpec(name="t", command=("true",), credentials={"a": "/m", "b": "/m/k1"},
                    files=(FileSpec(path="/m/k1/k2", contents="x"),))
    cmd = command("t")
    dirs = Home(tmp_path).attempt(cmd.workflow_id, cmd.task, cmd.retry)
    with pytest.raises(PrepareError, match="cannot prepare"):  # /m/k1 is a folder: no file
        prepare(dirs, cmd, task, {}, {"a": {"k0": "secret0", "k1": "secret1"}, "b": {"k": "v"}})
    assert not (dirs.files / "m" / "k0").exists()


def test_a_sandbox_view_binds_inputs_once_and_within_bubblewraps_limits(tmp_path: Path) -> None:
    """A join of 9,998 inputs failed with 'bwrap: Exceeded maximum number of arguments 9000'."""
    from osmo.runtime.process.sandboxed import attempt_view

    home = tmp_path / "home"
    dirs = Home(home).attempt("wf-1", "join", 0)
    inside = {f"m{i}": str(dirs.inputs / f"m{i}") for i in range(9998)}  # checked links
    view = attempt_view(dirs, command(inputs=inside), (home,))
    assert len(view.readonly) == 2  # the attempt's folder and its url inputs, nothing more

    outside = {"a": "/data/set", "b": "/data/set/sub", "c": "/data/other"}
    view = attempt_view(dirs, command(inputs=outside), (home,))
    assert [str(p) for p in view.readonly[2:]] == ["/data/other", "/data/set"]

    many = {f"d{i}": f"/data/d{i}" for i in range(2001)}
    with pytest.raises(PrepareError, match="2,001 input folders .* more than a sandbox can bind"):
        attempt_view(dirs, command(inputs=many), (home,))
