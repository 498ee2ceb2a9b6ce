"""The Kubernetes runtime: each attempt runs as a Pod of its task's image.

What it owns, one concern per method of the runtime contract (``osmo.runtime.api``):

- what the task sees: OSMO's data layout, the container runtime's
  (``osmo.runtime.container.layout``): ``/osmo/data/input/N``, ``/osmo/data/output``,
  ``files:`` at their absolute paths, the task's own environment only;
- the image: pinned to its id where the node has a container engine that knows it (as the
  container runtime pins it: the id goes into lineage; the server's cache key uses it);
  otherwise its tag, as the cluster resolves it;
- the launch (:meth:`KubernetesRuntime.prepare`): the attempt's Pod and Secret manifests
  (``osmo.runtime.kubernetes.manifest``), the node's attempt folders shared with the pod
  through the pool's work volume, its output folder handed to the pod's uid;
- start, kill, reap, release: one local agent process per attempt
  (``osmo.runtime.kubernetes.agent``), which creates the pod and its Secret, streams the
  task's log as its own stdout, exits with the task's exit code and deletes the pod. A kill
  is SIGTERM to the agent (the pod is deleted with its 3 s grace, then forced); a forced
  kill SIGKILLs it and the runtime deletes the pod itself. ``reap`` reads the agent's
  verdict: a pod whose image could not be pulled fails to start, an evicted, preempted or
  lost pod is a lost attempt (``ProcessHandle.start_failed`` / ``lost``);
- clean-up: nothing is left after an attempt (the agent deletes the pod; the API's garbage
  collector its Secret); at start, :meth:`KubernetesRuntime.clean_orphans` deletes every pod
  of this instance a previous life left (found by label): the server reschedules those
  attempts, which the restarted node reported lost by not knowing them.

- port-forward: the node dials the pod's IP (:meth:`KubernetesRuntime.connector`); the
  node's session relays it over zenoh as on every node.

Not here yet: ``exec`` (the Kubernetes exec API relayed by the node), inputs fetched by an
init container and outputs taken by a sidecar (today the pod
sees the node's folders through the work volume, so the node's own checks and atomic
promotion hold unchanged).
"""

from __future__ import annotations

import json
import os
import sys
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from osmo.errors import OsmoError
from osmo.runtime.api import (
    Attempt,
    ConnectError,
    Connector,
    ExecCommand,
    Launch,
    Paths,
    ProcessHandle,
    Runtime,
    StartError,
    dial,
)
from osmo.runtime.container.engine import ContainerEngine, EngineNotFound, detect_engine
from osmo.runtime.container.images import ImageIds
from osmo.runtime.container.layout import DATA_LAYOUT, mounts
from osmo.runtime.kubernetes.config import KubePool, load_pool
from osmo.runtime.kubernetes.groups import Groups, hostname
from osmo.runtime.kubernetes.kube import Kube, KubeError, connect
from osmo.runtime.kubernetes.manifest import (
    LABEL_INSTANCE,
    GroupPlan,
    PodPlan,
    label_value,
    pod_manifest,
    secret_manifest,
)
from osmo.runtime.process.groups import ProcessGroups
from osmo.scheduler.types import PrepareAttempt

__all__ = ["KubeRun", "KubernetesRuntime", "attempt_plan"]

_AGENT = "osmo.runtime.kubernetes.agent"
_PACKAGE_ROOT = Path(__file__).resolve().parents[3]  # the agent imports this very osmo


@dataclass(frozen=True)
class KubeRun:
    """A prepared attempt's pod: its manifests, the agent's files, its gang (never shown)."""

    pod: dict[str, Any] = field(repr=False)
    secret: dict[str, Any] | None = field(repr=False)
    plan_file: Path
    verdict_file: Path
    group: GroupPlan | None = None

    @property
    def name(self) -> str:
        """The pod's name."""
        return str(self.pod["metadata"]["name"])


class KubernetesRuntime:
    """Attempts as pods (see the module docstring).

    Args:
        pool: the pool's configuration.
        kube: the API (the node's own calls: orphans, forced deletes).
        instance: this node's ``osmo.dev/instance`` label (``owner_id`` of its home).
        python: the interpreter that runs the agents.
    """

    def __init__(self, pool: KubePool, kube: Kube, *, instance: str,
                 images: ImageIds | None = None, python: str = sys.executable) -> None:
        self.pool, self.kube, self.instance = pool, kube, label_value(instance)
        self.images = images
        self._python = python
        self._groups = ProcessGroups()
        self.gangs = Groups(kube, pool, self.instance)
        self._runs: dict[ProcessHandle, KubeRun] = {}
        self._forced: set[ProcessHandle] = set()
        self._threads: set[threading.Thread] = set()
        self._lock = threading.Lock()
        self._env = dict(os.environ)
        self._env["PYTHONPATH"] = os.pathsep.join(
            [str(_PACKAGE_ROOT), *filter(None, [
                os.environ.get("PYTHONPATH")])])

    @classmethod
    def for_node(cls, config: str | None, *, instance: str) -> KubernetesRuntime:
        """The runtime of a node configured by the file ``config``, its orphans deleted.

        Raises:
            UsageError: the configuration is wrong.
            KubeError: the cluster cannot be reached.
        """
        pool = load_pool(config)
        kube = connect(pool.kubeconfig, pool.context)
        try:
            engine: ContainerEngine | None = ContainerEngine(detect_engine(None))
        except EngineNotFound:
            engine = None
        made = cls(pool, kube, instance=instance,
                   images=ImageIds(engine) if engine is not None else None)
        made.clean_orphans()
        return made

    def describe(self) -> str:
        """``kubernetes (namespace NS)``: what ``osmo pool list`` shows."""
        return f"kubernetes (namespace {self.pool.namespace})"

    def clean_orphans(self) -> list[str]:
        """Delete every pod and group Service of this instance (a previous life's).

        Returns ``kind/name`` of each. (A PodGroup left by a crash stays: it holds nothing.)
        """
        mine = f"{LABEL_INSTANCE}={self.instance}"
        names = []
        for kind in ("pod", "service"):
            items, _ = self.kube.list_objects(kind, self.pool.namespace, labels=mine)
            for item in items:
                name = str(item["metadata"]["name"])
                self.kube.delete(kind, self.pool.namespace, name,
                                 grace=0 if kind == "pod" else None)
                names.append(f"{kind}/{name}")
        return names

    def paths(self, cmd: PrepareAttempt) -> Paths:
        """OSMO's data layout (the container runtime's); ``{{host:NAME}}`` a group's pod."""
        hosts = self.gangs.hosts(cmd)
        return DATA_LAYOUT if hosts is None else replace(DATA_LAYOUT, hosts=hosts)

    def prepare(self, launch: Launch, attempt: Attempt, *,
                progress: Callable[[str], None]) -> Launch:
        """The launch with its pod's manifests; its output folder handed to the pod's uid.

        Raises:
            ManifestError: a value no manifest can hold (the message names it).
        """
        cmd, task, dirs = attempt.cmd, attempt.task, attempt.dirs
        assert task.image is not None, "the chooser gives the Kubernetes runtime image tasks"
        pinned = self.images.known(cmd.workflow_id, task.image) if self.images else None
        plan = attempt_plan(launch, attempt, instance=self.instance, image=pinned)
        group, lead, workdir = plan.group, plan.lead, plan.workdir
        secret = (secret_manifest(plan, launch.secret_env, self.pool, owner_uid="")
                  if launch.secret_env else None)
        pod = pod_manifest(plan, self.pool, secret=plan.name if secret else None)
        self._hand_over(dirs.output_partial, dirs.work if workdir else None)
        if group is not None:
            self.gangs.join(cmd, group)
        run = KubeRun(pod, secret, dirs.root / "pod.plan.json", dirs.root / "pod.verdict.json",
                      group)
        note = (f"pod {plan.name} in namespace {self.pool.namespace}, image '{task.image}'"
                + (f" is {pinned}" if pinned else ""))
        waits = group is not None and not lead and self.pool.gang == "none"
        return replace(launch, run=run, image_id=pinned, notes=(*launch.notes, note),
                       waits=waits)

    def start(self, launch: Launch) -> ProcessHandle:
        """Start the attempt's agent, which creates its pod.

        Raises:
            StartError: the agent cannot be started.
        """
        run = _run(launch)
        if launch.waits and run.group is not None:
            self.gangs.wait_for_lead(run.group)
        plan = {"pod": run.pod, "secret": run.secret, "verdict": str(run.verdict_file),
                "parent": os.getpid(),
                "kubeconfig": self.pool.kubeconfig, "context": self.pool.context}
        try:
            run.verdict_file.unlink(missing_ok=True)
            _write_private(run.plan_file, json.dumps(plan))
        except OSError as exc:
            raise StartError(f"cannot write the pod's plan: {exc}") from exc
        handle = self._groups.start([self._python, "-m", _AGENT, str(run.plan_file)],
                                    cwd=run.plan_file.parent, env=self._env)
        with self._lock:
            self._runs[handle] = run
        return handle

    def kill(self, handle: ProcessHandle, *, force: bool = False) -> None:
        """SIGTERM to the agent (it deletes the pod); ``force``: SIGKILL, the pod deleted here."""
        with self._lock:
            run = self._runs.get(handle)
            if force and run is not None:
                self._forced.add(handle)
        self._groups.kill(handle, force=force)
        if force and run is not None:
            self._later(self._delete, run.name)

    def reap(self, handle: ProcessHandle) -> int:
        """The task's exit code; a pod that never ran or was lost says so on the handle."""
        code = self._groups.reap(handle)
        with self._lock:
            run = self._runs.get(handle)
        if run is None:
            return code
        try:
            verdict = json.loads(run.verdict_file.read_text())
        except (OSError, ValueError):
            self._later(self._delete, run.name)  # the agent did not finish: the pod may stay
            return code
        message = str(verdict.get("message") or "")
        if verdict.get("outcome") == "start_failed":
            handle.start_failed = message or "the pod could not start"
        elif verdict.get("outcome") == "lost":
            handle.lost = message or "the pod was lost"
        return code

    def release(self, handle: ProcessHandle) -> None:
        """Close the handle; the agent's files go."""
        self._groups.release(handle)
        with self._lock:
            run = self._runs.pop(handle, None)
            self._forced.discard(handle)
        if run is not None:
            run.plan_file.unlink(missing_ok=True)
            run.verdict_file.unlink(missing_ok=True)

    def exec(self, launch: Launch, command: Sequence[str], *, tty: bool,
             term: str | None) -> ExecCommand:
        """Not yet: the Kubernetes exec API is not relayed (the node says so).

        Raises:
            OsmoError: always.
        """
        raise OsmoError("osmo workflow exec does not reach Kubernetes pods yet "
                        f"(pod {_run(launch).name}: use kubectl exec)")

    def connector(self, launch: Launch, handle: ProcessHandle) -> Connector:
        """To the task's ports on its pod's IP (the node dials it; the node's session relays).

        An in-cluster node reaches pod IPs directly, as every pod of a cluster does (unless
        a NetworkPolicy forbids it); it does not go through the API's port-forward.

        Raises:
            ConnectError: the pod has no IP (not running) or is gone.
            KubeError: the API cannot be asked.
        """
        name = _run(launch).name
        pod = self.kube.read_pod(self.pool.namespace, name)
        address = str(((pod or {}).get("status") or {}).get("podIP") or "")
        if not address:
            raise ConnectError(f"pod {name} has no IP (it is not running)")
        return lambda port, udp: dial(address, port, udp=udp)

    def cleanup(self, launch: Launch) -> None:
        """Its group's objects go with the group's last member here (in the background).

        The pod itself was deleted by its agent (a forced kill's by ``kill``).
        """
        run = launch.run
        if isinstance(run, KubeRun) and run.group is not None:
            self._later(self.gangs.leave, run.group)

    def close(self) -> None:
        """Wait for the deletions still under way; let go of the API."""
        while True:
            with self._lock:
                threads = list(self._threads)
            if not threads:
                break
            for thread in threads:
                thread.join()
        self.kube.close()

    # ------------------------------------------------------------ internals

    def _hand_over(self, *folders: Path | None) -> None:
        """Let the pod's uid write the attempt's output (and working) folder.

        As root, the folders become the pod's uid's; otherwise pods run as this uid
        (``runAsUser`` must then be it).
        """
        if os.geteuid() != 0 or self.pool.security_context is not None:
            return
        for folder in folders:
            if folder is not None:
                os.chown(folder, self.pool.run_as_user, self.pool.run_as_user)

    def _delete(self, name: str) -> None:
        try:
            self.kube.delete("pod", self.pool.namespace, name, grace=0)
        except KubeError:
            pass  # the next start deletes what is left by label

    def _later(self, fn: Callable[..., object], *args: object) -> None:
        def run() -> None:
            try:
                fn(*args)
            finally:
                with self._lock:
                    self._threads.discard(thread)

        thread = threading.Thread(target=run, name="osmo-kube-call", daemon=True)
        with self._lock:
            self._threads.add(thread)
        thread.start()


def attempt_plan(launch: Launch, attempt: Attempt, *, instance: str,
                 image: str | None = None) -> PodPlan:
    """What the pod of a prepared attempt is made of (pure; ``image``: its pinned form).

    ``osmo.worker.pods`` uses it too, to show a spec's pods without a cluster.
    """
    cmd, task, request = attempt.cmd, attempt.task, attempt.resources
    assert task.image is not None, "only image tasks run as pods"
    binds, workdir = mounts(attempt.dirs, launch.files, launch.inputs)
    group = Groups.of(cmd)
    return PodPlan(
        attempt_id=cmd.attempt_id, workflow_id=cmd.workflow_id, task=cmd.task,
        retry=cmd.retry, instance=instance, image=image or task.image, argv=launch.argv,
        env=dict(launch.env), secret_env=tuple(sorted(launch.secret_env)), mounts=binds,
        workdir=workdir, cpu=float(request.cpu or 0) or None, memory=request.memory,
        gpus=request.gpu or 0, storage=request.storage, platform=request.platform,
        group=group, hostname=hostname(cmd.task) if group else None,
        lead=task.lead or next(iter(cmd.hosts), cmd.task) == cmd.task)


def _run(launch: Launch) -> KubeRun:
    run = launch.run
    if not isinstance(run, KubeRun):
        raise TypeError(f"{launch!r} was not prepared by the Kubernetes runtime")
    return run


def _write_private(path: Path, text: str) -> None:
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW | os.O_CLOEXEC
    fd = os.open(path, flags, 0o600)
    try:
        os.fchmod(fd, 0o600)
        os.write(fd, text.encode())
    finally:
        os.close(fd)


def _conforms(runtime: KubernetesRuntime) -> Runtime:
    """Never called: mypy checks here that KubernetesRuntime keeps the runtime contract."""
    return runtime


