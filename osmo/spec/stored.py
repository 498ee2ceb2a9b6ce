"""A workflow's spec as it is kept and sent: one record, one way back to the model.

:class:`StoredSpec` is the spec's whole identity once submitted: the rendered spec as plain
data (``localpath`` files already read by the client), the file it was submitted from (for
diagnostics), and what each typed task's type resolved to at submit (``ResolvedType``, so a
restarted server or a remote worker never imports or re-resolves a type). The server
stores it (``osmo.store``), sends it to a remote worker the first time the worker runs a
task of the workflow (``osmo.transport.wire``), and reads it back with :meth:`StoredSpec.load`.

The submit itself checks a client's spec against the server's own task types
(``osmo.server.handlers``), then keeps what they resolved to (:meth:`StoredSpec.resolved_as`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from osmo.spec.model import ResolvedType, WorkflowSpec

__all__ = ["SUBMITTED", "StoredSpec"]

SUBMITTED = "<submitted>"
"""The name diagnostics give a stored spec that came from no file."""


@dataclass(frozen=True)
class StoredSpec:
    """A submitted spec as stored (see the module docstring).

    Attributes:
        data: the rendered spec as plain data (``spec_to_dict``'s form).
        filename: the file it was submitted from (``<dict>``, ``<builder>`` for the SDK's
            other forms), or None.
        types: task name → its ``ResolvedType`` as plain data (``ResolvedType.to_dict``).
    """

    data: dict[str, Any]
    filename: str | None = None
    types: Mapping[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def source(self) -> str:
        """The name its diagnostics give it: its file, else :data:`SUBMITTED`."""
        return self.filename or SUBMITTED

    def load(self) -> WorkflowSpec:
        """The model, each typed task's type as resolved at submit (nothing is imported).

        Raises:
            SpecError: the data is not a valid spec.
        """
        from osmo.spec.loader import spec_from_dict
        from osmo.spec.typed import apply_resolved

        return apply_resolved(spec_from_dict(self.data, filename=self.source),
                              {name: ResolvedType.from_dict(data)
                               for name, data in self.types.items()})

    def resolved_as(self, spec: WorkflowSpec) -> StoredSpec:
        """This spec with the types ``spec`` (its checked model) resolved them to."""
        return StoredSpec(self.data, self.filename,
                          {t.name: t.resolved.to_dict() for t in spec.all_tasks()
                           if t.resolved is not None})

    def to_dict(self) -> dict[str, Any]:
        """Plain data: ``{"spec", "filename", "types"}`` (how a worker receives it)."""
        return {"spec": self.data, "filename": self.filename, "types": dict(self.types)}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> StoredSpec:
        """The inverse of :meth:`to_dict`; absent ``filename`` and ``types`` are empty.

        Raises:
            ValueError: ``spec`` or ``types`` is not a mapping, or ``filename`` not a string.
        """
        spec, filename, types = data.get("spec"), data.get("filename"), data.get("types")
        if not isinstance(spec, dict) or not isinstance(types or {}, dict) or not (
                filename is None or isinstance(filename, str)):
            raise ValueError("a stored spec is {spec: mapping, filename: string, "
                             "types: mapping}")
        return cls(spec, filename, dict(types or {}))
