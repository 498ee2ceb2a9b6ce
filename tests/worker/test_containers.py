"""The pool's container side, in pure parts: the runtime choice, the owner label, GPU slots,
registry credentials, the data layout and the worker's hello (no engine runs here; the
engine-backed behaviour is tests/containers)."""

from __future__ import annotations

from pathlib import Path

import pytest

from osmo.layout import AttemptDirs
from osmo.runtime.choose import container_engine
from osmo.runtime.container import EngineNotFound, owner_id
from osmo.runtime.container.images import registry_auth
from osmo.runtime.container.layout import (
    DATA_LAYOUT,
    RUNNER_PATHS,
    WORKDIR,
    CoverError,
    mounts,
    runner_mounts,
)
from osmo.runtime.container.run import DATA_OUTPUT, Mount
from osmo.scheduler.types import AttemptExited, Capacity, Node, PrepareAttempt
from osmo.spec.model import FileSpec, InputSpec, TaskSpec
from osmo.transport.wire import Hello, event_from_dict, event_to_dict
from osmo.worker.machine import GpuSlots
from osmo.worker.workdir import PrepareError, prepare


def test_process_runtime_needs_no_engine_and_container_names_the_package(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("PATH", str(tmp_path))  # no podman, no docker
    assert container_engine("process") is None
    assert container_engine("auto") is None  # image tasks run as processes, with the notice
    with pytest.raises(EngineNotFound, match="apt-get install podman"):
        container_engine("container")
    with pytest.raises(EngineNotFound, match="unknown runtime"):
        container_engine("vm")


def test_the_owner_label_is_stable_per_home_and_differs_between_homes(tmp_path: Path) -> None:
    assert owner_id(tmp_path / "a") == owner_id(tmp_path / "a")
    assert owner_id(tmp_path / "a") != owner_id(tmp_path / "b")


def test_gpu_slots_never_share_an_index_and_come_back() -> None:
    slots = GpuSlots(3)
    assert slots.take("a", 2) == (0, 1)
    assert slots.take("b", 2) == (2,)  # only what is free (the scheduler counted)
    slots.give_back("a")
    assert slots.take("c", 1) == (0,)
    slots.give_back("nobody")
    assert slots.take("d", 0) == ()


def test_a_registry_credential_is_found_by_the_image_host() -> None:
    creds = {"registry://nvcr.io": {"username": "$oauthtoken", "password": "pw"},
             "registry://docker.io": {"username": "me", "password": "hub"}}
    auth = registry_auth("nvcr.io/nvidia/pytorch:24.01", creds.get)
    assert auth is not None and (auth.registry, auth.username) == ("nvcr.io", "$oauthtoken")
    short = registry_auth("alpine:3.18", creds.get)
    assert short is not None and short.password == "hub"
    assert "hub" not in repr(short)
    assert registry_auth("quay.io/x:1", creds.get) is None
    assert registry_auth("nvcr.io/x:1", {"registry://nvcr.io": {"username": "u"}}.get) is None


def test_tokens_name_the_container_paths(tmp_path: Path) -> None:
    inputs = (InputSpec(task="make"), InputSpec(dataset="ds:v1"))
    cmd = PrepareAttempt("wf:t:0", "wf", "t", 0, "local", {"make": "/runs/make/output"}, {})

    def env_of(value: str) -> str:
        task = TaskSpec("t", image="alpine:3.18", command=("true",), inputs=inputs,
                        environment={"V": value})
        launch = prepare(AttemptDirs(tmp_path / value.strip("{}").replace(":", "-")), cmd,
                         task, {}, paths=DATA_LAYOUT)
        return launch.env["V"]

    assert env_of("{{output}}") == DATA_OUTPUT
    assert env_of("{{input:0}}") == "/osmo/data/input/0"
    assert env_of("{{input:make}}") == "/osmo/data/input/0"
    for unknown in ("{{input:1}}", "{{input:other}}"):  # not available: the preparation fails
        with pytest.raises(PrepareError, match="cannot resolve"):
            env_of(unknown)


def test_a_container_preparation_binds_outputs_inputs_and_files(tmp_path: Path) -> None:
    task = TaskSpec("use", image="alpine:3.18", command=("sh", "/opt/run.sh"),
                    environment={"OUT": "{{output}}"}, inputs=(InputSpec(task="make"),),
                    files=(FileSpec(path="/opt/run.sh", contents="cat {{input:make}}/x\n"),
                           FileSpec(path="conf/a.txt", contents="a")))
    upstream = tmp_path / "make-output"
    upstream.mkdir()
    cmd = PrepareAttempt("wf:use:0", "wf", "use", 0, "local", {"make": str(upstream)}, {})
    dirs = AttemptDirs(tmp_path / "attempt")
    launch = prepare(dirs, cmd, task, {"PATH": "/host/bin", "HOME": "/root"},
                     paths=DATA_LAYOUT)
    binds, workdir = mounts(dirs, launch.files, launch.inputs)
    assert "PATH" not in launch.env and launch.env["OUT"] == DATA_OUTPUT  # not the host's
    assert launch.env["OSMO_OUTPUT"] == DATA_OUTPUT
    assert (dirs.files / "opt/run.sh").read_text() == "cat /osmo/data/input/0/x\n"
    assert set(binds) == {
        Mount(dirs.output_partial, DATA_OUTPUT, read_only=False),
        Mount(upstream, "/osmo/data/input/0"),
        Mount(dirs.files / "opt/run.sh", "/opt/run.sh"),
        Mount(dirs.work, WORKDIR, read_only=False)}
    assert workdir == WORKDIR and launch.argv == ("sh", "/opt/run.sh")
    assert mounts(dirs, {}, [])[1] is None


def test_the_hello_and_the_exit_report_carry_runtime_and_image_id() -> None:
    node = Node(id="w1", pool="p", capacity=Capacity(cpu=1))
    hello = Hello.from_dict(Hello(node, runtime="container (podman 4.3.1)").to_dict())
    assert hello.runtime == "container (podman 4.3.1)"
    image_id = "sha256:" + "a" * 64
    sent = event_to_dict(AttemptExited("wf:t:0", 0, image_id=image_id))
    assert event_from_dict(sent) == AttemptExited("wf:t:0", 0, image_id=image_id)
    sent["image_id"] = "alpine; rm -rf /"  # a worker's report is checked
    assert event_from_dict(sent) == AttemptExited("wf:t:0", 0)


def test_a_container_secret_is_never_in_argv_or_env_only_in_the_secret_file(tmp_path: Path) -> None:
    task = TaskSpec("t", image="alpine:3.18", command=("sh", "-c"),
                    args=("echo $(API_TOKEN) $(PLAIN) $$API_TOKEN",),
                    environment={"PLAIN": "p"}, credentials={"api": {"API_TOKEN": "token"}})
    cmd = PrepareAttempt("wf:t:0", "wf", "t", 0, "local", {}, {})
    launch = prepare(AttemptDirs(tmp_path / "a"), cmd, task, {}, {"api": {"token": "s3cr3t"}},
                     paths=DATA_LAYOUT)
    assert launch.argv == ("sh", "-c", "echo $(API_TOKEN) p $API_TOKEN")
    assert "API_TOKEN" not in launch.env and "s3cr3t" in launch.secrets
    assert launch.secret_env == {"API_TOKEN": "s3cr3t"}


def test_a_typed_task_in_its_image_sees_its_type_folder_with_osmo_s_files_covered(
        tmp_path: Path) -> None:
    """A type's folder is the client's word: what of osmo it holds (a home, a token file) is
    covered, and a folder inside osmo's home is refused."""
    project = tmp_path / "project"
    home, token = project / ".osmo", project / "worker.token"
    home.mkdir(parents=True)
    token.write_text("secret")
    dirs = AttemptDirs(tmp_path / "attempt")
    empty = tmp_path / "empty"
    packages = {"osmo": tmp_path / "code" / "osmo"}
    binds = runner_mounts(dirs, packages, [str(project)], hidden=[home, token], empty=empty)
    assert set(binds) == {
        Mount(dirs.context, RUNNER_PATHS.context),
        Mount(dirs.work, RUNNER_PATHS.workdir, read_only=False),
        Mount(tmp_path / "code" / "osmo", "/osmo/lib/osmo"),
        Mount(project, "/osmo/types/0"),
        Mount(empty, "/osmo/types/0/.osmo"),
        Mount(Path("/dev/null"), "/osmo/types/0/worker.token"),
    }
    for inside in (home, home / "runs", project / "link"):
        if inside.name == "link":
            inside.symlink_to(home)  # a link into the home is the home
        with pytest.raises(CoverError, match="inside osmo's own files"):
            runner_mounts(dirs, packages, [str(inside)], hidden=[home], empty=empty)
