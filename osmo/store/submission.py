"""How a workflow was submitted, as one typed record, and how the store keeps it.

:class:`Submission` is what a submit said besides the spec: the pool, priority and labels,
the cache choice (``--no-cache``, ``--reuse``), who submitted it, the workflow it restarts,
and its tags (changed later by ``osmo workflow tag``). The spec's own identity is
``osmo.spec.stored.StoredSpec``.

Both live in the ``workflows`` table: the spec's data in its ``spec`` column, everything else
in the JSON ``options`` column (:func:`options_column`: the submission's fields plus the spec's
``filename`` and ``types``). Rows written by older servers load too (:func:`from_columns`):
keys they lack take their defaults, keys no longer used (``type_paths``) are ignored.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from osmo.spec.stored import StoredSpec

__all__ = ["Submission", "from_columns", "options_column"]


@dataclass(frozen=True)
class Submission:
    """What a submit said besides the spec (see the module docstring).

    Attributes:
        pool: the pool it runs in (the request's, else the spec's; None: any).
        priority: ``HIGH``, ``NORMAL`` or ``LOW``.
        labels: the spec's labels with the request's over them.
        no_cache: ``--no-cache``: no task takes an earlier success.
        reuse: ``--reuse``: every task whose spec says nothing may take one.
        submitted_by: the submitter's identity name (a ``user`` may change only its own).
        reused_from: the workflow ``osmo restart`` made this one from.
        tags: its tags (``osmo workflow tag``).
    """

    pool: str | None = None
    priority: str = "NORMAL"
    labels: Mapping[str, str] = field(default_factory=dict)
    no_cache: bool = False
    reuse: bool = False
    submitted_by: str | None = None
    reused_from: str | None = None
    tags: tuple[str, ...] = ()

    @property
    def reuses(self) -> bool | None:
        """What it said about the cache: True (``--reuse``), False (``--no-cache``), or None.

        The ``submitted`` of ``osmo.server.cache.reuses``.
        """
        if self.no_cache:
            return False
        return True if self.reuse else None

    def to_dict(self) -> dict[str, Any]:
        """Plain data (:meth:`from_dict` reads it back)."""
        return {"pool": self.pool, "priority": self.priority, "labels": dict(self.labels),
                "no_cache": self.no_cache, "reuse": self.reuse,
                "submitted_by": self.submitted_by, "reused_from": self.reused_from,
                "tags": list(self.tags)}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Submission:
        """The inverse of :meth:`to_dict`, also of a row an older server wrote.

        Absent or empty values take the defaults; other keys are ignored.
        """
        labels = data.get("labels")
        return cls(pool=_text(data.get("pool")),
                   priority=_text(data.get("priority")) or "NORMAL",
                   labels={str(k): str(v) for k, v in labels.items()}
                   if isinstance(labels, dict) else {},
                   no_cache=bool(data.get("no_cache")), reuse=bool(data.get("reuse")),
                   submitted_by=_text(data.get("submitted_by")),
                   reused_from=_text(data.get("reused_from")),
                   tags=tuple(str(t) for t in data.get("tags") or ()))


def options_column(spec: StoredSpec, submission: Submission) -> dict[str, Any]:
    """The ``options`` column of a workflow: the submission and the spec's file and types."""
    return {**submission.to_dict(), "filename": spec.filename, "types": dict(spec.types)}


def from_columns(spec: dict[str, Any], column: Mapping[str, Any]) -> tuple[StoredSpec,
                                                                            Submission]:
    """A workflow row's ``spec`` and ``options`` columns (decoded) as the two records."""
    types = column.get("types")
    return (StoredSpec(spec, _text(column.get("filename")),
                       types if isinstance(types, dict) else {}),
            Submission.from_dict(column))


def _text(value: object) -> str | None:
    return value if isinstance(value, str) and value else None
