"""What the server takes from a client's submission, and what it never does for one.

The server never reads a path a client chose, and never imports code from a folder a client
named:

- ``localpath`` files are read by the client (``osmo.sdk``), which sends their contents; a
  submitted spec that still names a ``localpath`` is refused (:func:`check_no_localpath`),
  since the server would read its own file (its database, say) into the workflow.
- A custom task type (``type: module:attr``) is imported by the client, from the workflow's
  folder, which sends what it resolved: version, default resources, the folders the worker
  imports it from (``ResolvedType``). :class:`ClientTypes` gives the spec checker that
  description (its params accepted as the client checked them) instead of importing the code;
  installed types are still resolved and checked with this server's own plugins. Workers
  import the custom code when they run the task, as before.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from osmo.errors import UsageError
from osmo.params import Param
from osmo.spec.model import ResolvedType
from osmo.tasktypes.registry import Resolver, is_custom

__all__ = ["ClientTypes", "check_no_localpath"]

_MAX_DEPTH = 64


def check_no_localpath(spec: Any, depth: int = 0) -> None:
    """Refuse a spec (plain data) that still names a ``localpath``.

    Raises:
        UsageError: naming the fix (the client reads the file and sends its contents).
    """
    if depth > _MAX_DEPTH:
        return  # deeper than any spec; the spec checker refuses it
    if isinstance(spec, dict):
        if "localpath" in spec:
            raise UsageError(f"a submitted spec may not name a 'localpath' "
                             f"({str(spec.get('localpath'))[:200]!r}): the server never reads "
                             "files a client names; submit with `osmo submit` or the SDK, "
                             "which read it on your machine and send its contents")
        for value in spec.values():
            check_no_localpath(value, depth + 1)
    elif isinstance(spec, list):
        for value in spec:
            check_no_localpath(value, depth + 1)


@dataclass(frozen=True)
class _Described:
    """A custom type as the client described it (the server never imports it)."""

    version: str
    resources: Mapping[str, Any]
    params: Mapping[str, Param] = field(default_factory=dict)


class ClientTypes:
    """A ``TypeResolver`` (``osmo.spec.typed``) for a submission: see the module docstring.

    Args:
        described: ``task name -> ResolvedType`` data the client sent (``types``).
        spec: the submitted spec (plain data), to accept each custom task's params as given.

    Raises:
        UsageError: ``described`` is not such data.
    """

    def __init__(self, described: Mapping[str, Any], spec: Mapping[str, Any]) -> None:
        self._installed = Resolver(())
        self._custom: dict[str, _Described] = {}
        self._paths: dict[str, tuple[str, ...]] = {}
        self.described: dict[str, ResolvedType] = {}  # custom-typed task -> the client's word
        tasks = _tasks(spec)
        for name, data in described.items():
            task = tasks.get(name) or {}
            ref = task.get("type")
            if not isinstance(ref, str) or not is_custom(ref):
                continue  # installed types are resolved here, never taken from a client
            resolved = _resolved(name, data)
            params = task.get("params")
            given: dict[str, Any] = params if isinstance(params, dict) else {}
            known = self._custom.get(ref)  # another task of the same type: both its params
            taken = {k: Param(type(v), default=None) for k, v in given.items()}
            self._custom[ref] = _Described(resolved.version, {}, {
                **taken, **(known.params if known is not None else {})})
            self._paths[ref] = resolved.paths
            self.described[name] = resolved

    def resolve(self, ref: str) -> Any:
        """The client's description of a custom type, or this server's installed type."""
        if is_custom(ref):
            if ref not in self._custom:
                raise UsageError(f"custom task type '{ref}' was not described by the client "
                                 "(the server does not import code a client names)")
            return self._custom[ref]
        return self._installed.resolve(ref)

    def paths_for(self, ref: str) -> tuple[str, ...]:
        """Where the worker imports a custom type from (as the client resolved it)."""
        return self._paths.get(ref, ()) if is_custom(ref) else ()


def _tasks(spec: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    wf = spec.get("workflow") if isinstance(spec.get("workflow"), dict) else {}
    assert isinstance(wf, dict)
    tasks = [t for t in wf.get("tasks") or [] if isinstance(t, dict)]
    for group in wf.get("groups") or []:
        if isinstance(group, dict):
            tasks += [t for t in group.get("tasks") or [] if isinstance(t, dict)]
    return {str(t.get("name")): t for t in tasks}


def _resolved(name: str, data: Any) -> ResolvedType:
    try:
        resolved = ResolvedType.from_dict(data)
    except (TypeError, KeyError, ValueError, AttributeError):
        raise UsageError(f"'types.{name}' is not a resolved task type (version, resources, "
                         "paths)") from None
    if not all(isinstance(p, str) for p in resolved.paths):
        raise UsageError(f"'types.{name}.paths' must be a list of folders")
    return resolved
