"""Container tasks of a pool: which tasks run in their image, and everything around the run.

A task with an ``image:`` and no ``type:`` runs in that image when the node's runtime is
``container`` (``--runtime``; ``auto`` picks it when an engine answers): :func:`choose` is
that decision, made once when a server or worker starts. Typed plugin tasks and tasks with no
image stay host processes (``osmo.runtime.process``).

OSMO's data layout inside the container (:func:`layout`, built when the attempt's folder is
prepared, ``workdir.prepare(boxed=True)``):

- ``{{output}}`` is ``/osmo/data/output``, a read-write bind of the attempt's private
  ``output.partial`` (promotion, ingest and lineage are unchanged);
- ``{{input:N}}`` and ``{{input:NAME}}`` are ``/osmo/data/input/N``, read-only binds of the
  attempt's own input copies;
- ``files:`` and credential mounts are bound read-only at their declared absolute paths (no
  path rewriting); relative ones live in the working folder, bound at ``/osmo/run/work``,
  which is then the container's working folder (else the image's own);
- the environment is the task's, then osmo's (``OSMO_OUTPUT`` etc.), never the host's;
  credential variables go through the runtime's 0600 secret file, never ``--env``.

:class:`ContainerTasks` finishes a prepared launch (:meth:`ContainerTasks.finish`): resolves
the image to its id (pulling a missing one, progress lines kept for the task's log, registry
credentials for the pull only), names and labels the container (``osmo.owner``,
``osmo.workflow``, ``osmo.task``, ``osmo.attempt``), runs it as the invoking uid:gid with
``--init``, applies cpu/memory limits and GPU indices, and puts a group on its network.

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
import posixpath
import re
import socket
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

from osmo.runtime.container import ContainerEngine, EngineNotFound, detect_engine
from osmo.runtime.container_run import (
    DATA_OUTPUT,
    ContainerError,
    ContainerRun,
    Mount,
    RegistryAuth,
    data_input,
    pull_reference,
    safe_name,
)
from osmo.runtime.container_runtime import ContainerRuntime
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import TaskSpec
from osmo.worker import launch as typed
from osmo.worker.secrets import SecretLookup

if TYPE_CHECKING:
    from osmo.layout import AttemptDirs
    from osmo.worker.workdir import Launch

__all__ = ["REGISTRY_PREFIX", "RUNTIMES", "WORKDIR", "ContainerTasks", "GpuSlots", "Limits",
           "choose", "data_path", "for_node", "layout", "osmo_env", "owner_id", "registry_auth"]

RUNTIMES = ("auto", "container", "process")
"""The values of ``--runtime``."""
WORKDIR = "/osmo/run/work"
"""Where the attempt's working folder is bound when the task has relative ``files:``."""

_ALIAS = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,62}")
_LEAD_WAIT = 30.0  # s: a peer waits this long for its lead's container, then starts anyway
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


def osmo_env(cmd: PrepareAttempt) -> dict[str, str]:
    """The variables osmo sets inside a container (the task cannot override them)."""
    return {"OSMO_WORKFLOW_ID": cmd.workflow_id, "OSMO_TASK": cmd.task,
            "OSMO_RETRY": str(cmd.retry), "OSMO_NODE": cmd.node_id,
            "OSMO_OUTPUT": DATA_OUTPUT, "OSMO_FILES_ROOT": "/"}


def data_path(token: str, task: TaskSpec, refs: Sequence[str | None]) -> str | None:
    """The container path of an ``output``/``input:N``/``input:NAME`` token (None: unknown).

    An input resolves only when the attempt has it (``refs``: each input's reference).
    """
    kind, _, arg = token.partition(":")
    if kind == "output":
        return DATA_OUTPUT
    for index, spec in enumerate(task.inputs):
        names = (str(index),) if arg.isdigit() else (typed.input_name(spec), spec.task)
        if arg in names and refs[index] is not None:
            return data_input(index)
    return None


def layout(dirs: AttemptDirs, task: TaskSpec, files: Mapping[str, Path],
           refs: Sequence[str | None], secret_env: Mapping[str, str]) -> ContainerRun:
    """The container's data layout for a prepared attempt (see the module docstring).

    Args:
        dirs: the attempt's folder.
        task: what runs (its image).
        files: each declared ``files:``/credential path → where it was written.
        refs: each input's reference (a folder on this node), None when it has none.
        secret_env: the credential variables (written to the runtime's secret file).

    The result still lacks its name, labels, user and image id (:meth:`ContainerTasks.finish`).
    """
    assert task.image is not None
    mounts = [Mount(dirs.output_partial, DATA_OUTPUT, read_only=False)]
    mounts += [Mount(Path(ref), data_input(i)) for i, ref in enumerate(refs)
               if ref is not None and ref.startswith("/")]
    relative = False
    for declared, written in files.items():
        if declared.startswith("/"):
            mounts.append(Mount(written, posixpath.normpath(declared)))
        else:
            relative = True
    if relative:
        mounts.append(Mount(dirs.work, WORKDIR, read_only=False))
    return ContainerRun(image=task.image, name="", secret_env=dict(secret_env),
                        mounts=tuple(mounts), workdir=WORKDIR if relative else None)


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
        self.labels = {"osmo.owner": owner}
        self._pull = pull
        self._lock = threading.Lock()
        self._networks: dict[str, int] = {}  # network → attempts of this pool using it
        self._leads: dict[str, threading.Event] = {}  # network → its lead was started

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
               limits: Limits | None = None, auth: RegistryAuth | None = None) -> Launch:
        """The launch with its container complete: image id, name, labels, user, network.

        ``cmd`` is the placement as sent (not :meth:`placement`'s). Runs on an I/O thread
        (it may pull). Raises ImageError (``image 'x' not found: …``)
        or ContainerError (the network cannot be made).
        """
        assert launch.container is not None and task.image is not None
        notes: list[str] = []
        image = self.engine.resolve(task.image, pull=self._pull, auth=auth,
                                    progress=lambda line: notes.append(f"pull: {line}"))
        notes.append(f"image '{task.image}' is {image.id} ({self.describe()})")
        limits = limits or Limits()
        network = self._network(cmd)
        lead = task.lead or next(iter(cmd.hosts), cmd.task) == cmd.task
        labels = {**self.labels, "osmo.workflow": cmd.workflow_id, "osmo.task": cmd.task,
                  "osmo.attempt": cmd.attempt_id}
        if network is not None and network != "host":
            labels.update({"osmo.network": network, "osmo.lead": "1" if lead else "0"})
            self._join(network)
        run = replace(
            launch.container, image=image.id, name=safe_name(cmd.attempt_id), labels=labels,
            user=f"{os.getuid()}:{os.getgid()}", network=network,
            aliases=(_alias(cmd.task),) if network not in (None, "host") else (),
            hostname=_alias(cmd.task) if network not in (None, "host") else None,
            cpus=limits.cpus or None, memory=limits.memory, gpus=limits.gpus,
            shm_size=_GPU_SHM if limits.gpus else None,
            secret_env_file=dirs.root / "secret.env" if launch.container.secret_env else None)
        return replace(launch, container=run, notes=(*launch.notes, *notes))

    # -------------------------------------------------------------- groups

    def started(self, run: ContainerRun) -> None:
        """Note that ``run`` was started (a lead releases its waiting peers)."""
        if run.labels.get("osmo.lead") == "1" and run.network is not None:
            self._lead_event(run.network).set()

    def wait_for_lead(self, run: ContainerRun) -> None:
        """Block (I/O thread) until the lead of ``run``'s group network runs, at most 30 s.

        The start barrier starts a group's members together; a peer that calls its lead at
        once (OSMO's ``nc`` tutorial) needs the lead to be listening first.
        """
        if run.labels.get("osmo.lead") != "0" or run.network is None:
            return
        deadline = time.monotonic() + _LEAD_WAIT
        self._lead_event(run.network).wait(_LEAD_WAIT)
        lead = {**self.labels, "osmo.network": run.network, "osmo.lead": "1"}
        while time.monotonic() < deadline:
            try:
                if self.engine.running(lead):
                    return
            except ContainerError:
                return
            time.sleep(0.05)

    def ended(self, run: ContainerRun) -> None:
        """An attempt that used ``run`` ended: its group network goes with its last member."""
        if run.network is None or run.network == "host" or "osmo.network" not in run.labels:
            return
        with self._lock:
            left = self._networks.get(run.network, 1) - 1
            if left > 0:
                self._networks[run.network] = left
                return
            self._networks.pop(run.network, None)
            self._leads.pop(run.network, None)
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


REGISTRY_PREFIX = "registry://"
"""A registry's credential is named ``registry://HOST`` (keys ``username``, ``password``)."""


def registry_auth(task: TaskSpec, lookup: SecretLookup | None) -> RegistryAuth | None:
    """The stored credential for pulling ``task``'s image, if there is one.

    Found by the image's registry host (``docker.io`` for short names), like a data URL's
    credential; used for the pull only.
    """
    if lookup is None or task.image is None:
        return None
    host = pull_reference(task.image).split("/", 1)[0]
    payload = lookup(REGISTRY_PREFIX + host)
    if not payload or "username" not in payload or "password" not in payload:
        return None
    return RegistryAuth(host, payload["username"], payload["password"])


def for_node(runtime: str, engine: str | None, home: Path) -> ContainerTasks | None:
    """The container side of a server's or worker's pool (None: image tasks are processes).

    Raises:
        EngineNotFound: ``--runtime container`` with no usable engine (names the package).
    """
    found = choose(runtime, engine)
    return ContainerTasks(found, owner=owner_id(home)) if found is not None else None
