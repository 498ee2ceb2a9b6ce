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
- start, kill, reap, release: a thread per attempt follows its pod
  (``osmo.runtime.kubernetes.follow``: creates the pod and its Secret, follows its versions
  through the node's one watch of its pods (``osmo.runtime.kubernetes.podwatch``, by the
  instance label), streams its log, deletes it) and writes the log into the handle's
  pipes; the handle's process is a sleeping sentinel (its pid and pidfd are what the pool
  watches and records), killed when the pod's life is over, so the handle's exit
  descriptor becomes readable then. No Python process per attempt: a node follows
  hundreds of pods at the cost of threads (one watch for them all). A kill
  deletes the pod with its 3 s grace (forced: at once). ``reap`` reads the verdict: a pod
  whose image could not be pulled fails to start, an evicted, preempted or lost pod is a
  lost attempt (``ProcessHandle.start_failed`` / ``lost``);
- clean-up: nothing is left after an attempt (the follower deletes the pod; the API's
  garbage collector its Secret). A node that dies leaves its pods running: its pods outlive
  it (``osmo.runtime.api.Adopting``). Each attempt's pod name and group are kept in its
  folder (``pod.json``); a restarted node adopts a journaled attempt's pod
  (:meth:`KubernetesRuntime.adopt`: followed again, its log resumed after what was sent;
  only a pod carrying this node's instance label), then
  :meth:`KubernetesRuntime.cancel_orphans` deletes every other pod, Secret, group Service
  and PodGroup of this instance (by label), and a whole group's pods when one of its
  members was not adopted (:meth:`KubernetesRuntime.clean_orphans`: all of them). A pod
  with its own data is adopted too (:meth:`KubernetesRuntime._serve_again`): its
  collector's ticket digest is in ``pod.json`` and must give the pod's annotation
  (``podio.ticket_seal``). What a node down for good left is deleted by another node of
  the pool when the server orders it (:meth:`KubernetesRuntime.sweep`).

- exec: the Kubernetes exec API (a WebSocket), held by a relay process the node spawns
  (``osmo.runtime.kubernetes.exec_relay``); port-forward: the API's port-forward (a
  WebSocket per connection, :meth:`KubernetesRuntime.connector`); the node's session relays
  both over zenoh as on every node.

- data: with the pool's ``data`` (osmo's image), the pod shares no volume with the node:
  ``prepare`` lists and hashes what the task must find (``podio.scan_mounts``), opens the
  attempt on the node's pod-data API (:meth:`KubernetesRuntime.serve_pod_data`) and puts
  its two one-time tickets in the attempt's Secret; the pod's init container fetches, its
  collector sends the output back once the node saw the task's container end, and the
  follower hands the verdict on only after that (``_data_end``): a collection that failed
  is ``ProcessHandle.output_failed``, so nothing is promoted. Without ``data``, the pod sees
  the node's folders through the work volume (claim or hostPath).
"""

from __future__ import annotations

import hmac
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import IO, Any

from osmo.config import read_json_private, write_json_atomic
from osmo.errors import OsmoError, UsageError
from osmo.layout import AttemptDirs
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
)
from osmo.runtime.background import Background
from osmo.runtime.container.engine import ContainerEngine, EngineNotFound, detect_engine
from osmo.runtime.container.images import ImageIds, registry_auth
from osmo.runtime.container.layout import DATA_LAYOUT, mounts
from osmo.runtime.kubernetes.capacity import Capacity, platform_capacity
from osmo.runtime.kubernetes.config import KubePool, load_pool
from osmo.runtime.kubernetes.follow import PodFollower
from osmo.runtime.kubernetes.groups import Groups, hostname
from osmo.runtime.kubernetes.kube import Kube, KubeError, connect
from osmo.runtime.kubernetes.manifest import (
    ATTEMPT_ID,
    COLLECTOR,
    CONTAINER,
    FETCHER,
    LABEL_ATTEMPT,
    LABEL_GROUP,
    LABEL_INSTANCE,
    POD_GROUPS,
    TICKET_DIR,
    TICKETS,
    ZENOH_CONFIG,
    ZENOH_KEY,
    DataPlan,
    GroupPlan,
    PodPlan,
    in_volume,
    label_value,
    pod_manifest,
    secret_manifest,
)
from osmo.runtime.kubernetes.podio import COLLECT, SEALED, PodData, scan_mounts, ticket_seal
from osmo.runtime.kubernetes.podwatch import PodWatch
from osmo.runtime.kubernetes.status import Outcome, Verdict
from osmo.runtime.process.groups import die_with_parent
from osmo.scheduler.types import PrepareAttempt
from osmo.transport.auth import token_digest
from osmo.transport.zenoh_link import Link, client_credentials

__all__ = ["KubeRun", "KubernetesRuntime", "attempt_plan"]

START_FAILED = 125
"""The exit code reported for a pod that never ran its task (with ``start_failed``)."""
LOST = 3
"""The exit code reported for a lost pod (with ``lost``)."""
KILLED = 137
"""The exit code of an attempt reaped before its pod ended."""
_RELAY = "osmo.runtime.kubernetes.exec_relay"
_PACKAGE_ROOT = Path(__file__).resolve().parents[3]  # the relay imports this very osmo
_SLEEP = [shutil.which("sleep") or "sleep", "2147483647"]  # the sentinel: waits to be killed
_OBJECT_NAME = re.compile(r"[a-z0-9]([-a-z0-9]{0,61}[a-z0-9])?")
_DIGEST = re.compile(r"[0-9a-f]{64}")
_COLLECT_WAIT = 600.0  # seconds a collector may take to send an ended task's output back


@dataclass(frozen=True)
class KubeRun:
    """A prepared attempt's pod: its manifests and its gang (never shown)."""

    pod: dict[str, Any] = field(repr=False)
    secret: dict[str, Any] | None = field(repr=False)
    group: GroupPlan | None = None
    waiting: Callable[[str], None] = field(default=lambda _reason: None, repr=False)
    data: str | None = None  # the attempt id, when the pod fetches its own data

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
        images: the node's container engine's image ids (pins images), if it has one.
    """

    def __init__(self, pool: KubePool, kube: Kube, *, instance: str,
                 images: ImageIds | None = None) -> None:
        self.pool, self.kube, self.instance = pool, kube, label_value(instance)
        self.images = images
        self.gangs = Groups(kube, pool, self.instance)
        self.watch = PodWatch(kube, pool.namespace, labels=f"{LABEL_INSTANCE}={self.instance}")
        self._runs: dict[ProcessHandle, _Live] = {}
        self._background = Background("osmo-kube-call")
        self._followers = Background("osmo-pod")  # one per started attempt, until its pod went
        self._lock = threading.Lock()
        self.pod_data: PodData | None = None
        self._data: DataPlan | None = None
        self._data_zenoh: dict[str, str] = {}  # Secret key → what the data containers show

    def serve_pod_data(self, link: Link, node: str, connect: Sequence[str],
                       cluster: str, *, config_file: str | None = None) -> None:
        """Serve the pods' own data (the pool's ``data``) on ``link`` as node ``node``.

        Its pods dial the pool's ``data.connect``, else ``connect`` (the worker's own), with
        the user and certificates of the pool's ``data.zenohConfig`` (read once, here).
        Without ``data`` in the pool, nothing is served: pods use the work volume.

        Raises:
            UsageError: ``data.zenohConfig``, or a file it names, cannot be read; or there is
                none while the pods would dial the worker's own endpoints, which the worker
                reaches only with a user or TLS (``config_file``): they could not connect.
        """
        if self.pool.data_image is None:
            return
        if (self.pool.data_zenoh_config is None and not self.pool.data_connect
                and config_file and json.loads(client_credentials(config_file, "")[0])[
                    "transport"]):
            raise UsageError(
                f"the pool's pods fetch their own data from the router this worker dials "
                f"with a user or TLS ({config_file}), and would have neither: give the "
                "pool's data a zenohConfig, a zenoh client config with a user of the pods' "
                "own that the router confines to podio/** (the chart's auth.podUser), or "
                "the pool a work volume instead of data")
        files: dict[str, str] = {}
        if self.pool.data_zenoh_config is not None:
            config, files = client_credentials(self.pool.data_zenoh_config, TICKET_DIR)
            files[ZENOH_CONFIG] = config
        self._data_zenoh = {ZENOH_KEY + name: text for name, text in files.items()}
        self.pod_data = PodData(link, node)
        self._data = DataPlan(self.pool.data_image, tuple(self.pool.data_connect or connect),
                              cluster, node, zenoh_files=tuple(sorted(files)))

    @classmethod
    def for_node(cls, config: str | None, *, instance: str) -> KubernetesRuntime:
        """The runtime of a node configured by the file ``config``.

        What a previous life of the node left is the node's to adopt or delete
        (:meth:`adopt`, :meth:`cancel_orphans`).

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
        return cls(pool, kube, instance=instance,
                   images=ImageIds(engine) if engine is not None else None)

    def describe(self) -> str:
        """``kubernetes (namespace NS)``: what ``osmo pool list`` shows."""
        return f"kubernetes (namespace {self.pool.namespace})"

    def platforms(self) -> dict[str, Capacity]:
        """The pool's platforms some Ready node can take, each with its nodes' allocatable.

        (``capacity.platform_capacity``.) The worker registers them all, each with its
        capacity (``wire.Hello``): the server places a task with ``platform:`` only where
        its platform has room.

        Raises:
            KubeError: the nodes cannot be listed.
        """
        return platform_capacity(self.kube, self.pool)

    def adopted(self) -> set[str]:
        """The pods it follows (adopted ones among them)."""
        with self._lock:
            return {live.run.name for live in self._runs.values()}

    def adopt(self, dirs: AttemptDirs, shipped: Mapping[str, int]
              ) -> tuple[Launch, ProcessHandle]:
        """Follow again the pod a previous life of the node created for ``dirs``.

        Its log resumes after ``shipped["stdout"]`` bytes.

        Raises:
            OsmoError: no pod was recorded there, the record is not valid, the pod is gone
                or is not this node's (another instance label), or it is a pod with its own
                data that cannot be served again (:meth:`_serve_again` says why).
        """
        try:
            meta = read_json_private(dirs.root / "pod.json")
        except (OSError, ValueError) as exc:
            raise OsmoError(f"no pod to adopt in {dirs.root}: {exc}") from exc
        name, group = meta.get("name"), meta.get("group")
        own = _own_data(meta.get("data"), name)
        if not isinstance(name, str) or not _OBJECT_NAME.fullmatch(name):
            raise OsmoError(f"{dirs.root}/pod.json names no pod")
        plan = None
        if group is not None:
            if not (isinstance(group, dict) and isinstance(group.get("name"), str)
                    and _OBJECT_NAME.fullmatch(group["name"])
                    and type(group.get("size")) is int and group["size"] > 1):
                raise OsmoError(f"{dirs.root}/pod.json names no valid group")
            plan = GroupPlan(group["name"], group["size"])
        pod = self.kube.read_pod(self.pool.namespace, name)
        if pod is None:
            raise OsmoError(f"pod {name} is gone")
        if ((pod.get("metadata") or {}).get("labels") or {}).get(LABEL_INSTANCE) \
                != self.instance:
            raise OsmoError(f"pod {name} is not this node's")
        attempt = None if own is None else self._serve_again(pod, own, dirs.output_partial)
        run = KubeRun(pod, None, plan, data=attempt)
        if plan is not None:
            self.gangs.adopt(plan)
        handle, live = self._sentinel(run)
        follower = PodFollower(self.kube, pod, None, out=live.out, note=live.note,
                               stop=live.stop, force=live.force, adopted=pod,
                               skip=max(0, int(shipped.get("stdout", 0))), watch=self.watch,
                               on_end=None if attempt is None else (
                                   lambda found: self._data_end(live, found)))
        with self._lock:
            self._runs[handle] = live
        self._followers.later(self._follow, follower, live, handle)
        return Launch((), dirs.work, {}, run=run), handle

    def cancel_orphans(self, keep: Sequence[str] = ()) -> list[str]:
        """Delete what of this instance a previous life left but the pods in ``keep``.

        A group with a member not kept is deleted whole. Nothing kept: :meth:`clean_orphans`.
        Returns ``kind/name`` of each object deleted.
        """
        if not keep:
            return self.clean_orphans()
        mine = f"{LABEL_INSTANCE}={self.instance}"
        namespace = self.pool.namespace
        pods, _ = self.kube.list_objects("pod", namespace, labels=mine)
        labels = {str(p["metadata"]["name"]): (p["metadata"].get("labels") or {}) for p in pods}
        broken = {lb.get(LABEL_GROUP) for name, lb in labels.items() if name not in keep}
        kept = {name: lb for name, lb in labels.items()
                if name in keep and lb.get(LABEL_GROUP) not in broken}
        names = [f"pod/{name}" for name in labels if name not in kept
                 and self.kube.delete("pod", namespace, name, grace=0)]
        attempts = sorted({lb[LABEL_ATTEMPT] for lb in kept.values() if LABEL_ATTEMPT in lb})
        groups = sorted({lb[LABEL_GROUP] for lb in kept.values() if LABEL_GROUP in lb})
        secrets = mine + (f",{LABEL_ATTEMPT} notin ({','.join(attempts)})" if attempts else "")
        others = mine + (f",{LABEL_GROUP} notin ({','.join(groups)})" if groups else "")
        names += [f"secret/{n}" for n in self.kube.delete_labelled("secret", namespace,
                                                                   secrets)]
        names += [f"service/{n}" for n in self.kube.delete_labelled("service", namespace,
                                                                    others)]
        return names + self._delete_pod_groups(others)

    def clean_orphans(self) -> list[str]:
        """Delete everything of this instance a previous life left (found by its label).

        Its pods (at once), then every Secret (an attempt's, or a pull Secret made before a
        pod that never came), group Service and PodGroup of the instance: one
        ``deletecollection`` per kind, so the node never lists (reads) a Secret. PodGroups
        of every gang scheduler go (the pool's choice may have changed); a kind the API does
        not serve (404) or the node may not delete (403: not the pool's gang) is passed by.

        Returns ``kind/name`` of each object deleted.
        """
        return self._delete_instance(self.instance)

    def sweep(self, instance: str) -> list[str]:
        """Delete what another node of the pool, down for good, left (labelled ``instance``).

        Only the server orders it (``wire.Sweep``: that node's grace ended and the server no
        longer holds its attempts); this node's own instance, or a value that is no label
        value, is refused. Returns ``kind/name`` of each object deleted.

        Raises:
            OsmoError: ``instance`` is refused.
            KubeError: the API refused a call.
        """
        if instance == self.instance or not instance or label_value(instance) != instance:
            raise OsmoError(f"refused to sweep instance {instance[:80]!r}: not another "
                            "node's label value")
        return self._delete_instance(instance)

    def _delete_instance(self, instance: str) -> list[str]:
        """Delete every pod, Secret, Service and PodGroup labelled with ``instance``."""
        mine = f"{LABEL_INSTANCE}={instance}"
        namespace = self.pool.namespace
        pods, _ = self.kube.list_objects("pod", namespace, labels=mine)
        names = []
        for pod in pods:
            name = str(pod["metadata"]["name"])
            if self.kube.delete("pod", namespace, name, grace=0):
                names.append(f"pod/{name}")
        for kind in ("secret", "service"):
            names += [f"{kind}/{n}" for n in self.kube.delete_labelled(kind, namespace, mine)]
        return names + self._delete_pod_groups(mine)

    def _delete_pod_groups(self, selector: str) -> list[str]:
        """Delete the PodGroups ``selector`` picks, of every gang scheduler's kind.

        A kind the API does not serve (404) or the node may not delete (403: not the pool's
        gang) is passed by. Returns ``kind/name`` of each deleted.
        """
        names = []
        for gang, kind_of in POD_GROUPS.items():
            try:
                gone = self.kube.delete_labelled(kind_of, self.pool.namespace, selector)
            except KubeError as exc:
                if exc.status in (403, 404, 405) and gang != self.pool.gang:
                    continue
                raise
            names += [f"{kind_of[2]}.{kind_of[0]}/{n}" for n in gone]
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
        registry = registry_auth(task.image, attempt.credential)
        own = self._data is not None
        pod = pod_manifest(plan, self.pool,
                           secret=plan.name if launch.secret_env or registry or own else None,
                           pulls_with_secret=registry is not None, data=self._data)
        values = dict(launch.secret_env)
        data: dict[str, Any] | None = None
        if own:
            values.update(self._data_zenoh)
            tickets = self._open_data(plan, launch, dirs.output_partial)
            values.update({TICKETS[role]: token for role, token in tickets.items()})
            # what a restarted node serves its collector again by (never the ticket itself)
            data = {"collect": token_digest(tickets[COLLECT]),
                    "max_bytes": launch.max_output_bytes}
            pod["metadata"].setdefault("annotations", {})[SEALED] = ticket_seal(
                plan.attempt_id, data["collect"])
        else:
            self._hand_over(dirs.output_partial, dirs.work if workdir else None)
        secret = (secret_manifest(plan, values, self.pool, owner_uid="", registry=registry)
                  if values or registry else None)
        # what a restarted node adopts the pod by (``adopt``); private (0600): the digest
        # opens the collector's channel
        write_json_atomic(dirs.root / "pod.json", {
            "name": plan.name, "data": data, "group": None if group is None else {
                "name": group.name, "size": group.size}})
        if group is not None:
            self.gangs.join(cmd, group)
        run = KubeRun(pod, secret, group, attempt.waiting, cmd.attempt_id if own else None)
        note = (f"pod {plan.name} in namespace {self.pool.namespace}, image '{task.image}'"
                + (f" is {pinned}" if pinned else ""))
        waits = group is not None and not lead and self.pool.gang == "none"
        return replace(launch, run=run, image_id=pinned, notes=(*launch.notes, note),
                       waits=waits)

    def start(self, launch: Launch) -> ProcessHandle:
        """Start following the attempt's pod (a thread here) and its sentinel process.

        Raises:
            StartError: the sentinel or the pipes cannot be made.
        """
        run = _run(launch)
        if launch.waits and run.group is not None:
            self.gangs.wait_for_lead(run.group)
        handle, live = self._sentinel(run)
        follower = PodFollower(self.kube, run.pod, run.secret, out=live.out,
                               note=live.note, stop=live.stop, force=live.force,
                               waiting=run.waiting, watch=self.watch,
                               on_end=None if run.data is None else (
                                   lambda found: self._data_end(live, found)))
        with self._lock:
            self._runs[handle] = live
        self._followers.later(self._follow, follower, live, handle)
        return handle

    def kill(self, handle: ProcessHandle, *, force: bool = False) -> None:
        """Delete the pod with its 3 s grace (``force``: at once); never raises."""
        with self._lock:
            live = self._runs.get(handle)
        if live is None:
            return
        live.stop.set()
        if force:
            live.force.set()

    def reap(self, handle: ProcessHandle) -> int:
        """The task's exit code; a pod that never ran or was lost says so on the handle.

        Reaped before its end (the pool closing): the pod is deleted at once, in the
        background, and the attempt counts as killed (137).
        """
        with self._lock:
            live = self._runs.get(handle)
        if live is not None and live.verdict is None:
            live.stop.set()
            live.force.set()
        _end_sentinel(handle)
        handle.popen.wait()
        found = live.verdict if live is not None else None
        if found is None:
            return KILLED
        if found.outcome is Outcome.START_FAILED:
            handle.start_failed = found.message or "the pod could not start"
            return START_FAILED
        if found.outcome is Outcome.LOST:
            handle.lost = found.message or "the pod was lost"
            return LOST
        if live is not None:
            handle.output_failed = live.output_failed
        return found.exit_code if found.exit_code is not None else 1

    def release(self, handle: ProcessHandle) -> None:
        """Close the handle's descriptors (idempotent)."""
        with self._lock:
            self._runs.pop(handle, None)
        for fd in (handle.stdout_fd, handle.stderr_fd, handle.exit_fd):
            if fd >= 0:
                os.close(fd)
        handle.stdout_fd = handle.stderr_fd = handle.exit_fd = -1

    def exec(self, launch: Launch, command: Sequence[str], *, tty: bool,
             term: str | None) -> ExecCommand:
        """``command`` in the pod's task container, through the API's exec.

        The node spawns a relay (``osmo.runtime.kubernetes.exec_relay``) that holds the
        exec's WebSocket; with a TTY, ``TERM`` is set for the command.
        """
        argv = list(command)
        if tty and term:
            argv = ["env", f"TERM={term}", *argv]
        spec = {"kubeconfig": self.pool.kubeconfig, "context": self.pool.context,
                "namespace": self.pool.namespace, "pod": _run(launch).name,
                "container": CONTAINER, "command": argv, "tty": tty}
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(_PACKAGE_ROOT),
                                                          env.get("PYTHONPATH")]))
        return ExecCommand([sys.executable, "-m", _RELAY, json.dumps(spec)], launch.cwd, env,
                           ctty=tty)

    def connector(self, launch: Launch, handle: ProcessHandle) -> Connector:
        """To the task's TCP ports through the API's port-forward (the node's session relays).

        Each connection is a port-forward of its own (``Kube.port_forward``), so the node
        needs nothing but the API: no route to pod IPs, whatever the NetworkPolicies, and the
        Role's ``pods/portforward``. UDP is refused: the API forwards TCP only.

        Raises:
            ConnectError: the pod is gone or not running, or the API cannot be asked.
        """
        name = _run(launch).name
        try:
            pod = self.kube.read_pod(self.pool.namespace, name)
        except KubeError as exc:
            raise ConnectError(f"pod {name}: {exc}") from None
        phase = ((pod or {}).get("status") or {}).get("phase")
        if phase != "Running":
            raise ConnectError(f"pod {name} is not running ({phase or 'gone'})")

        def connect(port: int, udp: bool) -> socket.socket:
            if udp:
                raise ConnectError("the Kubernetes API forwards TCP only, not UDP")
            try:
                return self.kube.port_forward(self.pool.namespace, name, port)
            except KubeError as exc:
                raise ConnectError(f"cannot forward port {port} of pod {name}: {exc}"
                                   ) from None
        return connect

    def cleanup(self, launch: Launch) -> None:
        """Its group's objects go with the group's last member here (in the background).

        The pod itself was deleted by its follower.
        """
        run = launch.run
        if isinstance(run, KubeRun) and run.data is not None and self.pod_data is not None:
            self.pod_data.close(run.data)
        if isinstance(run, KubeRun) and run.group is not None:
            self._background.later(self.gangs.leave, run.group)

    def close(self) -> None:
        """Wait for the followers (pods still being deleted), the group objects; close the API.

        A follower ends at most ``follow.GIVE_UP_AFTER`` seconds after its kill.
        """
        self._followers.close()
        self._background.close()
        if self.pod_data is not None:
            self.pod_data.stop()
        self.kube.close()

    # ------------------------------------------------------------ internals

    def _open_data(self, plan: PodPlan, launch: Launch, output: Path) -> dict[str, str]:
        """Open the attempt on the pod-data API; its tickets (role → token)."""
        assert self.pod_data is not None
        sources = [(m.source, in_volume(m.target)) for m in plan.mounts
                   if m.target != DATA_LAYOUT.output]
        files, folders = scan_mounts(sources)
        folders.append(in_volume(str(DATA_LAYOUT.output)))
        return self.pod_data.open(plan.attempt_id, files, folders, output,
                                  max_bytes=launch.max_output_bytes)

    def _serve_again(self, pod: dict[str, Any], own: _OwnData, output: Path) -> str:
        """Serve an adopted data pod's collector again; its attempt id.

        Only a pod whose init container fetched its data and whose collector still runs
        (waits for the task's end, or is sending: it sends again, whole, into an emptied
        ``output``), and whose annotation the journaled ticket digest gives
        (``podio.ticket_seal``): a record altered, or another attempt's, is refused.

        Raises:
            OsmoError: the pod cannot be adopted (the message says why).
        """
        name = str(pod["metadata"]["name"])
        if self.pod_data is None:
            raise OsmoError(f"pod {name} fetches its own data, but this node's pool has no "
                            "'data' any more")
        notes = pod["metadata"].get("annotations") or {}
        attempt = notes.get(ATTEMPT_ID)
        if not isinstance(attempt, str) or not hmac.compare_digest(
                ticket_seal(attempt, own.collect), str(notes.get(SEALED) or "")):
            raise OsmoError(f"pod {name}: its journaled tickets are not its own (altered, or "
                            "another attempt's)")
        states = _states(pod)
        fetched = (states.get(FETCHER) or {}).get("terminated") or {}
        if fetched.get("exitCode") != 0:
            raise OsmoError(f"pod {name} had not fetched its data (it starts again)")
        if "terminated" in (states.get(COLLECTOR) or {}):
            raise OsmoError(f"pod {name}'s collector ended while the node was away")
        _empty(output)
        self.pod_data.reopen(attempt, own.collect, output, max_bytes=own.max_bytes)
        return attempt

    def _data_end(self, live: _Live, found: Verdict) -> Verdict:
        """The pod's task ended: wait for its collector (a task that exited), or let go.

        An init container that gave up says why (its own report beats the API's reason).
        """
        assert self.pod_data is not None and live.run.data is not None
        attempt = live.run.data
        exited = found.outcome is Outcome.EXITED and not live.stop.is_set()
        self.pod_data.ended(attempt, collect=exited)
        if exited:
            live.output_failed = self.pod_data.collected(attempt, _COLLECT_WAIT)
        if found.outcome is Outcome.START_FAILED and found.row == "init-failed":
            why = self.pod_data.fetch_failure(attempt) or self._fetch_log(live.run)
            if why:
                return Verdict(found.outcome, f"{found.message}: {why}", found.exit_code,
                               found.row)
        return found

    def _fetch_log(self, run: KubeRun) -> str:
        """The last line the pod's init container wrote (what it said when it gave up)."""
        try:
            text = b"".join(self.kube.logs(self.pool.namespace, run.name, FETCHER,
                                           follow=False)).decode("utf-8", "replace")
        except KubeError:
            return ""
        lines = [line for line in text.splitlines() if line.strip()]
        return lines[-1][:1000] if lines else ""

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

    def _sentinel(self, run: KubeRun) -> tuple[ProcessHandle, _Live]:
        """The handle: a sleeping local process (its pid, its pidfd) and the log's pipes."""
        fds: list[int] = []
        try:
            out_r, out_w = os.pipe2(os.O_CLOEXEC)
            fds += [out_r, out_w]
            err_r, err_w = os.pipe2(os.O_CLOEXEC)
            fds += [err_r, err_w]
            popen = subprocess.Popen(_SLEEP, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL, start_new_session=True,
                                     preexec_fn=die_with_parent())
        except OSError as exc:
            for fd in fds:
                os.close(fd)
            raise StartError(f"cannot follow pod {run.name}: {exc.strerror or exc}") from exc
        started = time.time()
        os.set_blocking(out_r, False)
        os.set_blocking(err_r, False)
        handle = ProcessHandle(popen.pid, os.pidfd_open(popen.pid), out_r, err_r, popen,
                               started_at=started)
        return handle, _Live(run, os.fdopen(out_w, "wb", buffering=0),
                             os.fdopen(err_w, "wb", buffering=0))

    def _follow(self, follower: PodFollower, live: _Live, handle: ProcessHandle) -> None:
        """The attempt's thread: the pod's life, then its verdict and the handle's end.

        The handle ends with the verdict; the pod's deletion follows on this thread.
        """
        def ended(verdict: Verdict) -> None:
            live.verdict = verdict
            live.close()
            _end_sentinel(handle)

        try:
            live.verdict = follower.run(ended)
        except KubeError as exc:
            live.note(str(exc))
            live.verdict = Verdict(Outcome.START_FAILED, str(exc))
        except Exception as exc:  # noqa: BLE001 - a bug: the attempt fails, the node goes on
            live.note(f"following the pod failed: {exc!r}")
            live.verdict = Verdict(Outcome.START_FAILED, f"following the pod failed: {exc!r}")
        finally:
            live.close()
            _end_sentinel(handle)


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
        lead=task.lead or next(iter(cmd.hosts), cmd.task) == cmd.task,
        priority=attempt.terms.priority)


@dataclass(eq=False)
class _Live:
    """A started attempt: its pod, the write ends of its log pipes, its kill and verdict."""

    run: KubeRun
    out: IO[bytes]
    err: IO[bytes]
    stop: threading.Event = field(default_factory=threading.Event)
    force: threading.Event = field(default_factory=threading.Event)
    verdict: Verdict | None = None
    output_failed: str | None = None  # why the pod's output did not come back whole

    def note(self, line: str) -> None:
        """An osmo line about the pod, on the task's stderr."""
        try:
            self.err.write(f"osmo: {line}\n".encode())
        except OSError:
            pass  # the pool let go of the attempt

    def close(self) -> None:
        """The log ends: close the write ends."""
        for pipe in (self.out, self.err):
            try:
                pipe.close()
            except OSError:
                pass


@dataclass(frozen=True)
class _OwnData:
    """A data pod's record in ``pod.json``: its collector's ticket digest, its output limit."""

    collect: str
    max_bytes: int | None


def _own_data(data: object, name: object) -> _OwnData | None:
    """The data pod record ``data`` of ``pod.json`` (None: the pod shares the node's volume).

    Raises:
        OsmoError: the record is not one (an older node's ``true``: not adopted).
    """
    if data is None or data is False:
        return None
    if not isinstance(data, dict):
        raise OsmoError(f"pod {name!r} sends its own data back but its tickets were not "
                        "journaled: not adopted (it runs again)")
    collect, limit = data.get("collect"), data.get("max_bytes")
    if not isinstance(collect, str) or not _DIGEST.fullmatch(collect) or not (
            limit is None or (type(limit) is int and limit >= 0)):
        raise OsmoError(f"pod {name!r}: its journaled tickets are not valid: not adopted")
    return _OwnData(collect, limit)


def _states(pod: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Each container's (init containers' too) state, by its name, as the API has it."""
    status = pod.get("status") or {}
    return {str(entry.get("name")): entry.get("state") or {}
            for key in ("initContainerStatuses", "containerStatuses")
            for entry in status.get(key) or []}


def _empty(folder: Path) -> None:
    """Remove what ``folder`` holds (the node's own folder: nothing followed)."""
    for child in folder.iterdir():
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child)
        else:
            child.unlink()


def _end_sentinel(handle: ProcessHandle) -> None:
    """The attempt ended: its sentinel goes, so the handle's exit descriptor is readable."""
    if handle.popen.returncode is None:
        try:
            os.killpg(handle.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


def _run(launch: Launch) -> KubeRun:
    run = launch.run
    if not isinstance(run, KubeRun):
        raise TypeError(f"{launch!r} was not prepared by the Kubernetes runtime")
    return run


def _conforms(runtime: KubernetesRuntime) -> Runtime:
    """Never called: mypy checks here that KubernetesRuntime keeps the runtime contract."""
    return runtime


