"""Golden argv of ``run``, ``login`` and ``pull`` for podman and docker (pure; no engine).

GPU arguments cannot run here (no GPU): these goldens are their test. The values that matter
for safety (entrypoint as JSON for podman, CSV-quoted mounts, NVIDIA_VISIBLE_DEVICES last,
no secret in argv) are asserted where they are made.
"""

from __future__ import annotations

import base64
import json
from pathlib import Path

import pytest

from osmo.runtime.container.run import (
    SECRET_ENV_PATH,
    ContainerError,
    ContainerRun,
    EngineInfo,
    Mount,
    RegistryAuth,
    pull_argv,
    pull_reference,
    registry_config,
    run_argv,
    safe_name,
    secret_env_text,
)

PODMAN = EngineInfo("podman", "/usr/bin/podman", "4.3.1")
ROOTLESS = EngineInfo("podman", "/usr/bin/podman", "4.3.1", rootless=True)
DOCKER = EngineInfo("docker", "/usr/bin/docker", "28.2.2")

FULL = ContainerRun(
    image="sha256:" + "ab" * 32, name="osmo-wf-1-train-0-123456789abc",
    argv=("python", "train.py", "--lr", "0.1"), env={"A": "1", "NVIDIA_VISIBLE_DEVICES": "all"},
    mounts=(Mount(Path("/h/in"), "/osmo/data/input/0"),
            Mount(Path("/h/out"), "/osmo/data/output", read_only=False)),
    workdir="/work", user="1000:1000", labels={"osmo.task": "train", "osmo.attempt": "wf-1:train:0"},
    network="osmo-wf-1-g", aliases=("train",), hostname="train", cpus=1.5, memory=2 << 30,
    shm_size=1 << 30, gpus=(0, 1))

FULL_TAIL = ["--mount=type=bind,source=/h/in,target=/osmo/data/input/0,readonly",
             "--mount=type=bind,source=/h/out,target=/osmo/data/output",
             "--workdir=/work", "--env=A=1", "--env=NVIDIA_VISIBLE_DEVICES=0,1"]
PRIVILEGES = ["--cap-drop=all", "--cap-add=CHOWN", "--cap-add=DAC_OVERRIDE", "--cap-add=FOWNER",
              "--cap-add=FSETID", "--cap-add=KILL", "--cap-add=SETGID", "--cap-add=SETUID",
              "--cap-add=SETPCAP", "--cap-add=NET_BIND_SERVICE", "--cap-add=SYS_CHROOT",
              "--cap-add=MKNOD", "--cap-add=AUDIT_WRITE", "--cap-add=SETFCAP",
              "--security-opt=no-new-privileges"]
FULL_HEAD = ["run", "--rm", "--name=osmo-wf-1-train-0-123456789abc", "--pull=never", "--init",
             *PRIVILEGES, "--user=1000:1000"]
FULL_MIDDLE = ["--label=osmo.attempt=wf-1:train:0", "--label=osmo.task=train",
               "--network=osmo-wf-1-g", "--network-alias=train", "--hostname=train",
               "--cpus=1.5", "--memory=2147483648", "--shm-size=1073741824"]


def test_podman_golden() -> None:
    assert run_argv(PODMAN, FULL) == [
        "/usr/bin/podman", *FULL_HEAD, *FULL_MIDDLE,
        "--device=nvidia.com/gpu=0", "--device=nvidia.com/gpu=1", *FULL_TAIL,
        '--entrypoint=["python"]', FULL.image, "train.py", "--lr", "0.1"]


def test_docker_golden() -> None:
    assert run_argv(DOCKER, FULL) == [
        "/usr/bin/docker", *FULL_HEAD, *FULL_MIDDLE, '--gpus="device=0,1"', *FULL_TAIL,
        "--entrypoint=python", FULL.image, "train.py", "--lr", "0.1"]


def test_rootless_podman_keeps_the_callers_uid() -> None:
    argv = run_argv(ROOTLESS, ContainerRun("alpine:3.18", "c", ("true",), user="1000:1000"))
    assert argv[argv.index("--user=1000:1000") + 1] == "--userns=keep-id"
    assert "--userns=keep-id" not in run_argv(PODMAN, ContainerRun("alpine:3.18", "c", ("true",),
                                                                   user="0:0"))


@pytest.mark.parametrize("engine", [PODMAN, DOCKER], ids=["podman", "docker"])
def test_no_gpu_means_none_visible(engine: EngineInfo) -> None:
    run = ContainerRun("alpine:3.18", "c", ("true",), env={"NVIDIA_VISIBLE_DEVICES": "all"})
    argv = run_argv(engine, run)
    assert [a for a in argv if "NVIDIA" in a] == ["--env=NVIDIA_VISIBLE_DEVICES="]
    assert not [a for a in argv if a.startswith(("--gpus", "--device"))]


def test_single_gpu() -> None:
    run = ContainerRun("alpine:3.18", "c", ("true",), gpus=(3,))
    assert '--gpus="device=3"' in run_argv(DOCKER, run)
    podman = run_argv(PODMAN, run)
    assert "--device=nvidia.com/gpu=3" in podman and "--env=NVIDIA_VISIBLE_DEVICES=3" in podman


def test_minimal_run_uses_the_image_entrypoint() -> None:
    assert run_argv(PODMAN, ContainerRun("alpine:3.18", "c", init=False)) == [
        "/usr/bin/podman", "run", "--rm", "--name=c", "--pull=never", *PRIVILEGES,
        "--env=NVIDIA_VISIBLE_DEVICES=", "alpine:3.18"]


def test_a_program_that_looks_like_json_stays_one_word_for_podman() -> None:
    argv = run_argv(PODMAN, ContainerRun("alpine:3.18", "c", ('["sh","-c","id"]',)))
    assert '--entrypoint=["[\\"sh\\",\\"-c\\",\\"id\\"]"]' in argv


def test_secret_env_goes_through_a_bound_file_never_argv() -> None:
    run = ContainerRun("alpine:3.18", "c", ("sh", "-c", "echo $TOKEN"), env={"A": "1"},
                       secret_env={"TOKEN": "s3cret"}, secret_env_file=Path("/h/secret.env"))
    argv = run_argv(PODMAN, run)
    assert not [a for a in argv if "s3cret" in a]
    assert "s3cret" not in repr(run)
    assert f"--mount=type=bind,source=/h/secret.env,target={SECRET_ENV_PATH},readonly" in argv
    assert argv[argv.index("alpine:3.18") - 1] == '--entrypoint=["/bin/sh"]'
    assert argv[argv.index("alpine:3.18") + 1:] == [
        "-c", f'. {SECRET_ENV_PATH} && exec "$@"', "osmo", "sh", "-c", "echo $TOKEN"]


def test_secret_env_file_quotes_every_value() -> None:
    text = secret_env_text({"A": "it's $HOME `x`\nline2", "B": ""})
    assert text == "export A='it'\\''s $HOME `x`\nline2'\nexport B=''\n"


def test_mount_paths_with_commas_quotes_and_colons_are_csv_quoted() -> None:
    run = ContainerRun("alpine:3.18", "c", ("true",), mounts=(
        Mount(Path('/h/a,b"c'), "/x:y", read_only=False),))
    assert '--mount=type=bind,"source=/h/a,b""c",target=/x:y' in run_argv(DOCKER, run)


@pytest.mark.parametrize("run, message", [
    (ContainerRun("--privileged", "c", ("true",)), "image"),
    (ContainerRun("alpine 3", "c", ("true",)), "image"),
    (ContainerRun("alpine", "-c", ("true",)), "container name"),
    (ContainerRun("alpine", "c", ("true",), network="--net=host"), "network"),
    (ContainerRun("alpine", "c", ("true",), aliases=("a b",)), "alias"),
    (ContainerRun("alpine", "c", ("",)), "program name is empty"),
    (ContainerRun("alpine", "c", ("true",), env={"A=B": "1"}), "environment variable"),
    (ContainerRun("alpine", "c", ("true",), env={"A": "x\0y"}), "environment variable"),
    (ContainerRun("alpine", "c", ("true",), labels={"k": "a\nb"}), "label"),
    (ContainerRun("alpine", "c", ("true",), secret_env={"A-B": "1"},
                  secret_env_file=Path("/s")), "shell variable"),
    (ContainerRun("alpine", "c", ("true",), secret_env={"A": "1"}), "secret_env_file"),
    (ContainerRun("alpine", "c", (), secret_env={"A": "1"}, secret_env_file=Path("/s")),
     "command"),
    (ContainerRun("alpine", "c", ("true",), mounts=(Mount(Path("rel"), "/x"),)), "mount path"),
    (ContainerRun("alpine", "c", ("true",), mounts=(Mount(Path("/h"), "x"),)), "mount path"),
    (ContainerRun("alpine", "c", ("true",), mounts=(Mount(Path("/h"), "/a\nb"),)), "mount path"),
    (ContainerRun("alpine", "c", ("true",), mounts=(Mount(Path("/h"), "/proc/"),)), "mount over"),
    (ContainerRun("alpine", "c", ("true",), mounts=(Mount(Path("/h"), "/x"),
                                                    Mount(Path("/g"), "/x/"))), "share"),
    (ContainerRun("alpine", "c", ("true",), secret_env={"A": "1"}, secret_env_file=Path("/s"),
                  mounts=(Mount(Path("/h"), SECRET_ENV_PATH),)), "share"),
])
def test_hostile_values_are_refused(run: ContainerRun, message: str) -> None:
    with pytest.raises(ContainerError, match=message):
        run_argv(PODMAN, run)


def test_the_registry_password_goes_into_the_auth_file_only(tmp_path: Path) -> None:
    auth = RegistryAuth("registry.example.com:5000", "robot", "pa55-word")
    token = base64.b64encode(b"robot:pa55-word").decode()
    path, text = registry_config(PODMAN, auth, tmp_path)
    assert path == tmp_path / "auth.json"
    assert json.loads(text) == {"auths": {"registry.example.com:5000": {"auth": token}}}
    path, text = registry_config(DOCKER, RegistryAuth("docker.io", "robot", "pa55-word"),
                                 tmp_path)
    assert path == tmp_path / "config.json"
    assert set(json.loads(text)["auths"]) == {"docker.io", "https://index.docker.io/v1/"}
    for engine in (PODMAN, DOCKER):
        argv, env = pull_argv(engine, "registry.example.com:5000/x:1", tmp_path)
        assert "pa55-word" not in repr((argv, env)) and token not in repr((argv, env))
    assert "pa55-word" not in repr(auth)
    with pytest.raises(ContainerError, match="registry"):
        registry_config(PODMAN, RegistryAuth("--tls-verify=false", "u", "p"), tmp_path)


def test_pull_uses_the_auth_folder_and_qualifies_short_names(tmp_path: Path) -> None:
    assert pull_argv(PODMAN, "ubuntu:24.04") == (
        ["/usr/bin/podman", "pull", "docker.io/library/ubuntu:24.04"], {})
    assert pull_argv(PODMAN, "nvcr.io/nvidia/pytorch:24.01", tmp_path) == (
        ["/usr/bin/podman", "pull", f"--authfile={tmp_path}/auth.json",
         "nvcr.io/nvidia/pytorch:24.01"], {})
    assert pull_argv(DOCKER, "ubuntu:24.04", tmp_path) == (
        ["/usr/bin/docker", "pull", "ubuntu:24.04"], {"DOCKER_CONFIG": str(tmp_path)})
    with pytest.raises(ContainerError, match="image"):
        pull_argv(PODMAN, "-q")


@pytest.mark.parametrize("image, ref", [
    ("alpine:3.18", "docker.io/library/alpine:3.18"),
    ("nvidia/cuda:12.4", "docker.io/nvidia/cuda:12.4"),
    ("localhost/x:1", "localhost/x:1"),
    ("registry:5000/x", "registry:5000/x"),
    ("nvcr.io/nvidia/isaac-lab:2.0", "nvcr.io/nvidia/isaac-lab:2.0"),
])
def test_pull_reference(image: str, ref: str) -> None:
    assert pull_reference(image) == ref


def test_safe_name_is_engine_safe_and_unique() -> None:
    a, b = safe_name("wf-1", "task:0"), safe_name("wf-1", "task-0")
    assert a != b and a.startswith("osmo-wf-1-task-0-")
    assert safe_name("../../", "\n") .startswith("osmo-")
    for name in (a, b, safe_name("../../", "\n"), safe_name("x" * 300)):
        run_argv(PODMAN, ContainerRun("alpine", name, ("true",)))  # accepted as a name
