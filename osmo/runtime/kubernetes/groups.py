"""A node's groups as Kubernetes sees them: gang objects, group Services, the lead's start.

A group of several tasks (``PrepareAttempt.hosts``) is a gang (:class:`GroupPlan`): its pods
carry the pool's gang scheduler's markers (``osmo.runtime.kubernetes.manifest``), and the
node makes the group's objects with its first member here and deletes them with its last:

- a headless Service named after the group (``groupNetwork: service``, the default):
  ``{{host:NAME}}`` is ``NAME.GROUP``, the DNS name of NAME's pod (its ``hostname`` and
  ``subdomain``), resolved by the cluster's DNS;
- the scheduler's PodGroup (KAI, Volcano, coscheduling) with ``minMember`` the group's size;
  Kueue reads its labels and annotations on the pods and needs no object.

With ``groupNetwork: host`` the group's pods use their node's network (``hostNetwork``) and
``{{host:NAME}}`` is the address the server placed NAME at: what holds where pods share a
host (the test stand-in, a one-node cluster), not across the nodes of a real cluster.

Without a gang scheduler (``gang: none``) osmo's own barrier starts the members together
and a peer's start waits (at most :data:`LEAD_WAIT` seconds) until its lead's pod runs, so
the lead listens first, as with containers. With a gang scheduler nobody waits: the pods
must exist for the gang to be placed at all.

What a crash leaves is deleted by label (``KubernetesRuntime.clean_orphans``).
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Mapping

from osmo.runtime.kubernetes.config import KubePool
from osmo.runtime.kubernetes.kube import Kube, KubeError
from osmo.runtime.kubernetes.manifest import (
    LABEL_GROUP,
    LABEL_INSTANCE,
    LABEL_LEAD,
    LABEL_WORKFLOW,
    GroupPlan,
    label_value,
    object_name,
    pod_group_manifest,
    service_manifest,
)
from osmo.scheduler.types import PrepareAttempt

__all__ = ["LEAD_WAIT", "Groups", "group_hosts", "hostname"]

LEAD_WAIT = 30.0
"""Seconds a peer waits for its lead's pod to run, then starts anyway."""

_HOSTNAME = re.compile(r"[a-z0-9]([-a-z0-9]{0,61}[a-z0-9])?")


def hostname(task: str) -> str:
    """A task's pod hostname in its group: the name itself when it is a DNS label."""
    return task if _HOSTNAME.fullmatch(task) else object_name(task)


def group_hosts(cmd: PrepareAttempt, pool: KubePool) -> Mapping[str, str] | None:
    """``{{host:NAME}}`` of each member of ``cmd``'s group (None: the placement's addresses)."""
    group = Groups.of(cmd)
    if group is None or pool.group_network == "host":
        return None
    return {task: f"{hostname(task)}.{group.name}" for task in cmd.hosts}


class Groups:
    """The groups of one node's pods (thread-safe).

    Args:
        kube: the API.
        pool: the pool's configuration.
        instance: the node's instance label value.
    """

    def __init__(self, kube: Kube, pool: KubePool, instance: str) -> None:
        self.kube, self.pool, self.instance = kube, pool, instance
        self._lock = threading.Lock()
        self._members: dict[str, int] = {}  # group → its attempts here, prepared and not done

    @staticmethod
    def of(cmd: PrepareAttempt) -> GroupPlan | None:
        """The attempt's gang (None: it runs alone)."""
        if len(cmd.hosts) < 2:
            return None
        return GroupPlan(object_name(cmd.workflow_id, *sorted(cmd.hosts)), len(cmd.hosts))

    def hosts(self, cmd: PrepareAttempt) -> Mapping[str, str] | None:
        """``{{host:NAME}}`` of each member (None: the placement's addresses)."""
        return group_hosts(cmd, self.pool)

    def labels(self, cmd: PrepareAttempt, group: GroupPlan) -> dict[str, str]:
        """What the group's objects carry (for selection and clean-up)."""
        return {LABEL_INSTANCE: self.instance, LABEL_WORKFLOW: label_value(cmd.workflow_id),
                LABEL_GROUP: group.name}

    def join(self, cmd: PrepareAttempt, group: GroupPlan) -> None:
        """A member is prepared here: the group's objects exist once this returns.

        Raises:
            KubeError: they cannot be made.
        """
        with self._lock:
            first = self._members.get(group.name, 0) == 0
            self._members[group.name] = self._members.get(group.name, 0) + 1
        if not first:
            return
        labels = self.labels(cmd, group)
        try:
            if self.pool.group_network == "service":
                self._create("service", service_manifest(group, labels, self.pool))
            pod_group = pod_group_manifest(group, labels, self.pool)
            if pod_group is not None:
                try:
                    self.kube.create_custom(pod_group[0], self.pool.namespace, pod_group[1])
                except KubeError as exc:
                    if exc.status != 409:
                        raise
        except KubeError:
            self.leave(group)
            raise

    def adopt(self, group: GroupPlan) -> None:
        """A member a previous life of the node prepared is adopted: its objects exist."""
        with self._lock:
            self._members[group.name] = self._members.get(group.name, 0) + 1

    def leave(self, group: GroupPlan) -> None:
        """A member is done here; the group's objects go with its last one (blocks: I/O)."""
        with self._lock:
            left = self._members.get(group.name, 1) - 1
            if left > 0:
                self._members[group.name] = left
                return
            self._members.pop(group.name, None)
        try:
            if self.pool.group_network == "service":
                self.kube.delete("service", self.pool.namespace, group.name)
            pod_group = pod_group_manifest(group, {}, self.pool)
            if pod_group is not None:
                self.kube.delete_custom(pod_group[0], self.pool.namespace, group.name)
        except KubeError:
            pass  # the node's next start deletes what is left by label

    def wait_for_lead(self, group: GroupPlan, timeout: float = LEAD_WAIT) -> None:
        """Block (an I/O thread) until a lead pod of ``group`` runs, at most ``timeout``."""
        labels = f"{LABEL_GROUP}={group.name},{LABEL_LEAD}=1"
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                pods, _ = self.kube.list_objects("pod", self.pool.namespace, labels=labels)
            except KubeError:
                pods = []
            if any((p.get("status") or {}).get("phase") in ("Running", "Succeeded", "Failed")
                   for p in pods):
                return
            time.sleep(0.2)

    def _create(self, kind: str, body: dict[str, object]) -> None:
        try:
            self.kube.create(kind, self.pool.namespace, body)
        except KubeError as exc:
            if exc.status != 409:  # another node of this instance made it: shared
                raise
