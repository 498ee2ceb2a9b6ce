"""The one chooser: how an attempt runs here (a host process, sandboxed or not, or a container).

Two choices, each made once:

- **the node's** (when a server's or worker's pool is made): :func:`processes_for_node` picks
  the sandboxed process runtime when bubblewrap works here (``--sandbox auto``; ``on``
  requires it, ``off`` refuses it), else the plain one, and says why;
  :func:`containers_for_node` picks the container runtime when an engine answers
  (``--runtime auto``; ``container`` requires one, ``process`` refuses it). The node's
  :class:`Runtimes` holds what was chosen.
- **each attempt's** (:meth:`Runtimes.choose`): a task runs in its image where the node runs
  containers and :func:`container_image` names its image (a typed task's only on the node's
  own engine: a cluster's pods and Slurm's jobs run it as a process);
  every other task runs as a (sandboxed) process, its image only noted in its log. The
  server's placement asks :func:`in_container` too (a cache fingerprint names the image id
  of a task that runs in its image), never deciding it again.
- **a cluster node's** (``--runtime slurm``: :func:`slurm_for_node`): every attempt runs as
  a job of the cluster's scheduler (``osmo.runtime.slurm``); the node's :class:`Runtimes`
  holds it as its ``cluster`` runtime, which then runs every task.

A node's image runtime may also be a cluster's: :func:`image_runtime_for_node` gives the
Kubernetes runtime for ``--runtime kubernetes`` (an ``osmo worker`` inside or beside a
cluster: each image task a pod), else the container runtime as above. The Kubernetes
runtime is imported only then (its client is an extra).
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from osmo.errors import InfrastructureError, UsageError
from osmo.layout import Home
from osmo.options import SandboxMode, SlurmOptions, parse_share
from osmo.runtime.api import Adopting, Runtime
from osmo.runtime.container.engine import ContainerEngine, EngineNotFound, detect_engine
from osmo.runtime.container.images import ImageIds
from osmo.runtime.container.runtime import ContainerRuntime, owner_id
from osmo.runtime.process.runtime import ProcessRuntime
from osmo.runtime.process.sandbox import (
    Sandbox,
    choose,
    node_network,
    unavailable_reason,
    unavailable_summary,
)
from osmo.runtime.process.sandboxed import SandboxRuntime
from osmo.runtime.process.warm import WarmRunners
from osmo.runtime.slurm import Slurm, SlurmRuntime
from osmo.spec.model import TaskSpec

__all__ = ["CLUSTER_RUNTIMES", "RUNTIMES", "Runtimes", "container_engine", "container_image",
           "containers_for_node", "image_ids", "image_runtime_for_node", "in_container",
           "processes_for_node", "slurm_for_node"]

_log = logging.getLogger("osmo.worker.pool")

RUNTIMES = ("auto", "container", "process", "slurm")
"""The values of ``--runtime`` a node's own engine or its Slurm serves."""
CLUSTER_RUNTIMES = ("kubernetes",)
"""The values of ``--runtime`` that run image tasks on a cluster (an ``osmo worker``'s)."""


def container_image(task: TaskSpec, *, typed: bool = True) -> str | None:
    """The image ``task`` runs in where the node runs containers (None: none).

    Its ``image:``; a task with no image runs as a host process everywhere. A typed task
    (``type:``) runs osmo's runner on its image's ``python3`` where the node's own engine
    (podman, docker) runs it; a cluster's pods and Slurm's jobs run it as a process
    (``typed=False``: what they ask).
    """
    return task.image if typed or task.type is None else None


def in_container(task: TaskSpec, *, typed: bool = True) -> bool:
    """Whether ``task`` runs in its image where the node runs containers (``typed``: above)."""
    return container_image(task, typed=typed) is not None


class Runtimes:
    """A node's runtimes, and the choice of the one that runs each attempt.

    Args:
        process: how tasks run as host processes here (sandboxed or not).
        container: how tasks run in their images here: containers or a cluster's pods
            (None: this node runs image tasks as processes).
        cluster: a cluster scheduler's runtime that runs every task (None: none).
        cluster_images: the cluster's runtime for tasks that run in their image (None: the
            cluster has no container engine; ``cluster`` then refuses them).
    """

    def __init__(self, process: ProcessRuntime,
                 container: Runtime | None = None,
                 cluster: Runtime | None = None,
                 cluster_images: Runtime | None = None) -> None:
        self.process, self.container = process, container
        self.cluster, self.cluster_images = cluster, cluster_images

    def choose(self, task: TaskSpec) -> Runtime:
        """The runtime that runs ``task``'s attempts here."""
        if self.cluster is not None:
            if self.cluster_images is not None and in_container(task, typed=False):
                return self.cluster_images
            return self.cluster
        if self.container is not None and in_container(
                task, typed=isinstance(self.container, ContainerRuntime)):
            return self.container
        return self.process

    def adopting(self) -> list[Adopting]:
        """Its runtimes whose launches outlive the node (``osmo.runtime.api.Adopting``)."""
        found: list[Adopting] = []
        for runtime in (self.cluster, self.cluster_images, self.container):
            if isinstance(runtime, Adopting):
                found.append(runtime)
        return found

    @property
    def sandbox(self) -> Sandbox | None:
        """The sandbox process tasks run in (None: they run unsandboxed)."""
        return self.process.sandbox

    def describe(self) -> str:
        """How image tasks run here: ``container (podman 4.3.1)``, ``slurm (...)``, ``process``."""
        return (self.cluster_images or self.cluster or self.container
                or self.process).describe()

    def hide(self, path: Path) -> None:
        """Also hide ``path`` (another home, a secret file) from the tasks that could see it.

        Sandboxed tasks, and typed tasks in their image whose type's folder holds it.
        """
        self.process.hide(path)
        if isinstance(self.container, ContainerRuntime):
            self.container.hide(path)

    def close(self) -> None:
        """The node stops: the cluster's and container runtime's calls, then the namespaces."""
        for cluster in (self.cluster, self.cluster_images):
            if cluster is not None:
                cluster.close()
        if self.container is not None:
            self.container.close()
        self.process.close()


def processes_for_node(mode: SandboxMode, shares: Sequence[str], *, home: Path,
                       address: str | None, pool: str,
                       warm: WarmRunners | None = None) -> ProcessRuntime:
    """How a node's tasks run as host processes: in bubblewrap, in the node's namespaces, or not.

    Args:
        mode: ``auto`` (a sandbox when one works here), ``on`` (required) or ``off``.
        shares: host folders every sandboxed task may see (``DIR`` or ``DIR:ro``).
        home: osmo's home, which no task may see (nor a share inside it).
        address: how peers reach this node's tasks (given to the node's network).
        pool: the pool's name (for the warning when ``auto`` finds no sandbox).
        warm: the node's warm runners, which typed tasks start from (in the sandbox: only
            types osmo ships, and only for a root osmo; closed with the runtime).

    Without a sandbox, the runtime says why in each task's log (``note``), in a few words
    for ``osmo resource list`` (``why``), and, when ``auto`` found none, once at start
    (``warning``: nobody chose to run tasks unsandboxed). Without outbound network for its
    tasks, the sandboxed runtime says so in each task's log.

    Raises:
        InfrastructureError: ``mode`` is ``on`` and no sandbox works here.
        UsageError: a share is relative or inside ``home``.
    """
    inside = [d for d in shares if Path(parse_share(d)[0]).absolute().is_relative_to(home)]
    if inside:
        raise UsageError(f"--sandbox-share {inside[0]}: it is inside osmo's home "
                         f"{home}, which tasks must never see")
    sandbox = choose(mode, shares)
    if mode == "off":
        return ProcessRuntime(note="no sandbox: this task sees the host as the worker's user "
                                   "(--sandbox off)", why="--sandbox off", warm=warm)
    if sandbox is None:
        reason, summary = unavailable_reason(), unavailable_summary()
    else:
        try:
            network = node_network(address=address)
        except InfrastructureError as exc:
            if mode == "on":
                raise
            reason, summary = str(exc), "no network namespace"
        else:
            if network.caveat:
                _log.warning("sandboxed tasks: %s", network.caveat)
            return SandboxRuntime(sandbox.joined(network), network, hidden=(home,),
                                  note=network.caveat or None, warm=warm)
    return ProcessRuntime(
        note=f"no sandbox: this task sees the host as the worker's user ({reason})",
        why=summary,
        warning=f"UNSANDBOXED: pool {pool} runs its tasks without a sandbox (--sandbox {mode})"
                f": {reason}. They see the host as uid {os.geteuid()}, osmo's home (state, "
                "credentials) included; --sandbox on refuses to start instead", warm=warm)


def container_engine(runtime: str, engine: str | None = None) -> ContainerEngine | None:
    """The engine that runs image tasks, or None when they run as processes.

    Args:
        runtime: ``auto`` (an engine if one answers), ``container`` (one must) or ``process``.
        engine: ``podman`` or ``docker`` (default: the first that answers).

    Raises:
        EngineNotFound: ``container`` with no usable engine (the message says what to install),
            or an unknown ``engine``/``runtime``.
    """
    if runtime in CLUSTER_RUNTIMES:
        raise EngineNotFound(f"--runtime {runtime} runs in `osmo worker` (a cluster's node); "
                             "a server's own pool runs containers or processes")
    if runtime not in RUNTIMES:
        raise EngineNotFound(f"unknown runtime {runtime!r}: choose {', '.join(RUNTIMES)}")
    if runtime in ("process", "slurm"):
        return None
    try:
        return ContainerEngine(detect_engine(engine))
    except EngineNotFound:
        if runtime == "container" or engine is not None:
            raise
        return None


def containers_for_node(runtime: str, engine: str | None, home: Home
                        ) -> ContainerRuntime | None:
    """The container runtime of a server's or worker's pool (None: image tasks are processes).

    What a crashed predecessor on ``home`` left (containers, networks) is removed first.

    Raises:
        EngineNotFound: ``--runtime container`` with no usable engine (names the package).
    """
    found = container_engine(runtime, engine)
    if found is None:
        return None
    cover = home.root / "cover"  # empty: what covers osmo's files in a type's folder
    cover.mkdir(mode=0o555, parents=True, exist_ok=True)
    made = ContainerRuntime(found, owner=owner_id(home.root), hidden=(home.root,), cover=cover)
    made.clean_orphans()
    return made


def slurm_for_node(runtime: str, home: Home, options: SlurmOptions | None = None, *,
                   python: str | None = None, engine: str | None = None
                   ) -> tuple[SlurmRuntime, SlurmRuntime | None] | None:
    """A login host's Slurm runtimes: every task's, and image tasks' (None: not ``slurm``).

    Image tasks run through the container engine found here (``engine``: podman or docker,
    default the first that answers), expected on the compute nodes too; else through pyxis
    (``srun --container-image``) when the cluster has it; without either the second is None
    and image tasks fail at start. The jobs a crashed predecessor on ``home`` left queued or
    running are the node's to adopt or cancel (``Adopting``; ``osmo.worker.remote``).

    Raises:
        SlurmError: Slurm's commands are missing or slurmctld does not answer.
        UsageError: a partition, account or QOS that is not a plain Slurm word.
    """
    if runtime != "slurm":
        return None
    owner, slurm = owner_id(home.root), Slurm()
    made = SlurmRuntime(slurm, owner=owner, options=options, python=python or sys.executable)
    slurm.version()  # fails now, with what is missing, rather than at the first task
    try:
        found = ContainerEngine(detect_engine(engine))
    except EngineNotFound:
        images = slurm.has_pyxis() and engine is None
        return made, SlurmRuntime(slurm, owner=owner, options=options, pyxis=True,
                                  python=python or sys.executable) if images else None
    boxes = ContainerRuntime(found, owner=owner)
    boxes.clean_orphans()  # what a crashed predecessor's jobs left
    return made, SlurmRuntime(slurm, owner=owner, options=options,
                              python=python or sys.executable, containers=boxes)


def image_ids(runtime: str, engine: str | None, containers: ContainerRuntime | None
              ) -> Callable[[str, str], str | None] | None:
    """The server's ``(workflow id, image) → id`` lookup for cache fingerprints.

    The local pool's (so server and pool resolve each image once per workflow), else one
    for the engine ``runtime`` would choose (a server with remote workers only); None when
    there is none (tags are used). An image not on this host gives None; never pulls.
    """
    if containers is not None:
        return containers.images.known
    try:
        found = container_engine(runtime, engine)
    except EngineNotFound:
        return None
    return ImageIds(found).known if found is not None else None


def image_runtime_for_node(runtime: str, engine: str | None, home: Home, *,
                           kubernetes_config: str | None = None) -> Runtime | None:
    """How a worker's image tasks run: pods (``kubernetes``), containers, or None (processes).

    ``kubernetes_config``: the pool's configuration file (``osmo.runtime.kubernetes.config``).
    What a previous life on ``home`` left (pods, containers) is removed first.

    Raises:
        EngineNotFound: ``--runtime container`` with no usable engine.
        KubeError: ``--runtime kubernetes`` and the cluster cannot be reached.
        UsageError: the Kubernetes configuration is wrong.
    """
    if runtime == "kubernetes":
        from osmo.runtime.kubernetes.runtime import KubernetesRuntime

        return KubernetesRuntime.for_node(kubernetes_config, instance=owner_id(home.root))
    return containers_for_node(runtime, engine, home)
