"""Reports task types declare: tables the core shows without knowing their format.

A task type may declare a ``report``: an object with the :class:`Report` shape, naming the
output file it reads (``sim.eval`` declares its leaderboard, read from ``metrics.json``).
``osmo eval report`` finds those files among workflows' outputs (or takes local files),
hands each report the ones it accepts, and shows the :class:`Table` it makes: aligned text
whose every cell is escaped on the way to the terminal, or its rows as JSON. The core never
parses a report's files itself, so a new task type brings its own rows.

A report lives in a module that imports without the task type's own dependencies (the
file is JSON; the table is text), so ``osmo eval report`` works wherever the types install.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

from osmo.tasktypes.registry import TaskTypeError, entry_points, resolve

__all__ = ["Report", "Source", "Table", "installed_reports"]


@dataclass(frozen=True)
class Source:
    """One file a report reads: the JSON of ``task``'s output file in ``workflow``.

    A local file given on the command line has workflow ``-`` and its path as the task.
    """

    workflow: str
    task: str
    data: Any


@dataclass(frozen=True)
class Table:
    """What a report shows.

    Attributes:
        columns: the header cells.
        cells: the rows as text cells, one per column (the core escapes them when shown).
        rows: the same rows as data, for ``--format json``.
        notes: lines shown under the table (after a blank line), such as footnotes.
    """

    columns: tuple[str, ...]
    cells: tuple[tuple[str, ...], ...]
    rows: tuple[Mapping[str, Any], ...]
    notes: tuple[str, ...] = field(default=())


@runtime_checkable
class Report(Protocol):
    """The report a task type declares (its ``report`` attribute).

    Attributes:
        file: the name of the output file it reads (``metrics.json``), as JSON.
    """

    file: str

    def problem(self, data: Any) -> str | None:
        """Why ``data`` (a file's JSON) is not one of its files; None when it is."""
        ...

    def table(self, sources: Sequence[Source]) -> Table:
        """The table of every source it accepted (at least one)."""
        ...


def installed_reports() -> dict[str, Report]:
    """Task type name → its report, for the installed types that declare one.

    A type that does not load is left out (``osmo plugins list`` says why).
    """
    found: dict[str, Report] = {}
    for name in sorted(entry_points()):
        try:
            report = getattr(resolve(name), "report", None)
        except TaskTypeError:
            continue
        if isinstance(report, Report) and isinstance(report.file, str):
            found[name] = report
    return found
