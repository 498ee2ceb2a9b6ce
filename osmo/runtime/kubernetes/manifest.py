"""The manifests of one attempt: its Pod, its Secret, its group's Service (pure: sends nothing).

:func:`pod_manifest` turns a :class:`PodPlan` (what the runtime resolved for the attempt)
and its pool's :class:`~osmo.runtime.kubernetes.config.KubePool` into a core/v1 Pod as a
plain dict; :func:`secret_manifest` makes the attempt's own Secret, owned by its pod (the API
server's garbage collector deletes it with the pod); :func:`service_manifest` a group's
headless Service. What each pod gets:

- ``restartPolicy: Never``; ``shareProcessNamespace``, so the task is not PID 1 (the pod's
  pause process is, as ``--init`` is a container task's): a SIGTERM the task does not
  handle ends it (143), as on every other runtime; one container ``task`` running the
  task's ``command``/``args`` (the image's entrypoint replaced, as OSMO does), its
  environment, its working folder;
- OSMO's data layout (``osmo.runtime.container.layout``): the same binds as a container
  task. With a :class:`DataPlan` (the pool names osmo's image), each is a ``subPath`` of
  the pod's own ``emptyDir`` (at its absolute path: ``osmo/data/input/0``, ``etc/x.cfg``),
  filled before the task starts by the init container ``osmo-fetch`` and sent back after it
  ended by the container ``osmo-collect``, both of osmo's image, both mounting the
  attempt's Secret (their one-time tickets) that the task's container never mounts
  (``osmo.runtime.kubernetes.podio``). Otherwise each is a volume of the node's attempt
  folder (a ``hostPath``, or a ``subPath`` of the pool's work claim);
- credential variables from its Secret (``secretKeyRef``), never as literal values; the
  image's registry credentials (osmo's stored ``registry:HOST`` credential) in that same
  Secret as a ``.dockerconfigjson``, named in ``imagePullSecrets``;
- ``resources``: cpu and memory as requests and limits, ``nvidia.com/gpu`` and
  ``ephemeral-storage`` (the task's ``storage``) as limits, and a memory ``/dev/shm`` of the
  pool's ``shmSize`` for a GPU task;
- the pool's node selector and tolerations, the platform's added; the PriorityClass; the
  gang scheduler's group markers;
- never privileged: the pool's securityContext, by default a non-root uid, every capability
  dropped, no privilege escalation, the runtime's default seccomp profile; no service
  account token, no service links;
- labels: ``osmo.dev/instance``, ``osmo.dev/workflow``, ``osmo.dev/task``,
  ``osmo.dev/retry``, ``osmo.dev/attempt``: label values are made safe
  (:func:`label_value`), so no task or workflow name can break a manifest.

Names (:func:`object_name`) are DNS-1123 labels derived from the attempt id with a digest of
it, unique per attempt.
"""

from __future__ import annotations

import base64
import hashlib
import json
import posixpath
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from osmo.errors import OsmoError
from osmo.runtime.container.run import Mount, RegistryAuth
from osmo.runtime.kubernetes.config import KubePool, Placement

__all__ = ["ATTEMPT_ID", "COLLECTOR", "CONTAINER", "DataPlan", "FETCHER", "LABEL_ATTEMPT",
           "TICKETS", "TICKET_DIR", "ZENOH_CONFIG", "ZENOH_KEY",
           "in_volume", "LABEL_GROUP", "LABEL_INSTANCE", "LABEL_LEAD",
           "LABEL_WORKFLOW", "POD_GROUPS", "GroupPlan", "docker_config",
           "ManifestError", "PodPlan", "label_value", "object_name", "plan_labels",
           "pod_group_manifest", "pod_manifest", "priority_class", "secret_manifest",
           "selector", "service_manifest"]

CONTAINER = "task"
"""The name of the task's container in its pod."""
FETCHER = "osmo-fetch"
"""The init container that fetches the attempt's data into the pod (``DataPlan``)."""
COLLECTOR = "osmo-collect"
"""The container that sends the task's output back once it ended (``DataPlan``)."""
TICKETS = {"fetch": "osmo-fetch-ticket", "collect": "osmo-collect-ticket"}
"""Each pod-data role → its ticket's key in the attempt's Secret."""
ZENOH_KEY = "osmo-zenoh-"
"""The prefix of the Secret's keys holding what the data containers show the router."""
ZENOH_CONFIG = "zenoh.json5"
"""The data containers' zenoh config among ``DataPlan.zenoh_files``."""
TICKET_DIR = "/var/run/osmo-tickets"
"""Where osmo's data containers find the Secret's tickets and router credentials."""
_DATA_ROOT = "/osmo-pod"  # where osmo's containers mount the pod's data volume

LABEL_INSTANCE = "osmo.dev/instance"
LABEL_WORKFLOW = "osmo.dev/workflow"
LABEL_TASK = "osmo.dev/task"
LABEL_RETRY = "osmo.dev/retry"
LABEL_ATTEMPT = "osmo.dev/attempt"
LABEL_GROUP = "osmo.dev/group"
LABEL_LEAD = "osmo.dev/lead"
ATTEMPT_ID = "osmo.dev/attempt-id"
"""The annotation holding the pod's attempt id (whole: a label value may not hold it)."""

_GRACE = 3  # seconds: what a cancel gives the task, as osmo's other runtimes
_ENV_NAME = re.compile(r"[-._a-zA-Z][-._a-zA-Z0-9]*")


class ManifestError(OsmoError):
    """An attempt cannot be written as a manifest (the message says which value)."""


@dataclass(frozen=True)
class GroupPlan:
    """The gang an attempt belongs to: its group's object name and size."""

    name: str
    size: int


@dataclass(frozen=True)
class DataPlan:
    """How a pod gets its data without a shared volume (``osmo.runtime.kubernetes.podio``).

    Attributes:
        image: osmo's image, for the init container and the collector.
        connect: the zenoh endpoints they dial (the node's router).
        cluster: the osmo cluster's name (its key prefix).
        node: the node whose pod-data API they speak to.
        zenoh_files: the files of what they show the router
            (``osmo.transport.zenoh_link.client_credentials``: its config and certificates),
            each in the attempt's Secret under :data:`ZENOH_KEY` + its name; empty: none.
    """

    image: str
    connect: tuple[str, ...]
    cluster: str
    node: str
    zenoh_files: tuple[str, ...] = ()


def in_volume(target: str) -> str:
    """Where a layout path (``/osmo/data/input/0``) lives in the pod's data volume."""
    return posixpath.normpath(target).lstrip("/")


@dataclass(frozen=True)
class PodPlan:
    """What the runtime resolved for one attempt's pod.

    Attributes:
        attempt_id: the attempt (labels, names).
        workflow_id, task, retry: for the labels.
        instance: the osmo instance (the node's owner id).
        image: the image, pinned where it could be.
        argv: the command, tokens resolved (empty: the image's own).
        env: the task's variables (literal values; never credentials).
        secret_env: the names of its credential variables (their values go in its Secret).
        mounts: the node's folders the task sees (``osmo.runtime.container.layout.mounts``).
        workdir: its working folder (None: the image's).
        cpu, memory, gpus, storage: its request (memory and storage in bytes).
        platform: its platform (the pool's placement for it).
        group: its gang (None: it runs alone).
        hostname: its name in its group's Service.
        lead: it is its group's lead (the others may wait for it).
        priority: its workflow's priority, ``HIGH``, ``NORMAL`` or ``LOW`` (None: unknown).
    """

    attempt_id: str
    workflow_id: str
    task: str
    retry: int
    instance: str
    image: str
    argv: tuple[str, ...] = ()
    env: Mapping[str, str] = field(default_factory=dict, repr=False)
    secret_env: tuple[str, ...] = ()
    mounts: tuple[Mount, ...] = ()
    workdir: str | None = None
    cpu: float | None = None
    memory: int | None = None
    gpus: int = 0
    storage: int | None = None
    platform: str | None = None
    group: GroupPlan | None = None
    hostname: str | None = None
    lead: bool = False
    priority: str | None = None

    @property
    def name(self) -> str:
        """The pod's name (its Secret's too)."""
        return object_name(self.attempt_id)


def object_name(*parts: str) -> str:
    """A DNS-1123 label for ``parts``: readable, at most 63 characters, unique per parts."""
    readable = re.sub(r"[^a-z0-9-]+", "-", "-".join(parts).lower()).strip("-")[:40].strip("-")
    digest = hashlib.sha256("\0".join(parts).encode()).hexdigest()[:12]
    return f"osmo-{readable}-{digest}" if readable else f"osmo-{digest}"


def label_value(text: str) -> str:
    """``text`` as a label value: itself when it is one, else a readable form with a digest."""
    if re.fullmatch(r"([A-Za-z0-9]([-A-Za-z0-9_.]{0,61}[A-Za-z0-9])?)?", text):
        return text
    readable = re.sub(r"[^A-Za-z0-9_.-]+", "-", text).strip("-_.")[:48].strip("-_.")
    digest = hashlib.sha256(text.encode()).hexdigest()[:12]
    return f"{readable}-{digest}" if readable else digest


def selector(labels: Mapping[str, str]) -> str:
    """A label selector matching every one of ``labels``."""
    return ",".join(f"{k}={label_value(v)}" for k, v in sorted(labels.items()))


def plan_labels(plan: PodPlan) -> dict[str, str]:
    """The labels of an attempt's objects."""
    labels = {LABEL_INSTANCE: plan.instance, LABEL_WORKFLOW: plan.workflow_id,
              LABEL_TASK: plan.task, LABEL_RETRY: str(plan.retry),
              LABEL_ATTEMPT: plan.attempt_id}
    if plan.group is not None:
        labels[LABEL_GROUP] = plan.group.name
        labels[LABEL_LEAD] = "1" if plan.lead else "0"
    return {k: label_value(v) for k, v in labels.items()}


def priority_class(plan: PodPlan, pool: KubePool) -> str | None:
    """The PriorityClass of the attempt's pod (None: none).

    The pool's class for its workflow's priority (``HIGH``, ``NORMAL``, ``LOW``; "" there:
    none), else the pool's ``default`` class.
    """
    classes = pool.priority_classes
    key = plan.priority if plan.priority in classes else "default"
    return classes.get(key or "default") or None


def pod_manifest(plan: PodPlan, pool: KubePool, *, secret: str | None = None,
                 pulls_with_secret: bool = False, data: DataPlan | None = None
                 ) -> dict[str, Any]:
    """The attempt's Pod (``secret``: its Secret's name, when it has one).

    ``pulls_with_secret``: that Secret also holds the registry's credentials for the image.
    ``data``: the pod fetches and sends back its data itself (its Secret holds the tickets).

    Raises:
        ManifestError: a value no manifest can hold (an environment name, a mount path).
    """
    _check(plan)
    if data is not None and secret is None:
        raise ManifestError("a pod that fetches its data needs the attempt's Secret")
    volumes, mounts = _volumes(plan, pool, data is not None)
    container: dict[str, Any] = {
        "name": CONTAINER, "image": plan.image, "imagePullPolicy": "IfNotPresent",
        "env": _env(plan, secret), "resources": _resources(plan),
        "securityContext": dict(pool.security_context or _default_security(pool)),
        "volumeMounts": mounts, "terminationMessagePolicy": "FallbackToLogsOnError"}
    if plan.argv:
        container["command"] = list(plan.argv)
    if plan.workdir:
        container["workingDir"] = plan.workdir
    placement = _placement(plan, pool)
    spec: dict[str, Any] = {
        "restartPolicy": "Never", "containers": [container], "volumes": volumes,
        "terminationGracePeriodSeconds": _GRACE, "enableServiceLinks": False,
        "shareProcessNamespace": True,
        "automountServiceAccountToken": False,
        "securityContext": {"runAsNonRoot": True,
                            "seccompProfile": {"type": "RuntimeDefault"}}}
    if data is not None:
        assert secret is not None
        _data_containers(spec, plan, data, secret, container["securityContext"])
    if placement.node_selector:
        spec["nodeSelector"] = dict(placement.node_selector)
    if placement.tolerations:
        spec["tolerations"] = [dict(t) for t in placement.tolerations]
    priority = priority_class(plan, pool)
    if priority:
        spec["priorityClassName"] = priority
    pulls = [*pool.image_pull_secrets, *([secret] if pulls_with_secret and secret else [])]
    if pulls:
        spec["imagePullSecrets"] = [{"name": n} for n in pulls]
    meta: dict[str, Any] = {"name": plan.name, "namespace": pool.namespace,
                            "labels": plan_labels(plan),
                            "annotations": {ATTEMPT_ID: plan.attempt_id}}
    if plan.group is not None:
        _gang(meta, spec, plan.group, pool)
        if pool.group_network == "host":
            spec["hostNetwork"] = True
        elif plan.hostname:
            spec["hostname"], spec["subdomain"] = plan.hostname, plan.group.name
    return {"apiVersion": "v1", "kind": "Pod", "metadata": meta, "spec": spec}


def secret_manifest(plan: PodPlan, values: Mapping[str, str], pool: KubePool, *,
                    owner_uid: str | None = None, registry: RegistryAuth | None = None
                    ) -> dict[str, Any]:
    """The attempt's Secret of ``values``, owned by its pod (``owner_uid``: the pod's uid).

    With ``registry`` it is also the pod's pull Secret (type
    ``kubernetes.io/dockerconfigjson``): it must exist before the pod, so it has no owner
    and is deleted after the pod.
    """
    meta: dict[str, Any] = {"name": plan.name, "namespace": pool.namespace,
                            "labels": plan_labels(plan)}
    if owner_uid is not None and registry is None:
        meta["ownerReferences"] = [{"apiVersion": "v1", "kind": "Pod", "name": plan.name,
                                    "uid": owner_uid}]
    data = {_secret_key(k): base64.b64encode(v.encode()).decode() for k, v in values.items()}
    kind = "Opaque"
    if registry is not None:
        kind = "kubernetes.io/dockerconfigjson"
        data[".dockerconfigjson"] = base64.b64encode(docker_config(registry).encode()).decode()
    return {"apiVersion": "v1", "kind": "Secret", "type": kind, "metadata": meta,
            "data": data}


def docker_config(auth: RegistryAuth) -> str:
    """A ``.dockerconfigjson`` holding one registry's credentials."""
    token = base64.b64encode(f"{auth.username}:{auth.password}".encode()).decode()
    host = "https://index.docker.io/v1/" if auth.registry == "docker.io" else auth.registry
    return json.dumps({"auths": {host: {"username": auth.username, "password": auth.password,
                                        "auth": token}}})


def service_manifest(group: GroupPlan, labels: Mapping[str, str], pool: KubePool
                     ) -> dict[str, Any]:
    """A group's headless Service: its pods' hostnames resolve as ``HOST.GROUP``."""
    return {"apiVersion": "v1", "kind": "Service",
            "metadata": {"name": group.name, "namespace": pool.namespace,
                         "labels": dict(labels)},
            "spec": {"clusterIP": "None", "publishNotReadyAddresses": True,
                     "selector": {LABEL_GROUP: group.name}}}


POD_GROUPS = {
    "kai": ("scheduling.run.ai", "v2alpha2", "podgroups"),
    "volcano": ("scheduling.volcano.sh", "v1beta1", "podgroups"),
    "coscheduling": ("scheduling.x-k8s.io", "v1alpha1", "podgroups"),
}
"""Each gang scheduler's PodGroup kind: ``(group, version, plural)``."""


def pod_group_manifest(group: GroupPlan, labels: Mapping[str, str], pool: KubePool
                       ) -> tuple[tuple[str, str, str], dict[str, Any]] | None:
    """``((group, version, plural), body)`` of the gang's PodGroup (None: the gang has none)."""
    kind = POD_GROUPS.get(pool.gang)
    if kind is None:
        return None
    spec: dict[str, Any] = {"minMember": group.size}
    if pool.queue and pool.gang in ("kai", "volcano"):
        spec["queue"] = pool.queue
    body = {"apiVersion": f"{kind[0]}/{kind[1]}", "kind": "PodGroup",
            "metadata": {"name": group.name, "namespace": pool.namespace,
                         "labels": dict(labels)}, "spec": spec}
    return kind, body


# ---------------------------------------------------------------- parts


def _check(plan: PodPlan) -> None:
    for name in [*plan.env, *plan.secret_env]:
        if not _ENV_NAME.fullmatch(name):
            raise ManifestError(f"environment variable {name!r}: Kubernetes takes names of "
                                "letters, digits, '_', '-' and '.' not starting with a digit")
    for key, value in plan.env.items():
        if "\0" in value:
            raise ManifestError(f"environment variable {key!r} holds a NUL character")
    if plan.argv and any("\0" in a for a in plan.argv):
        raise ManifestError("the command holds a NUL character")


def _secret_key(name: str) -> str:
    return name  # env names pass _check, and are valid Secret keys ([-._a-zA-Z0-9]+)


def _env(plan: PodPlan, secret: str | None) -> list[dict[str, Any]]:
    env: list[dict[str, Any]] = [{"name": k, "value": v} for k, v in plan.env.items()
                                 if k not in plan.secret_env]
    if plan.secret_env and secret is None:
        raise ManifestError("credential variables need the attempt's Secret")
    env += [{"name": k, "valueFrom": {"secretKeyRef": {"name": secret, "key": _secret_key(k)}}}
            for k in plan.secret_env]
    return env


def _quantity(amount: float) -> str:
    return f"{round(amount * 1000)}m" if amount != int(amount) else str(int(amount))


def _resources(plan: PodPlan) -> dict[str, Any]:
    requests: dict[str, str] = {}
    limits: dict[str, str] = {}
    if plan.cpu:
        requests["cpu"] = limits["cpu"] = _quantity(plan.cpu)
    if plan.memory:
        requests["memory"] = limits["memory"] = str(plan.memory)
    if plan.gpus:
        limits["nvidia.com/gpu"] = str(plan.gpus)
    if plan.storage:
        requests["ephemeral-storage"] = limits["ephemeral-storage"] = str(plan.storage)
    out: dict[str, Any] = {}
    if requests:
        out["requests"] = requests
    if limits:
        out["limits"] = limits
    return out


def _default_security(pool: KubePool) -> dict[str, Any]:
    return {"runAsNonRoot": True, "runAsUser": pool.run_as_user,
            "runAsGroup": pool.run_as_user, "allowPrivilegeEscalation": False,
            "privileged": False, "capabilities": {"drop": ["ALL"]}}


def _data_containers(spec: dict[str, Any], plan: PodPlan, data: DataPlan, secret: str,
                     security: dict[str, Any]) -> None:
    """Add osmo's init container and collector, the data volume and the tickets' volume."""
    spec["volumes"] += [
        {"name": "osmo-data", "emptyDir": {}},
        {"name": "osmo-tickets", "secret": {
            "secretName": secret, "defaultMode": 0o444,
            "items": [*({"key": key, "path": role} for role, key in TICKETS.items()),
                      *({"key": ZENOH_KEY + name, "path": name} for name in data.zenoh_files)]}}]
    mounts: list[dict[str, Any]] = [{"name": "osmo-data", "mountPath": _DATA_ROOT},
                                    {"name": "osmo-tickets", "mountPath": TICKET_DIR,
                                     "readOnly": True}]

    def side(name: str, role: str) -> dict[str, Any]:
        argv = ["python3", "-m", "osmo.runtime.kubernetes.podside", role]
        for endpoint in data.connect:
            argv += ["--connect", endpoint]
        argv += ["--cluster", data.cluster, "--node", data.node, "--attempt",
                 plan.attempt_id, "--ticket", f"{TICKET_DIR}/{role}", "--root", _DATA_ROOT]
        if ZENOH_CONFIG in data.zenoh_files:
            argv += ["--zenoh-config", f"{TICKET_DIR}/{ZENOH_CONFIG}"]
        return {"name": name, "image": data.image, "imagePullPolicy": "IfNotPresent",
                "command": argv, "volumeMounts": [dict(m) for m in mounts],
                "securityContext": dict(security),
                "terminationMessagePolicy": "FallbackToLogsOnError"}

    spec["initContainers"] = [side(FETCHER, "fetch")]
    spec["containers"].append(side(COLLECTOR, "collect"))


def _volumes(plan: PodPlan, pool: KubePool, own_data: bool = False
             ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    volumes: list[dict[str, Any]] = []
    mounts: list[dict[str, Any]] = []
    if own_data:
        for mount in plan.mounts:
            target = posixpath.normpath(mount.target)
            if not target.startswith("/") or target in ("/", "/proc", "/sys", "/dev"):
                raise ManifestError(f"cannot mount at {mount.target!r}")
            mounts.append({"name": "osmo-data", "mountPath": target,
                           "subPath": in_volume(target), "readOnly": mount.read_only})
        targets = [m["mountPath"] for m in mounts]
        nested = [t for t in targets if any(t.startswith(o + "/") for o in targets)]
        if nested:
            raise ManifestError(f"{nested[0]} lies inside another of the task's mounts")
    elif pool.work_claim is not None:
        volumes.append({"name": "work", "persistentVolumeClaim": {"claimName": pool.work_claim}})
    for index, mount in enumerate(() if own_data else plan.mounts):
        target = posixpath.normpath(mount.target)
        if not target.startswith("/") or target in ("/", "/proc", "/sys", "/dev"):
            raise ManifestError(f"cannot mount at {mount.target!r}")
        entry: dict[str, Any] = {"mountPath": target, "readOnly": mount.read_only}
        if pool.work_claim is not None:
            assert pool.work_mount is not None
            entry.update(name="work", subPath=_sub_path(mount.source, pool.work_mount))
        else:
            name = f"osmo-{index}"
            volumes.append({"name": name, "hostPath": {"path": str(mount.source)}})
            entry["name"] = name
        mounts.append(entry)
    if plan.gpus:
        volumes.append({"name": "dshm", "emptyDir": {"medium": "Memory",
                                                     "sizeLimit": pool.shm_size}})
        mounts.append({"name": "dshm", "mountPath": "/dev/shm"})
    return volumes, mounts


def _sub_path(source: Path, root: Path) -> str:
    if not source.is_relative_to(root):
        raise ManifestError(f"{source} is not on the pool's work claim (mounted at {root}): "
                            "the node's osmo home must live under work.mount")
    return str(source.relative_to(root))


def _placement(plan: PodPlan, pool: KubePool) -> Placement:
    extra = pool.platforms.get(plan.platform or "") or Placement()
    return Placement({**pool.placement.node_selector, **extra.node_selector},
                     (*pool.placement.tolerations, *extra.tolerations))


def _gang(meta: dict[str, Any], spec: dict[str, Any], group: GroupPlan, pool: KubePool) -> None:
    """Mark the pod as a member of ``group`` the way the pool's gang scheduler reads it."""
    labels: dict[str, str] = meta["labels"]
    annotations: dict[str, str] = meta["annotations"]
    if pool.gang == "kai":
        spec["schedulerName"] = "kai-scheduler"
        annotations["pod-group-name"] = group.name
        if pool.queue:
            labels["kai.scheduler/queue"] = label_value(pool.queue)
    elif pool.gang == "volcano":
        spec["schedulerName"] = "volcano"
        annotations["scheduling.k8s.io/group-name"] = group.name
    elif pool.gang == "coscheduling":
        labels["scheduling.x-k8s.io/pod-group"] = group.name
    elif pool.gang == "kueue":
        labels["kueue.x-k8s.io/pod-group-name"] = group.name
        annotations["kueue.x-k8s.io/pod-group-total-count"] = str(group.size)
        if pool.queue:
            labels["kueue.x-k8s.io/queue-name"] = label_value(pool.queue)


