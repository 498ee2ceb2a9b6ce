"""The manifests a workflow's attempts would make as pods, without a cluster (a preview).

``osmo submit SPEC --dry-run --runtime kubernetes`` prints them: each image task's first
attempt is prepared the way a Kubernetes node prepares it (``osmo.worker.workdir.prepare``
with the Kubernetes runtime's paths, then ``osmo.runtime.kubernetes.runtime.attempt_plan``)
in a temporary folder, and its Pod, Secret and group objects are rendered. What only the
node can know is shown as placeholders: the node's folders (under ``/osmo-node``, or under
the work claim's mount when the pool has one), an upstream task's output, a credential's
values (``<credential NAME>``), an image's digest. With the pool's ``data`` the pod fetches
and sends back its own data: its Secret then holds ``<ticket>`` placeholders and its data
containers dial ``<the worker's endpoints>`` unless ``data.connect`` names them.
"""

from __future__ import annotations

import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

from osmo.layout import AttemptDirs
from osmo.runtime.api import Attempt, Terms
from osmo.runtime.choose import container_image
from osmo.runtime.container.layout import DATA_LAYOUT
from osmo.runtime.kubernetes.config import KubePool
from osmo.runtime.kubernetes.groups import group_hosts
from osmo.runtime.kubernetes.manifest import (
    LABEL_GROUP,
    LABEL_INSTANCE,
    LABEL_WORKFLOW,
    TICKETS,
    ZENOH_CONFIG,
    ZENOH_KEY,
    DataPlan,
    label_value,
    pod_group_manifest,
    pod_manifest,
    secret_manifest,
    service_manifest,
)
from osmo.runtime.kubernetes.runtime import attempt_plan
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import TaskSpec, WorkflowSpec
from osmo.worker.workdir import prepare

__all__ = ["NODE_ROOT", "pod_manifests"]

NODE_ROOT = Path("/osmo-node")
"""Where the preview shows the node's folders."""
_WORKFLOW = "WORKFLOW_ID"
_INSTANCE = "INSTANCE"


def pod_manifests(spec: WorkflowSpec, pool: KubePool, task: str | None = None, *,
                  priority: str | None = None) -> list[dict[str, Any]]:
    """The objects each image task's first attempt would create (only ``task``'s if given).

    ``priority``: the workflow's (``HIGH``, ``NORMAL``, ``LOW``), which picks its pods'
    PriorityClass.

    Raises:
        PrepareError: a task's tokens cannot be resolved.
        ManifestError: a value no manifest can hold.
    """
    out: list[dict[str, Any]] = []
    made_groups: set[str] = set()
    with tempfile.TemporaryDirectory(prefix="osmo-pods-") as folder:
        for group in spec.groups:
            hosts = {t.name: t.name for t in group.tasks} if len(group.tasks) > 1 else {}
            for each in group.tasks:
                if (container_image(each, typed=False) is None
                        or (task is not None and each.name != task)):
                    continue
                cmd = PrepareAttempt(f"{_WORKFLOW}:{each.name}:0", _WORKFLOW, each.name, 0,
                                     "preview", _upstream(each), hosts)
                out += _objects(cmd, each, spec, pool, Path(folder), made_groups,
                                Terms(priority=priority))
    return out


def _upstream(task: TaskSpec) -> dict[str, str]:
    return {i.task: str(NODE_ROOT / "inputs" / i.task) for i in task.inputs if i.task}


def _objects(cmd: PrepareAttempt, task: TaskSpec, spec: WorkflowSpec, pool: KubePool,
             folder: Path, made_groups: set[str], terms: Terms) -> list[dict[str, Any]]:
    dirs = AttemptDirs(folder / cmd.task)
    paths = group_hosts(cmd, pool)
    layout = DATA_LAYOUT if paths is None else replace(DATA_LAYOUT, hosts=paths)
    secrets = {name: _placeholders(name, value) for name, value in task.credentials.items()}
    launch = prepare(dirs, cmd, task, {}, secrets, paths=layout)
    plan = attempt_plan(launch, Attempt(cmd, task, dirs, spec.resource_for(task), terms=terms),
                        instance=_INSTANCE)
    root = NODE_ROOT if pool.work_mount is None else pool.work_mount / NODE_ROOT.name
    plan = replace(plan, mounts=tuple(replace(m, source=root / m.source.relative_to(
        folder)) if m.source.is_relative_to(folder) else m for m in plan.mounts))
    objects: list[dict[str, Any]] = []
    if plan.group is not None and plan.group.name not in made_groups:
        made_groups.add(plan.group.name)
        labels = {LABEL_INSTANCE: _INSTANCE, LABEL_WORKFLOW: label_value(_WORKFLOW),
                  LABEL_GROUP: plan.group.name}
        if pool.group_network == "service":
            objects.append(service_manifest(plan.group, labels, pool))
        pod_group = pod_group_manifest(plan.group, labels, pool)
        objects += [pod_group[1]] if pod_group else []
    values = dict(launch.secret_env)
    data = None
    if pool.data_image is not None:
        # the router credentials: named, never read here (they are the node's, not the user's)
        zenoh = (ZENOH_CONFIG,) if pool.data_zenoh_config else ()
        data = DataPlan(pool.data_image, pool.data_connect or ("<the worker's endpoints>",),
                        "<cluster>", "<worker>", zenoh_files=zenoh)
        values.update({key: "<ticket>" for key in TICKETS.values()})
        values.update({ZENOH_KEY + name: f"<the user of {pool.data_zenoh_config}>"
                       for name in zenoh})
    secret = secret_manifest(plan, values, pool, owner_uid="POD_UID") if values else None
    objects.append(pod_manifest(plan, pool, secret=plan.name if secret else None, data=data))
    objects += [secret] if secret else []
    return objects


def _placeholders(name: str, value: Any) -> dict[str, str]:
    """A credential's keys, each with ``<credential NAME>`` for its value."""
    keys = value.values() if isinstance(value, dict) else ()
    return {str(key): f"<credential {name}>" for key in keys}
