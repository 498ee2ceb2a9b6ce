"""Task caching: a task whose fingerprint matches an earlier success reuses its outputs.

A fingerprint is the sha256 of the task's definition as submitted (command, args,
environment including ``--set-env``, files, image, plugin type, its version and params,
and its ``credentials:`` — names, variables, keys and mount paths, never the secret
values, so a rotated secret does not invalidate the cache) and the manifest digests of
its inputs, in input order. A task that runs in its image (a server with a container
engine, ``--runtime`` not ``process``) is fingerprinted by the image's **id**, resolved on
the server when the task is placed, not by its tag: a retagged image runs the task again, and
an image the server does not hold yet is not cached (its content is unknown). Tokens are
hashed as written: they resolve the same
way for the same inputs; ``{{workflow_id}}``/``{{uuid}}`` are not treated as changes.

Only attempts that no group barrier holds have a fingerprint (single-task groups and
``barrier: false`` groups); co-started group members interact and always run. Tasks with
``url`` inputs or outputs have none either: the remote content is not known when the task is
placed, and a hit would skip the upload. Every success with a fingerprint is recorded, whether
or not its task was allowed to reuse one, so a later run that may reuse finds it.

Whether a task *takes* an earlier success is :func:`reuses`: first ``osmo submit
--no-cache`` (never), then the task's ``cache:``, then the workflow's ``cache:``, then ``osmo
submit --reuse`` (yes), else the default (``WorkflowSpec.reuses_by_default``: typed tasks and
tasks whose output another task takes; a bare command task that feeds none runs every time,
as in OSMO). A hit is taken only while the earlier output folder still exists; its readers
get their own copies of it, checked against its manifest (a changed blob fails them instead).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

from osmo.record import LineageInput
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import TaskSpec, WorkflowSpec
from osmo.store.sqlite import Store

__all__ = ["CacheHit", "fingerprint", "input_sources", "key", "lookup", "reuses"]

_VERSION = 1  # bump when the fingerprint's content changes


def fingerprint(task: TaskSpec, inputs: list[tuple[str, str]],
                image_id: str | None = None) -> str:
    """The fingerprint of ``task`` given ``(input name, manifest digest)`` pairs.

    ``image_id``: the id its image resolved to (it stands for the tag), if it runs in it.
    """
    body: dict[str, object] = {
        "v": _VERSION,
        "command": list(task.command), "args": list(task.args),
        "environment": sorted(task.environment.items()),
        "files": [[f.path, f.contents, f.base64] for f in task.files],
        "image": image_id or task.image, "type": task.type, "params": task.params,
        "inputs": inputs,
    }
    if task.credentials:  # only when present: earlier fingerprints stay valid
        body["credentials"] = task.credentials
    if task.type is not None:  # typed tasks: the type's version is part of the definition
        body["type_version"] = task.resolved.version if task.resolved else None
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), default=str)
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()


def key(cmd: PrepareAttempt, task: TaskSpec, sources: list[LineageInput | None], *,
        contained: bool = False, image_id: str | None = None) -> str | None:
    """The cache key of a placed attempt, or None when it can neither reuse nor be reused.

    The key is the attempt's fingerprint; the rules are the module docstring's. Whether the
    attempt may take a hit is :func:`reuses`.

    Args:
        cmd: the placement (``run``: no group barrier holds it).
        task: its task's definition.
        sources: what each of its inputs is (:func:`input_sources`).
        contained: it runs in its image.
        image_id: that image's id (None: unknown, so not cached).
    """
    if not cmd.run:
        return None  # held by a group barrier
    if any(i.url for i in task.inputs) or any(o.url for o in task.outputs):
        return None  # URL contents are unknown at placement; a hit would skip the upload
    if any(s is None for s in sources):
        return None  # an input without a recorded manifest: its content is unknown
    if contained and image_id is None:
        return None  # an image the server cannot name: its content is unknown
    return fingerprint(task, [(s.task, s.manifest_digest) for s in sources if s],
                       image_id if contained else None)


def reuses(spec: WorkflowSpec, task: TaskSpec, *, submitted: bool | None) -> bool:
    """Whether ``task`` of ``spec`` may take an identical earlier success instead of running.

    Args:
        spec: its workflow.
        task: the task.
        submitted: what the submission said: True for ``--reuse``, False for ``--no-cache``,
            None for neither (``osmo.store.submission.Submission.reuses``).
    """
    if submitted is False:
        return False
    for said in (task.cache, spec.cache, submitted or None):
        if said is not None:
            return said
    return spec.reuses_by_default(task)


@dataclass(frozen=True)
class CacheHit:
    """An earlier successful attempt whose outputs can stand in for a new one."""

    attempt_id: str
    output_path: str
    manifest: str
    manifest_body: str


def input_sources(store: Store, cmd: PrepareAttempt) -> list[LineageInput | None]:
    """What each input of ``cmd`` is: its manifest and owning workflow (None if unrecorded).

    Read once at placement; the cache key and the lineage record both use it.
    """
    sources: list[LineageInput | None] = []
    for name, ref in cmd.inputs.items():
        found = store.output_of(ref)
        sources.append(None if found is None else LineageInput(name, found[1], found[0]))
    return sources


def lookup(store: Store, key: str) -> CacheHit | None:
    """The cached success for fingerprint ``key`` whose output folder still exists."""
    row = store.cached(key)
    if row is None or not Path(row["output_path"]).is_dir():
        return None
    body = store.manifest_body(row["manifest"])
    if body is None:
        return None
    return CacheHit(row["attempt_id"], row["output_path"], row["manifest"], body)
