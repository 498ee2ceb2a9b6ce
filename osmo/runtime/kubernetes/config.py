"""A Kubernetes pool's configuration: where and how its pods run (pure: reads one JSON file).

``osmo worker --runtime kubernetes --kubernetes-config FILE`` reads :class:`KubePool` from a
JSON object (the chart writes it from ``values.yaml``)::

    {"namespace": "osmo-tasks",             # where pods, Secrets and Services are made
     "kubeconfig": null,                    # null: in-cluster (the pod's ServiceAccount)
     "context": null,
     "nodeSelector": {"pool": "robots"},    # the nodes this pool may use
     "tolerations": [...],
     "platforms": {"jetson": {"nodeSelector": {...}, "tolerations": [...]}},
     "priorityClasses": {"HIGH": "osmo-high", "NORMAL": "", "LOW": "osmo-low"},
     "gang": "none",                        # kai | volcano | kueue | coscheduling | none
     "groupNetwork": "service",             # {{host:X}}: a headless Service per group, or
                                            # "host": hostNetwork pods (one host only)
     "securityContext": {...},              # the task container's (default: non-root, no
                                            # capabilities, no privilege escalation)
     "runAsUser": 1000,
     "imagePullSecrets": ["regcred"],
     "shmSize": "1Gi",                      # /dev/shm of a GPU task
     "data": {"image": "osmo:0.1.0",        # pods fetch and send back their own data
              "zenohConfig": "/run/osmo/zenoh/pod.json5"},
     "work": {"hostPath": true}}            # or: they see the node's attempt folders

``data``: each pod gets its data without any volume shared with the node: an init
container of osmo's image ``image`` fetches its inputs and files into the pod's own
``emptyDir`` and a second container sends its output back once the task ended, both over
zenoh to the node (``osmo.runtime.kubernetes.podio``), dialling ``connect`` (default: the
endpoints the worker itself dials). ``zenohConfig``: a zenoh client config (on the node) with
what those containers show the router: a user and password of their own, which the router
should confine to ``podio/**`` (the chart's ``auth.podUser``), and TLS certificates; the
node hands them to each pod in the attempt's Secret
(``osmo.transport.zenoh_link.client_credentials``). It takes precedence over ``work``.

``work``: the node's attempt folders (inputs, files, output) reach the pod through a volume.
``{"hostPath": true}`` binds each folder from the node's host: the node and its pods share a
host (a node per Kubernetes node, or the test stand-in). ``{"claim": NAME, "mount": PATH}``
mounts the ReadWriteMany claim ``NAME``, which the node has mounted at ``PATH`` (its osmo home
lives under it), with a ``subPath`` per folder.

Every key is optional; an unknown one is refused (a misspelt key must not silently do nothing).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from osmo.errors import UsageError

__all__ = ["GANGS", "KubePool", "Placement", "load_pool"]

GANGS = ("none", "kai", "volcano", "kueue", "coscheduling")
"""The gang schedulers a pool may name."""

_KEYS = {"namespace", "kubeconfig", "context", "nodeSelector", "tolerations", "platforms",
         "priorityClasses", "gang", "securityContext", "runAsUser", "imagePullSecrets",
         "shmSize", "work", "queue", "groupNetwork", "data"}


@dataclass(frozen=True)
class Placement:
    """Where a platform's pods go: a node selector and tolerations."""

    node_selector: Mapping[str, str] = field(default_factory=dict)
    tolerations: tuple[Mapping[str, Any], ...] = ()


@dataclass(frozen=True)
class KubePool:
    """A Kubernetes pool (see the module docstring for each key).

    Attributes:
        namespace: where its pods, Secrets, Services and PodGroups are made.
        kubeconfig: a kubeconfig file (None: in-cluster, else ``~/.kube/config``).
        context: the kubeconfig's context (None: its current one).
        placement: the nodes every pod may use.
        platforms: platform name → where its pods go (added to ``placement``).
        priority_classes: osmo priority → PriorityClass name ("" or missing: none).
        gang: the gang scheduler of groups (``GANGS``).
        queue: the gang scheduler's queue (KAI, Volcano, Kueue), if it needs one.
        group_network: how a group's pods reach each other: ``service`` (a headless Service
            per group) or ``host`` (``hostNetwork``; ``osmo.runtime.kubernetes.groups``).
        security_context: the task container's securityContext (None: the default).
        run_as_user: the uid the default securityContext runs tasks as.
        image_pull_secrets: Secrets every pod may pull with.
        shm_size: ``/dev/shm`` of a GPU task (a memory emptyDir).
        work_claim: the claim holding the node's attempt folders (None: hostPath binds).
        work_mount: where the node has ``work_claim`` mounted.
        data_image: osmo's image for the pods' own data containers (None: ``work``).
        data_connect: the endpoints those containers dial (empty: the worker's own).
        data_zenoh_config: the zenoh client config they connect with (None: none).
    """

    namespace: str = "default"
    kubeconfig: str | None = None
    context: str | None = None
    placement: Placement = field(default_factory=Placement)
    platforms: Mapping[str, Placement] = field(default_factory=dict)
    priority_classes: Mapping[str, str] = field(default_factory=dict)
    gang: str = "none"
    queue: str | None = None
    group_network: str = "service"
    security_context: Mapping[str, Any] | None = None
    run_as_user: int = 1000
    image_pull_secrets: tuple[str, ...] = ()
    shm_size: str = "1Gi"
    work_claim: str | None = None
    work_mount: Path | None = None
    data_image: str | None = None
    data_connect: tuple[str, ...] = ()
    data_zenoh_config: str | None = None


def load_pool(path: str | Path | None) -> KubePool:
    """The pool configured in the JSON file ``path`` (None: every default).

    Raises:
        UsageError: the file cannot be read, is not JSON, or holds an unknown key or a value
            of the wrong kind (the message names it).
    """
    if path is None:
        return KubePool()
    try:
        raw = json.loads(Path(path).read_text())
    except OSError as exc:
        raise UsageError(f"--kubernetes-config {path}: {exc.strerror}") from None
    except ValueError as exc:
        raise UsageError(f"--kubernetes-config {path}: not JSON: {exc}") from None
    try:
        return _pool(raw)
    except (TypeError, ValueError) as exc:
        raise UsageError(f"--kubernetes-config {path}: {exc}") from None


def _pool(raw: Any) -> KubePool:
    if not isinstance(raw, dict):
        raise ValueError("the configuration must be a JSON object")
    unknown = sorted(set(raw) - _KEYS)
    if unknown:
        raise ValueError(f"unknown key {unknown[0]!r} (known: {', '.join(sorted(_KEYS))})")
    gang = _str(raw, "gang", "none")
    if gang not in GANGS:
        raise ValueError(f"gang {gang!r}: choose {', '.join(GANGS)}")
    network = _str(raw, "groupNetwork", "service")
    if network not in ("service", "host"):
        raise ValueError(f"groupNetwork {network!r}: choose service or host")
    work = raw.get("work") or {"hostPath": True}
    if not isinstance(work, dict) or not (work.get("hostPath") is True or "claim" in work):
        raise ValueError('work: {"hostPath": true} or {"claim": NAME, "mount": PATH}')
    claim = work.get("claim")
    if claim is not None and not (isinstance(work.get("mount"), str)
                                  and str(work["mount"]).startswith("/")):
        raise ValueError("work.claim needs work.mount: where the node has it mounted")
    data = raw.get("data")
    if data is not None and not (isinstance(data, dict) and isinstance(data.get("image"), str)
                                 and data["image"]
                                 and set(data) <= {"image", "connect", "zenohConfig"}
                                 and isinstance(data.get("connect") or [], list)
                                 and isinstance(data.get("zenohConfig") or "", str)):
        raise ValueError('data: {"image": IMAGE}, optionally with "connect": [ENDPOINT] and '
                         '"zenohConfig": FILE')
    platforms = raw.get("platforms") or {}
    if not isinstance(platforms, dict):
        raise ValueError("platforms must be an object of platform → placement")
    security = raw.get("securityContext")
    if security is not None and not isinstance(security, dict):
        raise ValueError("securityContext must be an object")
    user = raw.get("runAsUser", 1000)
    if not isinstance(user, int) or user <= 0:
        raise ValueError("runAsUser must be a positive uid (tasks never run as root)")
    pulls = raw.get("imagePullSecrets") or []
    if not isinstance(pulls, list) or not all(isinstance(p, str) for p in pulls):
        raise ValueError("imagePullSecrets must be a list of Secret names")
    return KubePool(
        namespace=_str(raw, "namespace", "default"), kubeconfig=raw.get("kubeconfig"),
        context=raw.get("context"), placement=_placement(raw, "pool"),
        platforms={str(k): _placement(v, f"platforms.{k}") for k, v in platforms.items()},
        priority_classes=_strings(raw.get("priorityClasses") or {}, "priorityClasses"),
        gang=gang, queue=raw.get("queue"), group_network=network,
        security_context=security, run_as_user=user,
        image_pull_secrets=tuple(pulls), shm_size=_str(raw, "shmSize", "1Gi"),
        work_claim=claim, work_mount=Path(work["mount"]) if claim is not None else None,
        data_image=data["image"] if data else None,
        data_connect=tuple(str(e) for e in (data or {}).get("connect") or ()),
        data_zenoh_config=(data or {}).get("zenohConfig") or None)


def _str(raw: Mapping[str, Any], key: str, default: str) -> str:
    value = raw.get(key, default)
    if not isinstance(value, str) or not value:
        raise ValueError(f"{key} must be a non-empty string")
    return value


def _strings(raw: Any, where: str) -> dict[str, str]:
    if not isinstance(raw, dict) or not all(isinstance(v, str) for v in raw.values()):
        raise ValueError(f"{where} must be an object of strings")
    return {str(k): v for k, v in raw.items()}


def _placement(raw: Any, where: str) -> Placement:
    if not isinstance(raw, dict):
        raise ValueError(f"{where} must be an object")
    tolerations = raw.get("tolerations") or []
    if not isinstance(tolerations, list) or not all(isinstance(t, dict) for t in tolerations):
        raise ValueError(f"{where}: tolerations must be a list of objects")
    return Placement(_strings(raw.get("nodeSelector") or {}, f"{where}: nodeSelector"),
                     tuple(tolerations))
