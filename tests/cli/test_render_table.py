"""The task table: laid out by osmo when it fits (fast), by rich's Table otherwise.

The fast layout must print exactly what rich's borderless Table prints for the same cells.
"""

from __future__ import annotations

import io

import pytest
from rich.console import Console
from rich.table import Table

from osmo.cli import render
from osmo.cli.render import _table, console

HEADS = ["Task", "Retry", "Status", "Message"]
ROWS = [[("a", ""), ("0", ""), ("COMPLETED", "green"), ("", "")],
        [("bé-中文-task", ""), ("12", ""), ("FAILED", "red"), ("exit 3 \\n [bold]x[/]", "")],
        [("c", ""), ("1", ""), ("WAITING", ""), ("-", "")]]


def _printed(renderable: object, terminal: bool) -> str:
    out = io.StringIO()
    Console(file=out, width=console.width, highlight=False, force_terminal=terminal,
            color_system="standard").print(renderable)
    return out.getvalue()


def _rich_table(rows: list[list[tuple[str, str]]], monkeypatch: pytest.MonkeyPatch) -> Table:
    """The same cells as rich's Table: what ``_table`` gives when they do not fit."""
    with monkeypatch.context() as m:
        m.setattr(render.console, "width", 10, raising=False)
        table = _table(HEADS, rows)
    assert isinstance(table, Table)
    return table


@pytest.mark.parametrize("terminal", [False, True])
def test_a_table_that_fits_prints_what_rich_prints(terminal: bool,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    fast = _table(HEADS, ROWS)
    assert not isinstance(fast, Table)
    assert _printed(fast, terminal) == _printed(_rich_table(ROWS, monkeypatch), terminal)


def test_a_table_wider_than_the_console_is_rich_s() -> None:
    rows = [*ROWS, [("d", ""), ("0", ""), ("FAILED", "red"), ("x" * (console.width + 10), "")]]
    wide = _table(HEADS, rows)
    assert isinstance(wide, Table)
    assert [c.header for c in wide.columns] == HEADS and wide.row_count == len(rows)
