"""Container tasks of a pool: which tasks run in their image, and everything around the run.

A task with an ``image:`` and no ``type:`` runs in that image when the node's runtime is
``container`` (``--runtime``; ``auto`` picks it when an engine answers): :func:`choose` is
that decision, made once when a server or worker starts. Typed plugin tasks and tasks with no
image stay host processes (``osmo.runtime.process.groups``).

The data layout inside the container is ``osmo.worker.container_layout``'s.

:class:`ContainerTasks` finishes a prepared launch (:meth:`ContainerTasks.finish`): resolves
the image to its id (pulling a missing one, its progress lines to the task's log as the
engine prints them, registry credentials for the pull only), names and labels the container
(``osmo.owner``, ``osmo.workflow``, ``osmo.task``, ``osmo.attempt``), runs it as the
invoking uid:gid with ``--init``, applies cpu/memory limits and GPU indices, and puts a
group on its network.

Groups: when every member of a group runs at one address (this host), the group gets its own
network and ``{{host:NAME}}`` is NAME's alias on it (the task name). Members spread over
several hosts use the host's network and ``{{host:NAME}}`` stays NAME's address. A peer of
a networked group starts once the lead's container runs (the lead listens first, as in OSMO).

Orphans: :meth:`ContainerTasks.clean_orphans` removes every container and network carrying
this owner's label; servers and workers call it at start, before anything new runs.
"""

from __future__ import annotations

import hashlib
import os
import re
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

from osmo.runtime.container.engine import ContainerEngine, EngineNotFound, detect_engine
from osmo.runtime.container.run import (
    ContainerError,
    ContainerRun,
    RegistryAuth,
    safe_name,
)
from osmo.runtime.container.runs import ContainerRuntime
from osmo.runtime.process.groups import ProcessHandle
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import ResourceSpec, TaskSpec
from osmo.worker.container_images import ImageIds
from osmo.worker.workdir import Launch, remove_secret_files

if TYPE_CHECKING:
    from osmo.layout import AttemptDirs

__all__ = ["RUNTIMES", "ContainerTasks", "GpuSlots", "Limits", "choose",
           "for_node", "image_ids", "owner_id"]

RUNTIMES = ("auto", "container", "process")
"""The values of ``--runtime``."""

_ALIAS = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,62}")
_LEAD_WAIT = 30.0  # s: a peer waits this long for its lead's container, then starts anyway
_CLOCK_SLACK = 1.0  # s: events are stamped by the engine; read a little before the spawn
_GPU_SHM = 1 << 30  # bytes of /dev/shm for a GPU task (the engines' 64 MiB starves loaders)


def choose(runtime: str, engine: str | None = None) -> ContainerEngine | None:
    """The engine that runs image tasks, or None when they run as processes.

    Args:
        runtime: ``auto`` (an engine if one answers), ``container`` (one must) or ``process``.
        engine: ``podman`` or ``docker`` (default: the first that answers).

    Raises:
        EngineNotFound: ``container`` with no usable engine (the message says what to install),
            or an unknown ``engine``/``runtime``.
    """
    if runtime not in RUNTIMES:
        raise EngineNotFound(f"unknown runtime {runtime!r}: choose {', '.join(RUNTIMES)}")
    if runtime == "process":
        return None
    try:
        return ContainerEngine(detect_engine(engine))
    except EngineNotFound:
        if runtime == "container" or engine is not None:
            raise
        return None


def owner_id(home: Path) -> str:
    """The ``osmo.owner`` label of a server's or worker's containers: its host and home.

    Stable across restarts (a worker's default name is not), so a restarted process finds
    what its predecessor left.
    """
    where = f"{socket.gethostname()}\0{Path(home).absolute()}"
    return hashlib.sha256(where.encode()).hexdigest()[:20]


@dataclass(frozen=True)
class Limits:
    """What a task may use: ``cpus`` (0: no limit), ``memory`` bytes (None: no limit), GPUs."""

    cpus: float = 0.0
    memory: int | None = None
    gpus: tuple[int, ...] = ()


class ContainerTasks:
    """A pool's container side: the engine, its runtime, networks and orphans.

    Args:
        engine: the engine (``choose``).
        owner: the ``osmo.owner`` label value (``owner_id``).
        pull: pull images that are missing (policy "missing"); off: they must be present.
    """

    def __init__(self, engine: ContainerEngine, *, owner: str, pull: bool = True) -> None:
        self.engine = engine
        self.runtime = ContainerRuntime(engine)
        self.images = ImageIds(engine)
        self.labels = {"osmo.owner": owner}
        self._pull = pull
        self._lock = threading.Lock()
        self._networks: dict[str, int] = {}  # network → attempts of this pool using it
        self._leads: dict[str, threading.Event] = {}  # network → its lead was started
        self._lead_since: dict[str, float] = {}  # network → when its lead's CLI was spawned
        self._gpus: GpuSlots | None = None  # made with the node's GPU count on first use

    def describe(self) -> str:
        """``podman 4.3.1``: what ``osmo pool list`` shows."""
        return f"{self.engine.engine.name} {self.engine.engine.version}"

    @staticmethod
    def applies(task: TaskSpec) -> bool:
        """Whether ``task`` runs in a container (an image, and not a typed plugin task)."""
        return task.image is not None and task.type is None

    def clean_orphans(self) -> tuple[list[str], list[str]]:
        """Remove every container, then network, of this owner (after a crash; at start)."""
        return self.engine.remove_labelled(self.labels)

    def placement(self, cmd: PrepareAttempt) -> PrepareAttempt:
        """``cmd`` with ``{{host:NAME}}`` naming the peers' aliases when the group is networked."""
        if self._network(cmd) is None:
            return cmd
        return replace(cmd, hosts={name: _alias(name) for name in cmd.hosts})

    def finish(self, launch: Launch, cmd: PrepareAttempt, task: TaskSpec, dirs: AttemptDirs, *,
               request: ResourceSpec, gpus: int, auth: RegistryAuth | None = None,
               progress: Callable[[str], None] = lambda line: None) -> Launch:
        """The launch with its container complete: image id, name, labels, user, network.

        ``cmd`` is the placement as sent (not :meth:`placement`'s); ``request`` the task's
        resources (cpu/memory limits, GPU count) and ``gpus`` how many the node has. Runs
        on an I/O thread (it may pull: each line the engine prints goes to ``progress`` as
        it comes). Raises ImageError (``image 'x' not found: …``) or ContainerError (the
        network cannot be made); nothing stays held then.
        """
        if self._gpus is None:
            self._gpus = GpuSlots(gpus)
        held = self._gpus.take(cmd.attempt_id, request.gpu or 0)
        limits = Limits(cpus=float(request.cpu or 0), memory=request.memory, gpus=held)
        try:
            return self._finish(launch, cmd, task, dirs, limits, auth, progress)
        except BaseException:
            self._gpus.give_back(cmd.attempt_id)
            remove_secret_files(launch)  # a failed preparation leaves no secret behind
            raise

    def start(self, launch: Launch, *, wait_for_lead: bool = False) -> ProcessHandle:
        """Start ``launch`` in its container (after its lead, if told: on an I/O thread).

        Raises:
            StartError: the engine's CLI cannot be started or the run cannot be expressed.
        """
        assert launch.container is not None
        if wait_for_lead:
            self.wait_for_lead(launch.container)
        spawned = time.time()  # its container starts after this (what a peer waits for)
        handle = self.runtime.start(launch.argv, cwd=launch.cwd, env=launch.env,
                                    container=launch.container)
        self.started(launch.container, since=spawned)
        return handle

    def _finish(self, launch: Launch, cmd: PrepareAttempt, task: TaskSpec, dirs: AttemptDirs,
                limits: Limits, auth: RegistryAuth | None,
                progress: Callable[[str], None]) -> Launch:
        assert launch.container is not None and task.image is not None
        image = self.images.resolve(cmd.workflow_id, task.image, pull=self._pull, auth=auth,
                                    progress=progress)
        note = f"image '{task.image}' is {image} ({self.describe()})"
        network = self._network(cmd)
        lead = task.lead or next(iter(cmd.hosts), cmd.task) == cmd.task
        labels = {**self.labels, "osmo.workflow": cmd.workflow_id, "osmo.task": cmd.task,
                  "osmo.attempt": cmd.attempt_id}
        if network is not None and network != "host":
            labels.update({"osmo.network": network, "osmo.lead": "1" if lead else "0"})
            self._join(network)
        run = replace(
            launch.container, image=image, name=safe_name(cmd.attempt_id), labels=labels,
            user=f"{os.getuid()}:{os.getgid()}", network=network,
            aliases=(_alias(cmd.task),) if network not in (None, "host") else (),
            hostname=_alias(cmd.task) if network not in (None, "host") else None,
            cpus=limits.cpus or None, memory=limits.memory, gpus=limits.gpus,
            shm_size=_GPU_SHM if limits.gpus else None,
            secret_env_file=dirs.root / "secret.env" if launch.container.secret_env else None)
        return replace(launch, container=run, notes=(*launch.notes, note))

    # -------------------------------------------------------------- groups

    def started(self, run: ContainerRun, *, since: float | None = None) -> None:
        """Note that ``run``'s engine CLI was spawned (at ``since``, epoch seconds, or now).

        A lead releases its waiting peers, which then wait for its container's start.
        """
        if run.labels.get("osmo.lead") == "1" and run.network is not None:
            with self._lock:
                self._lead_since[run.network] = time.time() if since is None else since
            self._lead_event(run.network).set()

    def wait_for_lead(self, run: ContainerRun) -> None:
        """Block (I/O thread) until the lead of ``run``'s group network runs, at most 30 s.

        The start barrier starts a group's members together; a peer that calls its lead at
        once (OSMO's ``nc`` tutorial) needs the lead to be listening first. The wait is the
        engine's event stream (``ContainerEngine.wait_started``); only an engine without
        one is asked every 50 ms whether the lead runs.
        """
        if run.labels.get("osmo.lead") != "0" or run.network is None:
            return
        deadline = time.monotonic() + _LEAD_WAIT
        if not self._lead_event(run.network).wait(_LEAD_WAIT):
            return
        with self._lock:
            since = self._lead_since.get(run.network, time.time()) - _CLOCK_SLACK
        try:
            self.engine.wait_started(("osmo.network", run.network), ("osmo.lead", "1"),
                                     since=since, timeout=max(0.0, deadline - time.monotonic()))
        except ContainerError:
            self._poll_lead(run.network, deadline)

    def _poll_lead(self, network: str, deadline: float) -> None:
        lead = {**self.labels, "osmo.network": network, "osmo.lead": "1"}
        while time.monotonic() < deadline:
            try:
                if self.engine.running(lead):
                    return
            except ContainerError:
                return
            time.sleep(0.05)

    def ended(self, run: ContainerRun) -> None:
        """An attempt that used ``run`` ended (I/O thread).

        Its GPUs are free again; its group network goes with its last member here.
        """
        if self._gpus is not None:
            self._gpus.give_back(run.labels.get("osmo.attempt", ""))
        if run.network is None or run.network == "host" or "osmo.network" not in run.labels:
            return
        with self._lock:
            left = self._networks.get(run.network, 1) - 1
            if left > 0:
                self._networks[run.network] = left
                return
            self._networks.pop(run.network, None)
            self._leads.pop(run.network, None)
            self._lead_since.pop(run.network, None)
        try:
            self.engine.remove_network(run.network)
        except ContainerError:
            pass  # still in use elsewhere, or the engine failed: orphan clean-up takes it

    def close(self) -> None:
        """Wait for the runtime's engine calls; remove the networks still in use here."""
        self.runtime.close()
        with self._lock:
            networks, self._networks = list(self._networks), {}
        for network in networks:
            try:
                self.engine.remove_network(network)
            except ContainerError:
                pass

    # -------------------------------------------------------------- internals

    def _network(self, cmd: PrepareAttempt) -> str | None:
        """The group's network: its own, ``host`` (spread over hosts) or None (one task)."""
        if len(cmd.hosts) < 2:
            return None
        if len(set(cmd.hosts.values())) > 1:
            return "host"
        return safe_name(cmd.workflow_id, *sorted(cmd.hosts))

    def _join(self, network: str) -> None:
        with self._lock:
            count = self._networks.get(network, 0)
            self._networks[network] = count + 1
            if count:
                return
            try:
                self.engine.create_network(network, self.labels)
            except ContainerError:
                self._networks.pop(network, None)
                raise

    def _lead_event(self, network: str) -> threading.Event:
        with self._lock:
            return self._leads.setdefault(network, threading.Event())


def _alias(task: str) -> str:
    """A task's name on its group network: the name itself when the engine can take it."""
    return task if _ALIAS.fullmatch(task) else safe_name(task)[:63]


class GpuSlots:
    """Which of a node's GPU indices each running attempt holds (the pool's assignment).

    The scheduler counts GPUs; this names them, so two tasks never share one.
    """

    def __init__(self, count: int) -> None:
        self._free = list(range(count))
        self._held: dict[str, tuple[int, ...]] = {}
        self._lock = threading.Lock()

    def take(self, attempt_id: str, count: int) -> tuple[int, ...]:
        """Assign ``count`` free indices to ``attempt_id`` (as many as are free)."""
        with self._lock:
            taken, self._free = tuple(self._free[:count]), self._free[count:]
            self._held[attempt_id] = taken
            return taken

    def give_back(self, attempt_id: str) -> None:
        """Free what ``attempt_id`` held (nothing held is fine)."""
        with self._lock:
            self._free = sorted([*self._free, *self._held.pop(attempt_id, ())])


def for_node(runtime: str, engine: str | None, home: Path) -> ContainerTasks | None:
    """The container side of a server's or worker's pool (None: image tasks are processes).

    Raises:
        EngineNotFound: ``--runtime container`` with no usable engine (names the package).
    """
    found = choose(runtime, engine)
    return ContainerTasks(found, owner=owner_id(home)) if found is not None else None


def image_ids(runtime: str, engine: str | None,
              boxes: ContainerTasks | None) -> Callable[[str, str], str | None] | None:
    """The server's ``(workflow id, image) → id`` lookup for cache fingerprints.

    The local pool's (so server and pool resolve each image once per workflow), else one
    for the engine ``runtime`` would choose (a server with remote workers only); None when
    there is none (tags are used). An image not on this host gives None; never pulls.
    """
    if boxes is not None:
        return boxes.images.known
    found = _quiet_choose(runtime, engine)
    return ImageIds(found).known if found is not None else None


def _quiet_choose(runtime: str, engine: str | None) -> ContainerEngine | None:
    try:
        return choose(runtime, engine)
    except EngineNotFound:
        return None
