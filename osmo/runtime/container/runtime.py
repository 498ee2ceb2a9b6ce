"""The container runtime: an attempt runs in its task's image, through podman or docker.

A task with an ``image:`` runs so where the node runs containers (``osmo.runtime.choose``);
a typed one (``type:``) runs osmo's runner on the image's ``python3``. What it owns, one
concern per method of the runtime contract:

- what the task sees: OSMO's data layout (``osmo.runtime.container.layout``; a typed task's
  runner, context and osmo's code too), and its group peers' aliases for ``{{host:NAME}}``
  (``osmo.runtime.container.groups``).
- the launch (:meth:`ContainerRuntime.prepare`): the image resolved to its id (pulling a
  missing one, its progress lines to the task's log as the engine prints them, registry
  credentials for the pull only), the container named and labelled (``osmo.owner``,
  ``osmo.workflow``, ``osmo.task``, ``osmo.attempt``), run as the invoking uid:gid with
  ``--init``, its cpu/memory limits and the GPU indices the pool assigned it, its binds, its
  secret variables in a 0600 file, and its group's network. A task that requests cpus gets
  ``OMP_NUM_THREADS`` set to that count, as a process does, unless its spec or its image
  sets it (the image's variables are read once per image id).
- start, kill, reap, release: the engine's attached CLI (``osmo.runtime.container.runs``);
  a group's peer starts once its lead's container runs.
- exec: ``<engine> exec -i [-t]`` into the container (its working folder and environment are
  the container's).
- port-forward: to the task's port on the container's own address (its network namespace,
  as OSMO's pod).
- clean-up: the group network with its last member; the container itself goes with its run.

Orphans: :meth:`ContainerRuntime.clean_orphans` removes every container and network carrying
this owner's label; a node's runtime is made with it (``osmo.runtime.choose``), before
anything new runs.
"""

from __future__ import annotations

import hashlib
import os
import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

from osmo.layout import AttemptDirs
from osmo.runtime.api import (
    Attempt,
    ConnectError,
    Connector,
    ExecCommand,
    Launch,
    Paths,
    PrepareError,
    ProcessHandle,
    Runtime,
    dial,
)
from osmo.runtime.container.engine import ContainerEngine
from osmo.runtime.container.groups import Groups, alias
from osmo.runtime.container.images import ImageIds, registry_auth
from osmo.runtime.container.layout import (
    DATA_LAYOUT,
    RUNNER_PATHS,
    CoverError,
    mounts,
    runner_mounts,
)
from osmo.runtime.container.run import ContainerError, ContainerRun, Mount, safe_name
from osmo.runtime.container.runs import ContainerRuns
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import TaskSpec
from osmo.tasktypes.registry import shipped_packages

__all__ = ["ContainerRuntime", "owner_id"]

_GPU_SHM = 1 << 30  # bytes of /dev/shm for a GPU task (the engines' 64 MiB starves loaders)
_THREADS = "OMP_NUM_THREADS"  # what a task's cpu request sets (``osmo.worker.taskenv``)
_KEEP_IMAGE_VARIABLES = 256  # image ids whose variables' names are remembered
_LAYOUT = replace(DATA_LAYOUT, runner=RUNNER_PATHS)


def owner_id(home: Path) -> str:
    """The ``osmo.owner`` label of a server's or worker's containers: its host and home.

    Stable across restarts (a worker's default name is not), so a restarted process finds
    what its predecessor left.
    """
    where = f"{socket.gethostname()}\0{Path(home).absolute()}"
    return hashlib.sha256(where.encode()).hexdigest()[:20]


class ContainerRuntime:
    """Attempts in their task's image (see the module docstring).

    Args:
        engine: the engine (``osmo.runtime.choose.container_engine``).
        owner: the ``osmo.owner`` label value (:func:`owner_id`).
        pull: pull images that are missing (policy "missing"); off: they must be present.
        kill_retry: seconds between tries of a kill that did not take yet.

    Attributes:
        images: the image ids each workflow resolved on this host (shared with the server's
            placement, for cache fingerprints).
        labels: what every container and network of it carries.
    """

    def __init__(self, engine: ContainerEngine, *, owner: str, pull: bool = True,
                 kill_retry: float = 0.1, hidden: Sequence[Path] = ()) -> None:
        self.engine = engine
        self._hidden = [Path(path).absolute() for path in hidden]
        self._variables: dict[str, frozenset[str]] = {}  # image id -> the names it sets
        self.images = ImageIds(engine)
        self.labels = {"osmo.owner": owner}
        self._pull = pull
        self._runs = ContainerRuns(engine, kill_retry=kill_retry)
        self._groups = Groups(engine, self.labels)

    def describe(self) -> str:
        """``container (podman 4.3.1)``: what ``osmo pool list`` shows."""
        return f"container ({self._engine_text()})"

    def hide(self, path: Path) -> None:
        """Never show ``path`` (osmo's homes, token files) to a typed task.

        A typed task's type folder may hold it; its own binds are the only host paths a
        container task sees otherwise.
        """
        path = Path(path).absolute()
        if path not in self._hidden:
            self._hidden.append(path)

    def clean_orphans(self) -> tuple[list[str], list[str]]:
        """Remove every container, then network, of this owner (after a crash; at start)."""
        return self.engine.remove_labelled(self.labels)

    def paths(self, cmd: PrepareAttempt) -> Paths:
        """OSMO's data layout; ``{{host:NAME}}`` a peer's alias when the group is networked."""
        hosts = self._groups.hosts(cmd)
        return _LAYOUT if hosts is None else replace(_LAYOUT, hosts=hosts)

    def prepare(self, launch: Launch, attempt: Attempt, *,
                progress: Callable[[str], None]) -> Launch:
        """The launch with its container complete: image id, name, labels, user, network.

        Runs on an I/O thread: it may pull (each line the engine prints goes to
        ``progress`` as it comes).

        Raises:
            ImageError: ``image 'x' not found: …``.
            ContainerError: the group's network cannot be made.
        """
        cmd, task, dirs = attempt.cmd, attempt.task, attempt.dirs
        assert task.image is not None, "the chooser gives the container runtime image tasks"
        image = self.images.resolve(cmd.workflow_id, task.image, pull=self._pull,
                                    auth=registry_auth(task.image, attempt.credential),
                                    progress=progress)
        network = self._groups.network(cmd)
        grouped = network is not None and network != "host"
        lead = task.lead or next(iter(cmd.hosts), cmd.task) == cmd.task
        labels = {**self.labels, "osmo.workflow": cmd.workflow_id, "osmo.task": cmd.task,
                  "osmo.attempt": cmd.attempt_id}
        if grouped:
            assert network is not None
            labels.update({"osmo.network": network, "osmo.lead": "1" if lead else "0"})
            self._groups.join(network)
        binds, workdir = mounts(dirs, launch.files, launch.inputs)
        if task.type is not None:  # osmo's runner on the image's python3
            binds += self._runner_mounts(dirs, task, {bind.target for bind in binds})
            workdir = RUNNER_PATHS.workdir
        request = attempt.resources
        env = dict(launch.env)
        if (request.cpu is not None and _THREADS not in env
                and _THREADS not in self._image_variables(image)):
            env[_THREADS] = str(max(1, int(request.cpu)))
        run = ContainerRun(
            image=image, name=safe_name(cmd.attempt_id, owner=self.labels["osmo.owner"]),
            argv=launch.argv, env=env,
            labels=labels, user=f"{os.getuid()}:{os.getgid()}", network=network,
            aliases=(alias(cmd.task),) if grouped else (),
            hostname=alias(cmd.task) if grouped else None,
            cpus=float(request.cpu or 0) or None, memory=request.memory, gpus=attempt.gpus,
            shm_size=_GPU_SHM if attempt.gpus else None, mounts=binds, workdir=workdir,
            secret_env=dict(launch.secret_env),
            secret_env_file=dirs.root / "secret.env" if launch.secret_env else None)
        note = f"image '{task.image}' is {image} ({self._engine_text()})"
        if task.type is not None:
            note += (f"; task type {task.type} runs on its python3, osmo's code bound "
                     f"read-only at {RUNNER_PATHS.code}")
        return replace(launch, run=run, image_id=image, notes=(*launch.notes, note),
                       waits=labels.get("osmo.lead") == "0")

    def _image_variables(self, image: str) -> frozenset[str]:
        """What ``image`` (an id: its variables never change) sets; empty if unknown."""
        found = self._variables.get(image)
        if found is None:
            try:
                found = self.engine.image_variables(image)
            except ContainerError:
                return frozenset()
            if len(self._variables) >= _KEEP_IMAGE_VARIABLES:
                self._variables.clear()
            self._variables[image] = found
        return found

    def _runner_mounts(self, dirs: AttemptDirs, task: TaskSpec, taken: set[str]
                       ) -> tuple[Mount, ...]:
        empty = dirs.root / "cover"
        try:
            empty.mkdir(mode=0o555, exist_ok=True)
            found = runner_mounts(dirs, shipped_packages(),
                                  task.resolved.paths if task.resolved else (),
                                  hidden=self._hidden, empty=empty)
        except (OSError, CoverError) as exc:
            raise PrepareError(f"task '{task.name}': {exc}") from exc
        return tuple(bind for bind in found if bind.target not in taken)

    def start(self, launch: Launch) -> ProcessHandle:
        """Start the container (a peer first waits for its lead's: an I/O thread's call).

        Raises:
            StartError: the engine's CLI cannot be started or the run cannot be expressed.
        """
        run = _run(launch)
        if launch.waits:
            self._groups.wait_for_lead(run)
        spawned = time.time()  # its container starts after this (what a peer waits for)
        handle = self._runs.start(run.argv, cwd=launch.cwd, env=run.env, container=run)
        self._groups.started(run, since=spawned)
        return handle

    def kill(self, handle: ProcessHandle, *, force: bool = False) -> None:
        """SIGTERM (SIGKILL and removal when ``force``) to the container; never raises."""
        self._runs.kill(handle, force=force)

    def reap(self, handle: ProcessHandle) -> int:
        """The container's exit code, once its CLI has ended."""
        return self._runs.reap(handle)

    def release(self, handle: ProcessHandle) -> None:
        """Close the handle; the secret file goes, a killed or failed container too."""
        self._runs.release(handle)

    def exec(self, launch: Launch, command: Sequence[str], *, tty: bool,
             term: str | None) -> ExecCommand:
        """``<engine> exec -i [-t]`` of ``command`` in the running container."""
        env = [f"--env=TERM={term}"] if tty and term is not None else []
        argv = [self.engine.engine.path, "exec", "-i", *(["-t"] if tty else []), *env,
                _run(launch).name, *command]
        return ExecCommand(argv, launch.cwd, self.engine.env)

    def connector(self, launch: Launch, handle: ProcessHandle) -> Connector:
        """To the task's ports on its container's own address.

        Raises:
            ConnectError: the container has no network address of its own.
            ContainerError: the engine cannot inspect it.
        """
        address = self.engine.address(_run(launch).name)
        if address is None:
            raise ConnectError("the task's container has no network address of its own")
        return lambda port, udp: dial(address, port, udp=udp)

    def cleanup(self, launch: Launch) -> None:
        """Its group's network goes with the group's last member here (in the background)."""
        run = launch.run
        if isinstance(run, ContainerRun) and run.network not in (None, "host"):
            self._runs.later(self._groups.left, run)

    def close(self) -> None:
        """Wait for the engine calls still under way; remove the networks still in use."""
        self._runs.close()
        self._groups.close()

    def _engine_text(self) -> str:
        return f"{self.engine.engine.name} {self.engine.engine.version}"


def _run(launch: Launch) -> ContainerRun:
    run = launch.run
    if not isinstance(run, ContainerRun):
        raise TypeError(f"{launch!r} was not prepared by a container runtime")
    return run


def _conforms(runtime: ContainerRuntime) -> Runtime:
    """Never called: mypy checks here that ContainerRuntime keeps the runtime contract."""
    return runtime
