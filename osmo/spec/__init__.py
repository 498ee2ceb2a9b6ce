"""Workflow specs: YAML or the Python builder to a validated, frozen model, and back.

OSMO v2 YAML (with Jinja templating) or the Python builder → a validated, frozen
:class:`WorkflowSpec`, and back to plain data/YAML.

Public API::

    load_spec(path | text=..., set_values=, set_strings=, set_env=) -> WorkflowSpec
    render_spec(path | text=..., set_values=, set_strings=) -> str     # --dry-run
    spec_to_dict(spec) -> dict;  dump_yaml(spec) -> str
    spec_from_dict(d) -> WorkflowSpec                                  # stored specs
    load_spec(..., types=Resolver(paths))   # [ext] check type:/params: against task types
    Workflow(name, ...).resource(...).task(...).group(name, [Task(...)]).build()

Every problem is reported at once as a :class:`osmo.errors.SpecError` whose ``diagnostics``
read ``file:line:col: message``. Module map: ``yamlnodes`` (the only ``yaml`` import),
``template`` (the only ``jinja2`` import), ``units``, ``reader`` (typed node access),
``parse``/``parse_task``/``parse_io`` (one document → model), ``validate`` (cross-references),
``typed`` (typed tasks against their task types), ``support`` (what is not supported yet),
``dump``, ``builder``, ``loader`` (the pipeline), ``isolation`` (templates rendered in a child
process), ``values`` (template values), ``files`` (reading spec and ``localpath`` files).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# Loaded on first use, like ``osmo`` itself: a caller that needs one light module of the
# package (``osmo.spec.files`` to read a spec file) does not pay for YAML and the parsers.
_WHERE = {
    "Task": "osmo.spec.builder",
    "Workflow": "osmo.spec.builder",
    "dump_yaml": "osmo.spec.dump",
    "spec_to_dict": "osmo.spec.dump",
    "load_spec": "osmo.spec.loader",
    "render_spec": "osmo.spec.loader",
    "spec_from_dict": "osmo.spec.loader",
    "TypeResolver": "osmo.spec.typed",
    "apply_resolved": "osmo.spec.typed",
    **{name: "osmo.spec.model" for name in (
        "DEFAULT_RESOURCE", "ExitAction", "ExitRule", "FileSpec", "GroupSpec", "InputSpec",
        "OutputSpec", "Pos", "ResolvedType", "ResourceSpec", "TaskSpec", "Timeouts",
        "TopologySpec", "WorkflowSpec")},
}

__all__ = [
    "DEFAULT_RESOURCE",
    "ExitAction",
    "ExitRule",
    "FileSpec",
    "GroupSpec",
    "InputSpec",
    "OutputSpec",
    "Pos",
    "ResolvedType",
    "ResourceSpec",
    "Task",
    "TaskSpec",
    "Timeouts",
    "TopologySpec",
    "TypeResolver",
    "Workflow",
    "WorkflowSpec",
    "apply_resolved",
    "dump_yaml",
    "load_spec",
    "render_spec",
    "spec_from_dict",
    "spec_to_dict",
]

if TYPE_CHECKING:
    from osmo.spec.builder import Task, Workflow
    from osmo.spec.dump import dump_yaml, spec_to_dict
    from osmo.spec.loader import load_spec, render_spec, spec_from_dict
    from osmo.spec.model import (
        DEFAULT_RESOURCE,
        ExitAction,
        ExitRule,
        FileSpec,
        GroupSpec,
        InputSpec,
        OutputSpec,
        Pos,
        ResolvedType,
        ResourceSpec,
        TaskSpec,
        Timeouts,
        TopologySpec,
        WorkflowSpec,
    )
    from osmo.spec.typed import TypeResolver, apply_resolved


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:  # also how ``from osmo.spec import yamlnodes`` finds a submodule
        raise AttributeError(f"module 'osmo.spec' has no attribute '{name}'")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
