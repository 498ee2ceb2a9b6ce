"""A small Python builder for workflow specs, producing the same model as YAML.

::

    wf = Workflow("train-eval", pool="local", exec_timeout="2h")
    wf.resource(cpu=4, memory="8Gi")                     # the "default" resource
    wf.task("prep", ["python", "prep.py"])
    wf.task("train", ["python", "train.py", "--data", "{{input:0}}"], inputs=["prep"])
    spec = wf.build()                                    # a validated WorkflowSpec

Groups of co-scheduled tasks are declared with :class:`Task` values, one marked ``lead=True``::

    wf = Workflow("sim")
    wf.group("rollout", [Task("server", ["sim-server"], lead=True),
                         Task("client", ["sim-client", "{{host:server}}"])])

A task runs a ``command`` or, [ext], a task type with parameters::

    wf.task("roll", type="sim.rollout", params={"episodes": 10})   # an installed type
    wf.task("mine", type=tasks.rollout, params={"n": 3})             # a @task_type object

A type object (a function decorated with ``osmo.task_type`` or a task-type instance) is
written as its ``module:attr`` reference; its module must be importable by the worker.

A workflow uses either ``.task`` (bare tasks) or ``.group``, not both. ``build()`` dumps the
builder to plain data and loads it through the same parser and validation as a YAML file, so
every rule (and every error message) is the same; positions in those messages refer to
``to_yaml()``'s text.
"""

from __future__ import annotations

import base64
import shlex
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from osmo.names import object_ref
from osmo.spec import yamlnodes
from osmo.spec.dump import jinja_literal
from osmo.spec.loader import spec_from_dict
from osmo.spec.model import DEFAULT_RESOURCE, InputSpec, WorkflowSpec

__all__ = ["Task", "Workflow"]

Codes = str | int | Sequence[int | str]


def _input(item: str | InputSpec) -> dict[str, Any]:
    if isinstance(item, str):
        return {"task": item}
    if item.task is not None:
        out: dict[str, Any] = {"task": f"{item.workflow}:{item.task}" if item.workflow
                               else item.task}
    elif item.url is not None:
        out = {"url": item.url}
    else:
        out = {"dataset": {"name": item.dataset}}
    if item.regex is not None:
        out["regex"] = item.regex
    return out


def _file(path: str, contents: str | bytes) -> dict[str, Any]:
    if isinstance(contents, bytes):
        return {"path": path, "contents": base64.b64encode(contents).decode(), "base64": True}
    return {"path": path, "contents": contents}


@dataclass(frozen=True)
class Task:
    """One task for :meth:`Workflow.group` (``Workflow.task`` takes the same arguments).

    ``command`` is a list of words, or a string split like a shell would (``shlex``).
    ``inputs`` are upstream task names (``"prep"``, ``"other-wf-3:prep"``) or ``InputSpec``.
    ``files`` maps a path to its contents (``bytes`` are stored base64). ``exit_actions``
    maps ``COMPLETE``/``FAIL``/``RESCHEDULE`` to codes like ``"0,1-10"``, ``3`` or a list.
    ``type`` (a name, ``module:attr`` or a task-type object) and ``params`` replace
    ``command`` for a typed task.
    """

    name: str
    command: Sequence[str] | str | None = None
    args: Sequence[str] = ()
    image: str | None = None
    environment: Mapping[str, Any] | None = None
    files: Mapping[str, str | bytes] | None = None
    inputs: Sequence[str | InputSpec] = ()
    resource: str | None = None
    exit_actions: Mapping[str, Codes] | None = None
    cache: bool | None = None
    lead: bool = False
    type: Any = None
    params: Mapping[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        """The task as spec data (OSMO key names).

        Raises:
            UsageError: ``type`` is an object that cannot be named as ``module:attr``.
        """
        out: dict[str, Any] = {"name": self.name}
        if self.command is not None:
            command = shlex.split(self.command) if isinstance(self.command, str) \
                else self.command
            out["command"] = list(command)
        optional: dict[str, Any] = {
            "type": _type_ref(self.type),
            "params": dict(self.params) if self.params else None,
            "image": self.image,
            "args": list(self.args) or None,
            "environment": {k: _env_value(v) for k, v in (self.environment or {}).items()}
            or None,
            "files": [_file(p, c) for p, c in (self.files or {}).items()] or None,
            "inputs": [_input(i) for i in self.inputs] or None,
            "resource": None if self.resource in (None, DEFAULT_RESOURCE) else self.resource,
            "lead": True if self.lead else None,
            "exitActions": {k: v if isinstance(v, str | int) else list(v)
                            for k, v in self.exit_actions.items()} if self.exit_actions
            else None,
            "cache": self.cache,
        }
        out.update({k: v for k, v in optional.items() if v is not None})
        return out


def _type_ref(value: Any) -> str | None:
    """``value`` as a spec's ``type:`` writes it.

    A string as is, an object as the ``module:attr`` its module holds it under (found there, so a
    worker can import it).

    Raises:
        UsageError: the object is not in its module's globals, or lives in ``__main__``.
    """
    if value is None or isinstance(value, str):
        return value
    return object_ref(value)


def _env_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


class Workflow:
    """A workflow under construction; see the module docstring for an example.

    Timeouts are seconds (int) or strings like ``"30m"``; sizes are bytes (int) or strings
    like ``"4Gi"``. Methods return the builder, so calls can be chained.
    """

    def __init__(self, name: str, *, pool: str | None = None,
                 labels: Mapping[str, str] | None = None, exec_timeout: str | int | None = None,
                 queue_timeout: str | int | None = None, max_retries: int | None = None,
                 cache: bool | None = None) -> None:
        """Start a workflow called ``name`` (arguments are the ``workflow:`` fields)."""
        self.name, self.pool, self.labels = name, pool, labels
        self.exec_timeout, self.queue_timeout, self.max_retries = (
            exec_timeout, queue_timeout, max_retries)
        self.cache = cache
        self._resources: dict[str, dict[str, Any]] = {}
        self._tasks: list[Task] = []
        self._groups: list[dict[str, Any]] = []

    def resource(self, name: str = DEFAULT_RESOURCE, *, cpu: int | None = None,
                 gpu: int | None = None, memory: str | int | None = None,
                 storage: str | int | None = None, platform: str | None = None) -> Workflow:
        """Define (or replace) the resource ``name``; tasks use ``default`` unless told."""
        values = {"cpu": cpu, "gpu": gpu, "memory": memory, "storage": storage,
                  "platform": platform}
        self._resources[name] = {k: v for k, v in values.items() if v is not None}
        return self

    def task(self, name: str, command: Sequence[str] | str | None = None, *,
             args: Sequence[str] = (), image: str | None = None,
             environment: Mapping[str, Any] | None = None,
             files: Mapping[str, str | bytes] | None = None,
             inputs: Sequence[str | InputSpec] = (), resource: str | None = None,
             exit_actions: Mapping[str, Codes] | None = None, cache: bool | None = None,
             type: Any = None, params: Mapping[str, Any] | None = None) -> Workflow:
        """Add a bare task (its own one-task group). Arguments as for :class:`Task`."""
        self._tasks.append(Task(name, command, args, image, environment, files, inputs,
                                resource, exit_actions, cache, type=type, params=params))
        return self

    def group(self, name: str, tasks: Sequence[Task], barrier: bool = True,
              ignore_nonlead_status: bool = True) -> Workflow:
        """Add a group of co-scheduled tasks; with more than one, mark one ``lead=True``."""
        group: dict[str, Any] = {"name": name, "tasks": [t.to_dict() for t in tasks]}
        if not barrier:
            group["barrier"] = False
        if not ignore_nonlead_status:
            group["ignoreNonleadStatus"] = False
        self._groups.append(group)
        return self

    def to_dict(self) -> dict[str, Any]:
        """The workflow as spec data (not validated)."""
        timeout = {k: v for k, v in (("exec_timeout", self.exec_timeout),
                                     ("queue_timeout", self.queue_timeout)) if v is not None}
        workflow: dict[str, Any] = {"name": self.name}
        optional: dict[str, Any] = {
            "pool": self.pool, "labels": dict(self.labels or {}) or None,
            "timeout": timeout or None, "maxRetries": self.max_retries, "cache": self.cache,
            "resources": dict(self._resources) or None,
            "tasks": [t.to_dict() for t in self._tasks] or None,
            "groups": list(self._groups) or None,
        }
        workflow.update({k: v for k, v in optional.items() if v is not None})
        if "tasks" not in workflow and "groups" not in workflow:
            workflow["tasks"] = []
        return {"version": 2, "workflow": workflow}

    def to_yaml(self) -> str:
        """The workflow as YAML text, loadable with ``load_spec(text=...)``."""
        return jinja_literal(yamlnodes.dump(self.to_dict()))

    def build(self) -> WorkflowSpec:
        """Validate through the same rules as YAML and return the model.

        Raises:
            SpecError: with every problem found (positions refer to ``to_yaml()``).
        """
        return spec_from_dict(self.to_dict(), filename="<builder>")
