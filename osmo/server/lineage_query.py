"""Answers lineage questions: which attempts made an artifact, from what, and who used it.

A target names an artifact: a blob digest (``sha256:...`` of one file), a manifest digest
(a whole output), ``WORKFLOW_ID:TASK[:PATH]``, or ``dataset:NAME[:TAG_OR_VERSION]``.

The answer is a graph: ``nodes`` keyed by manifest digest (each with the lineage record of
the attempt that made it) and ``edges`` ``[from, to]`` meaning "``to`` was made from
``from``". Upstream walks back to sources; downstream walks forward to consumers. Pure
reads of the store.
"""

from __future__ import annotations

from typing import Any

from osmo.errors import NotFoundError, UsageError
from osmo.names import parse_ref
from osmo.store.sqlite import Store

__all__ = ["lineage_graph", "resolve_target"]


def resolve_target(store: Store, target: str) -> tuple[list[str], str | None]:
    """The manifests a target names, and the blob digest if it named one file.

    Raises:
        UsageError: a ``dataset:`` target whose reference is not one (``osmo.names``).
        NotFoundError: nothing recorded matches the target.
    """
    if target.startswith("dataset:"):
        ref = target[len("dataset:"):]
        name, tag = parse_ref(ref)
        row = store.dataset(name, tag)
        if row is None:
            raise NotFoundError(f"dataset '{ref}' does not exist")
        return [str(row["manifest"])], None
    if target.startswith("sha256:"):
        if store.manifest_body(target) is not None:
            return [target], None
        holders = store.manifests_holding(target)
        if not holders:
            raise NotFoundError(f"no recorded artifact has digest {target}")
        return holders, target
    parts = target.split(":", 2)
    if len(parts) < 2:
        raise UsageError(f"cannot read target '{target}': use a digest (sha256:...), "
                         "WORKFLOW_ID:TASK[:PATH], or a local file")
    workflow_id, task = parts[0], parts[1]
    outputs = store.outputs(workflow_id, task)
    if not outputs:
        raise NotFoundError(f"no recorded output for task '{task}' of workflow '{workflow_id}'")
    manifest = str(outputs[0]["manifest"])
    if len(parts) == 2:
        return [manifest], None
    for path, digest, _size in _entries(store, manifest):
        if path == parts[2]:
            return [manifest], digest
    raise NotFoundError(f"no file '{parts[2]}' in the output of {workflow_id}:{task}")


def _entries(store: Store, manifest: str) -> list[tuple[str, str, int]]:
    from osmo.artifacts import Manifest

    body = store.manifest_body(manifest)
    if body is None:
        return []
    return [(e.path, e.digest, e.size) for e in Manifest.from_json(body).entries]


def lineage_graph(store: Store, target: str, *, downstream: bool = False) -> dict[str, Any]:
    """The lineage graph of ``target``, upstream (default) or downstream."""
    roots, blob = resolve_target(store, target)
    nodes: dict[str, dict[str, Any]] = {}
    edges: list[list[str]] = []
    pending = list(roots)
    while pending:
        manifest = pending.pop()
        if manifest in nodes:
            continue
        records = store.lineage_of_manifest(manifest)
        nodes[manifest] = records[0] if records else _dataset_node(store, manifest)
        if downstream:
            for consumer in store.consumers_of(manifest):
                made = consumer.get("manifest_digest")
                if made:
                    edges.append([manifest, made])
                    pending.append(made)
        else:
            origin = nodes[manifest].get("dataset_source")
            if origin:
                edges.append([origin, manifest])
                pending.append(origin)
            for source in nodes[manifest].get("inputs", []):
                made_from = source.get("manifest")
                if made_from:
                    edges.append([made_from, manifest])
                    pending.append(made_from)
    return {"target": target, "blob": blob, "roots": roots, "downstream": downstream,
            "nodes": nodes, "edges": sorted(map(list, {tuple(e) for e in edges}))}


def _dataset_node(store: Store, manifest: str) -> dict[str, Any]:
    """A node for a manifest no attempt made as a whole.

    A dataset version cut from an output (``dataset_source``), an upload, or unknown.
    """
    row = store.dataset_of_manifest(manifest)
    if row is None:
        return {"manifest_digest": manifest}
    return {"task": f"dataset {row['name']}:{row['version']}",
            "workflow_id": row["attempt_id"] or "upload", "manifest_digest": manifest,
            "dataset_source": row["source_manifest"], "inputs": []}
