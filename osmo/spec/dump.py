"""The model back to plain data and YAML in OSMO key names (``exitActions``, ``maxRetries``...).

``spec_to_dict`` gives a JSON/YAML-able dict that ``spec_from_dict`` (and ``load_spec`` on
``dump_yaml``'s text) turns back into an equal model: sizes become exact binary units
(``"4Gi"``) or byte counts, timeouts ``"<n>s"``, exit codes ``"0,1-10"``. Pure.
"""

from __future__ import annotations

import re
from typing import Any

from osmo.spec import tokens, yamlnodes
from osmo.spec.model import (
    DEFAULT_RESOURCE,
    FileSpec,
    GroupSpec,
    InputSpec,
    OutputSpec,
    ResourceSpec,
    TaskSpec,
    WorkflowSpec,
)
from osmo.spec.units import format_duration, format_exit_codes, format_size

__all__ = ["dump_yaml", "jinja_literal", "spec_to_dict"]


def _drop_none(d: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in d.items() if v is not None}


def _resource(r: ResourceSpec) -> dict[str, Any]:
    return _drop_none({
        "cpu": r.cpu,
        "gpu": r.gpu,
        "memory": None if r.memory is None else format_size(r.memory),
        "storage": None if r.storage is None else format_size(r.storage),
        "platform": r.platform,
        "nodesExcluded": list(r.nodes_excluded) or None,
        "topology": [_drop_none({"key": t.key, "group": t.group,
                                 "requirementType": t.requirement_type})
                     for t in r.topology] or None,
    })


def _file(f: FileSpec) -> dict[str, Any]:
    out: dict[str, Any] = {"path": f.path, "contents": f.contents}
    if f.base64:
        out["base64"] = True
    return out


def _input(i: InputSpec) -> dict[str, Any]:
    if i.dataset is not None:
        return {"dataset": _drop_none({"name": i.dataset, "regex": i.regex})}
    if i.url is not None:
        return _drop_none({"url": i.url, "regex": i.regex})
    task = f"{i.workflow}:{i.task}" if i.workflow else i.task
    return _drop_none({"task": task, "regex": i.regex})


def _output(o: OutputSpec) -> dict[str, Any]:
    if o.dataset is not None:
        return {"dataset": _drop_none({"name": o.dataset, "path": o.path, "regex": o.regex,
                                       "metadata": o.metadata})}
    return _drop_none({"url": o.url, "regex": o.regex})


def _task(t: TaskSpec) -> dict[str, Any]:
    return _drop_none({
        "name": t.name,
        "image": t.image,
        "type": t.type,
        "params": dict(t.params) or None,
        "command": list(t.command) or None,
        "args": list(t.args) or None,
        "environment": dict(t.environment) or None,
        "files": [_file(f) for f in t.files] or None,
        "inputs": [_input(i) for i in t.inputs] or None,
        "outputs": [_output(o) for o in t.outputs] or None,
        "credentials": dict(t.credentials) or None,
        "resource": None if t.resource == DEFAULT_RESOURCE else t.resource,
        "lead": True if t.lead else None,
        "exitActions": {r.action.value: format_exit_codes(r.ranges) for r in t.exit_actions}
        or None,
        "checkpoint": [dict(c) for c in t.checkpoint] or None,
        "cache": t.cache,
        "warm": t.warm,
    })


def _group(g: GroupSpec) -> dict[str, Any]:
    return _drop_none({
        "name": g.name,
        "tasks": [_task(t) for t in g.tasks],
        "barrier": None if g.barrier else False,
        "ignoreNonleadStatus": None if g.ignore_nonlead_status else False,
    })


def _is_bare(spec: WorkflowSpec) -> bool:
    return spec.bare_tasks and all(
        len(g.tasks) == 1 and g.tasks[0].name == g.name and g.barrier
        and g.ignore_nonlead_status for g in spec.groups)


def spec_to_dict(spec: WorkflowSpec) -> dict[str, Any]:
    """The spec as plain data in OSMO's layout: ``{"version": 2, "workflow": {...}}``."""
    timeout = _drop_none({
        "exec_timeout": None if spec.timeout.exec_timeout is None
        else format_duration(spec.timeout.exec_timeout),
        "queue_timeout": None if spec.timeout.queue_timeout is None
        else format_duration(spec.timeout.queue_timeout),
    })
    workflow = _drop_none({
        "name": spec.name,
        "pool": spec.pool,
        "labels": dict(spec.labels) or None,
        "timeout": timeout or None,
        "maxRetries": spec.max_retries,
        "cache": spec.cache,
        "resources": {n: _resource(r) for n, r in spec.resources.items()} or None,
    })
    if _is_bare(spec):
        workflow["tasks"] = [_task(g.tasks[0]) for g in spec.groups]
    else:
        workflow["groups"] = [_group(g) for g in spec.groups]
    return {"version": 2, "workflow": workflow}


_JINJA_OPEN = re.compile(r"\{[{%#]")


def jinja_literal(text: str) -> str:
    """``text`` made to render to itself.

    Every ``{{``/``{%``/``{#`` that is not a special token is wrapped in ``{% raw %}``; inserts no
    quotes, so YAML quoting stays valid.
    """
    protected, saved = tokens.protect(text)
    escaped = _JINJA_OPEN.sub(lambda m: "{% raw %}" + m.group(0) + "{% endraw %}", protected)
    return tokens.restore(escaped, saved)


def dump_yaml(spec: WorkflowSpec) -> str:
    """The spec as YAML text that ``load_spec(text=...)`` reads back to an equal model."""
    return jinja_literal(yamlnodes.dump(spec_to_dict(spec)))
