"""The task table: laid out by osmo when it fits (fast), by rich's Table otherwise.

The fast layout must print exactly what rich's borderless Table prints for the same cells.
"""

from __future__ import annotations

import io

import pytest
from rich.console import Console
from rich.table import Table
from rich.text import Text

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


def _rich_table(rows: list[list[tuple[str, str]]]) -> Table:
    table = Table(box=None, pad_edge=False)
    for head in HEADS:
        table.add_column(head)
    for row in rows:
        table.add_row(*(Text(cell, style) for cell, style in row))
    return table


@pytest.mark.parametrize("terminal", [False, True])
def test_a_table_that_fits_prints_what_rich_prints(terminal: bool) -> None:
    fast = _table(HEADS, ROWS)
    assert not isinstance(fast, Table)
    assert _printed(fast, terminal) == _printed(_rich_table(ROWS), terminal)


def test_a_table_wider_than_the_console_is_rich_s() -> None:
    rows = [*ROWS, [("d", ""), ("0", ""), ("FAILED", "red"), ("x" * (console.width + 10), "")]]
    wide = _table(HEADS, rows)
    assert isinstance(wide, Table)
    assert _printed(wide, False) == _printed(_rich_table(rows), False)
