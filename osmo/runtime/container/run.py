"""What a container run is, and the engine argv that expresses it (pure: runs nothing).

:class:`ContainerRun` describes one container; :func:`run_argv` turns it into the ``run``
argv of podman or docker, :func:`login_argv` and :func:`pull_argv` a registry login and a
pull. ``osmo.runtime.container.engine`` is the module that runs these argvs; this one only builds
them, so every engine difference is golden-tested without an engine.

Decisions, each checked with podman 4.3 and the docker 28 CLI (``tests/containers``):

- The command replaces the image's entrypoint (OSMO's ``command`` is Kubernetes'
  ``command``). podman gets it as a JSON list: it parses a plain string that looks like one.
- Options are single ``--opt=value`` words and the image and names are validated, so no
  user value is read as an option. Mounts use ``--mount`` with CSV quoting (``-v`` splits
  on ``:``; both engines read ``--mount`` as CSV).
- Secret variables: ``inspect`` shows every ``--env``, ``--env-file`` and podman
  ``--secret type=env`` value. They go into a 0600 file bound read-only at
  ``SECRET_ENV_PATH``, which the image's ``/bin/sh`` sources before ``exec``-ing the
  command. The file's path is in ``inspect``; its contents are not.
- Outputs stay the caller's: ``--user UID:GID``; rootless podman also gets
  ``--userns=keep-id``, so that uid is the same inside and out (rootful podman and docker
  need nothing more; rootless docker cannot keep ids and is not supported for outputs).
- Privileges: what OSMO's task pods keep. Their spec sets ``privileged: false`` and no
  ``capabilities``, so a pod keeps Kubernetes' default container set
  (:data:`POD_CAPABILITIES`); every other capability is dropped (``--cap-drop=all``, then
  the set named, so the engine's own default does not matter: podman 4.3's adds
  ``NET_RAW``), and ``--security-opt=no-new-privileges`` stops a setuid file or a file
  capability from giving any back.
- ``NVIDIA_VISIBLE_DEVICES`` is always set to exactly the assigned GPUs (empty: none), after
  the task's own variables, so neither the task nor a CUDA image's ``all`` widens it. GPUs
  themselves: docker ``--gpus="device=0,1"``, podman CDI ``--device=nvidia.com/gpu=0``.
- A pull with credentials gets a private folder (``config_dir``) holding one auth file
  (:func:`registry_config`: podman's ``--authfile``, docker's ``DOCKER_CONFIG``), written
  0600 by ``ContainerEngine`` and deleted after the pull; no ``login`` (it would be a
  second round trip, and a login of the engine's own config would outlive the pull). The
  password is in neither argv nor environment.
"""

from __future__ import annotations

import base64
import csv
import hashlib
import io
import json
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from osmo.errors import OsmoError
from osmo.names import image_problem

__all__ = ["DATA_INPUT", "DATA_OUTPUT", "POD_CAPABILITIES", "SECRET_ENV_PATH", "ContainerError",
           "mount_option",
           "ContainerRun", "EngineInfo", "Mount", "RegistryAuth", "data_input", "pull_argv",
           "pull_reference", "registry_config", "run_argv", "safe_name", "secret_env_text"]

DATA_OUTPUT = "/osmo/data/output"
"""Where a task's output folder is bound inside its container."""
DATA_INPUT = "/osmo/data/input/{}"
"""Where a task's inputs are bound (read-only) inside its container, ``{}`` the index."""
SECRET_ENV_PATH = "/osmo/run/secret.env"
"""Where a run's secret-variables file is bound (read-only) inside its container."""
POD_CAPABILITIES = ("CHOWN", "DAC_OVERRIDE", "FOWNER", "FSETID", "KILL", "SETGID", "SETUID",
                    "SETPCAP", "NET_BIND_SERVICE", "SYS_CHROOT", "MKNOD", "AUDIT_WRITE",
                    "SETFCAP")
"""The capabilities a container task keeps: those of a Kubernetes pod's container by default."""

_WRAPPER = f'. {SECRET_ENV_PATH} && exec "$@"'
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,127}")
_SHELL_VAR = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def data_input(index: int) -> str:
    """Where a task's ``index``-th input is bound (read-only) inside its container."""
    return DATA_INPUT.format(index)


class ContainerError(OsmoError):
    """An engine command failed or a run cannot be expressed (the message says which)."""

    exit_code = 3


@dataclass(frozen=True)
class EngineInfo:
    """A detected engine: ``name`` (podman or docker), CLI ``path``, ``version``, rootless."""

    name: str
    path: str
    version: str
    rootless: bool = False


@dataclass(frozen=True)
class Mount:
    """A bind mount: host ``source`` at container ``target``, read-only unless told."""

    source: Path
    target: str
    read_only: bool = True


@dataclass(frozen=True)
class ContainerRun:
    """One container run; the engine's ``run`` options are named after these fields.

    Attributes:
        image: the image (best its id, so a tag moved meanwhile changes nothing).
        name: the container's name (``safe_name``), also how it is killed.
        argv: the command; it replaces the image's entrypoint (empty: the image's own).
        env: variables (shown by ``inspect``: never secrets).
        secret_env: secret variables, written to ``secret_env_file`` (a host path) by
            ``ContainerRuntime`` and sourced inside; neither is in ``repr``.
        mounts: bind mounts; ``user``: ``UID:GID``; ``labels``: for finding it again.
        network, aliases, hostname: the group network and this task's names on it.
        cpus, memory (bytes), shm_size (bytes): limits; ``gpus``: host GPU indices.
        init: run a tiny init as PID 1 (reaps zombies, forwards signals).
    """

    image: str
    name: str
    argv: tuple[str, ...] = ()
    env: Mapping[str, str] = field(default_factory=dict, repr=False)
    secret_env: Mapping[str, str] = field(default_factory=dict, repr=False)
    secret_env_file: Path | None = None
    mounts: tuple[Mount, ...] = ()
    workdir: str | None = None
    user: str | None = None
    labels: Mapping[str, str] = field(default_factory=dict)
    network: str | None = None
    aliases: tuple[str, ...] = ()
    hostname: str | None = None
    cpus: float | None = None
    memory: int | None = None
    shm_size: int | None = None
    gpus: tuple[int, ...] = ()
    init: bool = True


@dataclass(frozen=True)
class RegistryAuth:
    """Credentials for pulling from ``registry`` (the password is never shown)."""

    registry: str
    username: str
    password: str = field(repr=False)


def safe_name(*parts: str, owner: str = "") -> str:
    """A container or network name for ``parts``: engine-safe, readable, unique per parts.

    ``owner`` (an ``osmo.owner`` label) is in the digest, not the readable part: two homes
    on one host run the same workflow ids, and their names must not meet.
    """
    readable = re.sub(r"[^A-Za-z0-9_.-]+", "-", "-".join(parts)).strip("-.")[:40]
    named = (owner, *parts) if owner else parts
    digest = hashlib.sha256("\0".join(named).encode()).hexdigest()[:12]
    return f"osmo-{readable}-{digest}" if readable else f"osmo-{digest}"


def pull_reference(image: str) -> str:
    """``image`` with a registry: short names are Docker Hub's.

    As docker and Kubernetes read them (Debian's podman has no search registries, so
    ``ubuntu:24.04`` would not pull).
    """
    first, sep, rest = image.partition("/")
    if sep and ("." in first or ":" in first or first == "localhost"):
        return image
    return f"docker.io/{image}" if sep else f"docker.io/library/{image}"


# ---------------------------------------------------------------- argv


def run_argv(engine: EngineInfo, run: ContainerRun) -> list[str]:
    """The engine's ``run`` argv for ``run``.

    The container is removed when it ends (``--rm``), never pulls (``--pull=never``: resolve
    the image first) and is attached: its output is the CLI's, its exit code the CLI's.

    Raises:
        ContainerError: a value the engine cannot take safely (the message names it).
    """
    _check(run)
    argv = [engine.path, "run", "--rm", f"--name={run.name}", "--pull=never"]
    argv += ["--init"] if run.init else []
    argv += ["--cap-drop=all", *(f"--cap-add={cap}" for cap in POD_CAPABILITIES),
             "--security-opt=no-new-privileges"]
    if run.user:
        argv.append(f"--user={run.user}")
        if engine.name == "podman" and engine.rootless:
            argv.append("--userns=keep-id")
    argv += [f"--label={key}={value}" for key, value in sorted(run.labels.items())]
    argv += [f"--network={run.network}"] if run.network else []
    argv += [f"--network-alias={alias}" for alias in run.aliases]
    argv += [f"--hostname={run.hostname}"] if run.hostname else []
    argv += [f"--cpus={run.cpus:g}"] if run.cpus else []
    argv += [f"--memory={run.memory}"] if run.memory else []
    argv += [f"--shm-size={run.shm_size}"] if run.shm_size else []
    argv += _gpu_args(engine, run.gpus)
    mounts = list(run.mounts)
    if run.secret_env and run.secret_env_file is not None:
        mounts.append(Mount(run.secret_env_file, SECRET_ENV_PATH))
    argv += [f"--mount={mount_option(m)}" for m in mounts]
    argv += [f"--workdir={run.workdir}"] if run.workdir else []
    argv += [f"--env={k}={v}" for k, v in run.env.items() if k != "NVIDIA_VISIBLE_DEVICES"]
    argv.append("--env=NVIDIA_VISIBLE_DEVICES=" + ",".join(str(g) for g in run.gpus))
    command = list(run.argv)
    if run.secret_env:
        command = ["/bin/sh", "-c", _WRAPPER, "osmo", *command]
    if command:
        entry = json.dumps([command[0]]) if engine.name == "podman" else command[0]
        argv.append(f"--entrypoint={entry}")
    return [*argv, run.image, *command[1:]]


def registry_config(engine: EngineInfo, auth: RegistryAuth, config_dir: Path
                    ) -> tuple[Path, str]:
    """``(path, text)`` of the auth file in ``config_dir`` that ``pull_argv`` points at.

    The engines' common ``{"auths": {HOST: {"auth": base64(user:password)}}}``; Docker Hub
    is also written under the key docker's CLI looks it up by.
    """
    _check_registry(auth.registry)
    token = base64.b64encode(f"{auth.username}:{auth.password}".encode()).decode()
    hosts = [auth.registry]
    if auth.registry == "docker.io":
        hosts.append("https://index.docker.io/v1/")
    name = "auth.json" if engine.name == "podman" else "config.json"
    return config_dir / name, json.dumps({"auths": {h: {"auth": token} for h in hosts}})


def pull_argv(engine: EngineInfo, image: str, config_dir: Path | None = None
              ) -> tuple[list[str], dict[str, str]]:
    """``(argv, extra environment)`` of pulling ``image`` (with ``registry_config``'s folder)."""
    _check_image(image)
    argv = [engine.path, "pull"]
    env: dict[str, str] = {}
    if config_dir is not None and engine.name == "podman":
        argv.append(f"--authfile={config_dir / 'auth.json'}")
    elif config_dir is not None:
        env["DOCKER_CONFIG"] = str(config_dir)
    return [*argv, pull_reference(image) if engine.name == "podman" else image], env


def secret_env_text(values: Mapping[str, str]) -> str:
    """The secret-variables file: ``export K='v'`` lines (values single-quoted)."""
    for key, value in values.items():
        if not _SHELL_VAR.fullmatch(key) or "\0" in value:
            raise ContainerError(f"secret variable {key!r} is not a shell variable name "
                                 f"or its value holds a NUL character")
    return "".join(f"export {k}='" + v.replace("'", "'\\''") + "'\n" for k, v in values.items())


# ---------------------------------------------------------------- checks


def _gpu_args(engine: EngineInfo, gpus: tuple[int, ...]) -> list[str]:
    if not gpus:
        return []
    if engine.name == "docker":  # docker reads the value as CSV: the quotes keep one field
        return ['--gpus="device=' + ",".join(str(g) for g in gpus) + '"']
    return [f"--device=nvidia.com/gpu={g}" for g in gpus]  # CDI (`nvidia-ctk cdi generate`)


def _check_image(image: str) -> None:
    """The spec refuses these already; this keeps a stored or hand-made run honest too."""
    problem = image_problem(image)
    if problem is not None:
        raise ContainerError(f"unusable image reference: {problem}")


def _check(run: ContainerRun) -> None:
    _check_image(run.image)
    names = [("container name", run.name), *(("alias", a) for a in run.aliases)]
    names += [("network", run.network)] if run.network else []
    names += [("hostname", run.hostname)] if run.hostname else []
    for what, value in names:
        if not _NAME.fullmatch(value):
            raise ContainerError(f"unusable {what} {value!r} (letters, digits, _ . -)")
    if run.argv and not run.argv[0]:
        raise ContainerError("the command's program name is empty")
    for key, value in run.labels.items():
        if not key or "=" in key or _has(key + value, "\0\n"):
            raise ContainerError(f"unusable label {key!r}")
    for key, value in run.env.items():
        if not key or "=" in key or _has(key + value, "\0"):
            raise ContainerError(f"unusable environment variable {key!r} (name or value)")
    secret_env_text(run.secret_env)
    if run.secret_env and (run.secret_env_file is None or not run.argv):
        raise ContainerError("secret variables need a secret_env_file and a command")
    for mount in run.mounts:
        _check_mount(mount)
    targets = [os.path.normpath(m.target) for m in run.mounts]
    if len(set(targets)) != len(targets) or (run.secret_env and SECRET_ENV_PATH in targets):
        raise ContainerError("two mounts share a container path")


def _has(text: str, chars: str) -> bool:
    return any(c in text for c in chars)


def _check_mount(mount: Mount) -> None:
    for path in (str(mount.source), mount.target):
        if not path.startswith("/") or _has(path, "\0\n\r"):
            raise ContainerError(f"unusable mount path {path!r} (absolute, one line)")
    if os.path.normpath(mount.target) in ("/", "/proc", "/sys", "/dev"):
        raise ContainerError(f"cannot mount over {mount.target!r}")


def _check_registry(registry: str) -> None:
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9.:/_-]{0,254}", registry):
        raise ContainerError(f"unusable registry {registry!r}")


def mount_option(mount: Mount) -> str:
    """A bind as ``--mount``'s CSV value (both engines read it so; paths may hold commas)."""
    out = io.StringIO()
    fields = ["type=bind", f"source={mount.source}", f"target={mount.target}"]
    csv.writer(out, lineterminator="").writerow(fields + ["readonly"] * mount.read_only)
    return out.getvalue()
