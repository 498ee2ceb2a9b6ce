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
  a group's peer starts once its lead's container runs. With warm starts on (podman only:
  :meth:`ContainerRuntime.warm_up`), a typed task's attempt is a fork of a runner in a
  container of its image that imported its type once (``osmo.runtime.container.warm``):
  unless the task says ``warm: false``, is in a networked group or has GPUs, or its
  limits cannot be kept (no cgroup v1 hierarchy); its exec is then a new container over
  the attempt's view.
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
import uuid
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
from osmo.runtime.container.run import (
    ContainerError,
    ContainerRun,
    Mount,
    run_argv,
    safe_name,
)
from osmo.runtime.container.runs import ContainerRuns
from osmo.runtime.container.warm import (
    ContainerWarmHandle,
    ContainerWarmKey,
    ContainerWarmRunners,
    WarmRun,
)
from osmo.runtime.process.warm import RunnerInfo
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import TaskSpec
from osmo.tasktypes.registry import entry_target, shipped_packages

__all__ = ["ContainerRuntime", "owner_id"]

_GPU_SHM = 1 << 30  # bytes of /dev/shm for a GPU task (the engines' 64 MiB starves loaders)
_THREADS = "OMP_NUM_THREADS"  # what a task's cpu request sets (``osmo.worker.taskenv``)
_KEEP_IMAGE_VARIABLES = 256  # image ids whose variables are remembered
_LAYOUT_ROOTS = ("/osmo/data/", "/osmo/run/")  # made in a runner container for its attempts
_FRESH_ROOTS = ("/tmp/", "/dev/shm/")  # each warm attempt's own, empty
_ENGINE_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"  # with no ENV
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
        hidden: what no task may see (osmo's homes, token files): covered where a typed
            task's type folder holds it (:meth:`hide` adds more).
        cover: an empty folder, bound read-only over such a hidden folder.

    Attributes:
        images: the image ids each workflow resolved on this host (shared with the server's
            placement, for cache fingerprints).
        labels: what every container and network of it carries.
    """

    def __init__(self, engine: ContainerEngine, *, owner: str, pull: bool = True,
                 kill_retry: float = 0.1, hidden: Sequence[Path] = (),
                 cover: Path | None = None) -> None:
        self.engine = engine
        self._hidden = [Path(path).absolute() for path in hidden]
        self._cover = cover
        self._variables: dict[str, dict[str, str]] = {}  # image id -> the variables it sets
        self.images = ImageIds(engine)
        self.labels = {"osmo.owner": owner}
        self._pull = pull
        self._runs = ContainerRuns(engine, kill_retry=kill_retry)
        self._groups = Groups(engine, self.labels)
        self._warm: ContainerWarmRunners | None = None

    def warm_up(self, *, idle: float, max_rss: int | None) -> None:
        """Start typed tasks' attempts from runners in containers of their images.

        ``idle``: seconds a runner container waits for its next attempt; ``max_rss``: bytes
        of resident memory over which it is retired. Only podman passes the runner its
        socket (``--preserve-fds``): with docker every attempt starts cold.
        """
        if self.engine.engine.name == "podman" and self._warm is None:
            self._warm = ContainerWarmRunners(self.engine, self.labels["osmo.owner"],
                                              idle=idle, max_rss=max_rss, hidden=self._hidden,
                                              cover=self._cover)

    def warm_runners(self) -> list[RunnerInfo]:
        """Its live runner containers (``osmo resource list``)."""
        return self._warm.runners() if self._warm is not None else []

    def sweep(self) -> None:
        """Forget the runner containers that ended (idle)."""
        if self._warm is not None:
            self._warm.sweep()

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
        notes: tuple[str, ...] = (note,)
        if task.type is not None:
            notes = (note + f"; task type {task.type} runs on its python3, osmo's code bound "
                            f"read-only at {RUNNER_PATHS.code}",)
            warm = self._warm_start(task, run)
            if warm is not None:
                notes += (f"warm start: forked from a runner of {task.type} in a container "
                          "of its image",)
                return replace(launch, run=warm, image_id=image,
                               notes=(*launch.notes, *notes))
        return replace(launch, run=run, image_id=image, notes=(*launch.notes, *notes),
                       waits=labels.get("osmo.lead") == "0")

    def _warm_start(self, task: TaskSpec, run: ContainerRun
                    ) -> WarmRun | None:
        """How ``run`` starts warm (None: cold), its runner started if need be (blocks)."""
        if (self._warm is None or task.warm is False or run.network is not None or run.gpus
                or task.type is None):
            return None
        resolved = task.resolved
        key = ContainerWarmKey(run.image, task.type, resolved.version if resolved else None,
                               tuple(resolved.paths) if resolved else (),
                               entry=entry_target(task.type))
        if not self._warm.ready(key):
            return None
        if (run.cpus or run.memory) and not self._warm.can_limit(key):
            return None  # never an attempt without its limits: cold, as podman limits it
        binds = tuple(m for m in run.mounts if not _in_code(m.target))  # the runner has those
        if not all(self._warm.has(key, m.target) for m in binds
                   if not m.target.startswith(_LAYOUT_ROOTS + _FRESH_ROOTS)):
            return None  # a file it binds where the image has none: cold (see warm_runner)
        # what a cold container's process starts with: the engine's, the image's, its own
        uid = (run.user or "0").partition(":")[0]
        env = {"PATH": _ENGINE_PATH, "container": self.engine.engine.name,
               "HOME": "/root" if uid == "0" else "/", **self._image_variables(run.image),
               **run.env}
        return WarmRun(key, replace(run, env=env, mounts=binds))

    def _image_variables(self, image: str) -> dict[str, str]:
        """What ``image`` (an id: its variables never change) sets; empty if unknown."""
        found = self._variables.get(image)
        if found is None:
            try:
                found = self.engine.image_environment(image)
            except ContainerError:
                return {}
            if len(self._variables) >= _KEEP_IMAGE_VARIABLES:
                self._variables.clear()
            self._variables[image] = found
        return found

    def _runner_mounts(self, dirs: AttemptDirs, task: TaskSpec, taken: set[str]
                       ) -> tuple[Mount, ...]:
        try:
            found = runner_mounts(dirs, shipped_packages(),
                                  task.resolved.paths if task.resolved else (),
                                  hidden=self._hidden, empty=self._cover)
        except CoverError as exc:
            raise PrepareError(f"task '{task.name}': {exc}") from exc
        return tuple(bind for bind in found if bind.target not in taken)

    def start(self, launch: Launch) -> ProcessHandle:
        """Start the container (a peer first waits for its lead's: an I/O thread's call).

        Raises:
            StartError: the engine's CLI cannot be started or the run cannot be expressed.
        """
        if isinstance(launch.run, WarmRun) and self._warm is not None:
            return self._warm.start(launch.run.key, launch.run.run)
        run = _run(launch)
        if launch.waits:
            self._groups.wait_for_lead(run)
        spawned = time.time()  # its container starts after this (what a peer waits for)
        handle = self._runs.start(run.argv, cwd=launch.cwd, env=run.env, container=run)
        self._groups.started(run, since=spawned)
        return handle

    def kill(self, handle: ProcessHandle, *, force: bool = False) -> None:
        """SIGTERM (SIGKILL and removal when ``force``) to the container; never raises."""
        if isinstance(handle, ContainerWarmHandle) and self._warm is not None:
            self._warm.kill(handle, force=force)
            return
        self._runs.kill(handle, force=force)

    def reap(self, handle: ProcessHandle) -> int:
        """The container's exit code, once its CLI has ended."""
        if isinstance(handle, ContainerWarmHandle) and self._warm is not None:
            return self._warm.reap(handle)
        return self._runs.reap(handle)

    def release(self, handle: ProcessHandle) -> None:
        """Close the handle; the secret file goes, a killed or failed container too."""
        if isinstance(handle, ContainerWarmHandle) and self._warm is not None:
            self._warm.release(handle)
            return
        self._runs.release(handle)

    def exec(self, launch: Launch, command: Sequence[str], *, tty: bool,
             term: str | None) -> ExecCommand:
        """``<engine> exec -i [-t]`` of ``command`` in the running container."""
        env = [f"--env=TERM={term}"] if tty and term is not None else []
        if isinstance(launch.run, WarmRun):  # a new container over the attempt's view
            run = replace(launch.run.run, name=f"{launch.run.run.name}-exec-{uuid.uuid4().hex[:8]}",
                          argv=tuple(command), secret_env={}, secret_env_file=None)
            argv = run_argv(self.engine.engine, run)
            argv[2:2] = ["-i", *(["-t"] if tty else []), *env]
            return ExecCommand(argv, launch.cwd, self.engine.env)
        argv = [self.engine.engine.path, "exec", "-i", *(["-t"] if tty else []), *env,
                _run(launch).name, *command]
        return ExecCommand(argv, launch.cwd, self.engine.env)

    def connector(self, launch: Launch, handle: ProcessHandle) -> Connector:
        """To the task's ports on its container's own address.

        Raises:
            ConnectError: the container has no network address of its own.
            ContainerError: the engine cannot inspect it.
        """
        name = _run(launch).name
        if isinstance(launch.run, WarmRun) and self._warm is not None:
            found = self._warm.runner(launch.run.key)  # its network is its runner container's
            if found is None:
                raise ConnectError("the task's runner container has ended")
            name = found[0]
        address = self.engine.address(name)
        if address is None:
            raise ConnectError("the task's container has no network address of its own")
        return lambda port, udp: dial(address, port, udp=udp)

    def cleanup(self, launch: Launch) -> None:
        """Its group's network goes with the group's last member here (in the background)."""
        run = launch.run
        if isinstance(run, ContainerRun) and run.network not in (None, "host"):
            self._runs.later(self._groups.left, run)

    def close(self) -> None:
        """End the runner containers, wait for the engine calls, remove the networks."""
        if self._warm is not None:
            self._warm.close()
        self._runs.close()
        self._groups.close()

    def _engine_text(self) -> str:
        return f"{self.engine.engine.name} {self.engine.engine.version}"


def _in_code(target: str) -> bool:
    """Whether ``target`` is osmo's code or a type's folder (a runner container has them)."""
    return any(target == root or target.startswith(root + "/") for root in (
        RUNNER_PATHS.code, RUNNER_PATHS.types.partition("/{}")[0]))


def _run(launch: Launch) -> ContainerRun:
    run = launch.run.run if isinstance(launch.run, WarmRun) else launch.run
    if not isinstance(run, ContainerRun):
        raise TypeError(f"{launch!r} was not prepared by a container runtime")
    return run


def _conforms(runtime: ContainerRuntime) -> Runtime:
    """Never called: mypy checks here that ContainerRuntime keeps the runtime contract."""
    return runtime
