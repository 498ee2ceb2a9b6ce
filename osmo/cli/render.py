"""Turns SDK results into text: tables, OSMO-style log lines, JSON.

The one CLI module that imports ``rich``. Output to a non-terminal is plain text (no colour,
no live redraw) so scripts and tests read it.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rich.table import Table

    from osmo.sdk.client import EventInfo, LogRecord, TaskInfo, TaskWaiting, WorkflowInfo

__all__ = ["QUERY_LIMIT", "TRANSFER_BAR_MIN", "console", "err_console", "events_text",
           "format_log", "info_dict", "live_progress", "not_shown_line", "plugin_table",
           "print_error", "print_json", "resource_table", "reuse_notice", "safe", "task_table",
           "transfer_progress", "workflow_header", "workflows_table"]

QUERY_LIMIT = 1000
"""The most tasks ``osmo query`` shows in its table unless told (``--limit``)."""

TRANSFER_BAR_MIN = 4 * 2**20
"""A transfer of fewer bytes than this shows no progress bar."""

_PLAIN_WIDTH = 160


class _LazyConsole:
    """A ``rich`` console made on first real use.

    So a CLI command that only prints a few plain lines (``osmo submit`` to a pipe) never imports
    rich. Plain ASCII lines that fit the width are written as rich would write them to a
    non-terminal.
    """

    def __init__(self, *, stderr: bool = False, **kwargs: Any) -> None:
        self._stderr = stderr
        self._kwargs = {"stderr": stderr, **kwargs}
        self._real: Any = None

    def _stream(self) -> Any:
        return sys.stderr if self._stderr else sys.stdout

    def _get(self) -> Any:
        if self._real is None:
            from rich.console import Console

            self._real = Console(**self._kwargs)
        return self._real

    @property
    def is_terminal(self) -> bool:
        """Whether output goes to a terminal (live progress, colours)."""
        return bool(self._get().is_terminal) if self._real is not None else (
            self._stream().isatty())

    def print(self, *objects: Any, **kwargs: Any) -> None:
        """``rich.console.Console.print``."""
        if (self._real is None and len(objects) == 1 and isinstance(objects[0], str)
                and kwargs == {"markup": False} and not self._stream().isatty()
                and objects[0].isascii() and len(objects[0]) <= _PLAIN_WIDTH
                and "\n" not in objects[0]):
            self._stream().write(objects[0] + "\n")
            return
        self._get().print(*objects, **kwargs)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._get(), name)


console: Any = _LazyConsole(highlight=False, width=None if sys.stdout.isatty() else 160)
err_console: Any = _LazyConsole(stderr=True, highlight=False, soft_wrap=True)


_NAMED = {"\a": "\\a", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\v": "\\v", "\f": "\\f",
          "\r": "\\r", "\\": "\\\\"}


def _escape(c: str) -> str:
    if c in _NAMED:
        return _NAMED[c]
    if c.isprintable():
        return c
    code = ord(c)
    if 0xDC80 <= code <= 0xDCFF:  # a byte that was not UTF-8, kept by surrogateescape
        return f"\\{code - 0xDC00:03o}"
    if code < 0x100:
        return f"\\{code:03o}"
    return f"\\u{code:04x}" if code <= 0xFFFF else f"\\U{code:08x}"


def safe(text: object) -> str:
    r"""``text`` with control and other non-printing characters escaped.

    As GNU ``ls --escape`` shows file names (``\n``, ``\033``, ``\u202e``; a byte that was not UTF-8
    as ``\351``; backslashes doubled).

    Every name a task, a file or a user chose (task, workflow, artifact path, command, message)
    is printed through this, so it can neither move the cursor, retitle or clear the terminal
    nor forge a line. JSON output is left exact.
    """
    value = str(text)
    if value.isprintable() and "\\" not in value:
        return value
    return "".join(map(_escape, value))


def _when(ts: float | None) -> str:
    return time.strftime("%Y/%m/%d %H:%M:%S", time.localtime(ts)) if ts else "-"


def _dur(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    if seconds < 60:
        return f"{seconds:.1f}s"
    minutes, sec = divmod(int(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}h{minutes:02d}m{sec:02d}s" if hours else f"{minutes}m{sec:02d}s"


def _style(status: str) -> str:
    if status == "COMPLETED":
        return "green"
    if status.startswith("FAILED"):
        return "red"
    return "yellow" if status in ("RUNNING", "INITIALIZING") else ""


def _elapsed(info: WorkflowInfo) -> float | None:
    return (info.ended_at or time.time()) - info.started_at if info.started_at else None


def workflow_header(info: WorkflowInfo) -> str:
    """The lines above a task table: id, status, pool, times."""
    lines = [
        f"Workflow ID : {safe(info.id)}",
        f"Status      : {info.status.name}",
        f"Pool        : {safe(info.pool or '-')}",
        f"Submitted by: {safe(info.submitted_by or '-')}",
        f"Priority    : {info.priority}",
        f"Submitted   : {_when(info.submitted_at)}",
        f"Duration    : {_dur(_elapsed(info))}",
    ]
    if info.reused_from:
        lines.append(f"Restart of  : {safe(info.reused_from)}")
    if info.labels:
        lines.append("Labels      : " + ", ".join(f"{safe(k)}={safe(v)}"
                                                  for k, v in sorted(info.labels.items())))
    if info.tags:
        lines.append(f"Tags        : {', '.join(map(safe, info.tags))}")
    return "\n".join(lines)


def reuse_notice(info: WorkflowInfo, *, most: int = 5) -> str | None:
    """The lines under ``osmo submit --wait`` that say which tasks did not run, or None.

    ``reused 1 task instead of running it: hello (from hello-1 task hello retry 0)``, then how
    to see their logs and how to run them. At most ``most`` tasks are named.
    """
    from osmo.status import reused_attempt

    reused = [t for t in info.tasks if t.reused]
    if not reused:
        return None
    named = []
    for t in reused[:most]:
        source = reused_attempt(t.message)
        where = (f"{source[0]} task {source[1]} retry {source[2]}" if source
                 else info.reused_from or "an earlier run")
        named.append(f"{safe(t.name)} (from {safe(where)})")
    more = f" and {len(reused) - most:,} more" if len(reused) > most else ""
    count = f"{len(reused):,} task{'s' if len(reused) > 1 else ''}"
    it = "them" if len(reused) > 1 else "it"
    return (f"reused {count} instead of running {it}: {', '.join(named)}{more}\n"
            f"  their logs: osmo logs {safe(info.id)}; to run every task: osmo submit "
            "--no-cache")


def not_shown_line(info: WorkflowInfo) -> str:
    """``99,000 more task(s) not shown; tasks by status: ...`` under a limited task table."""
    counts = ", ".join(f"{status} {n:,}" for status, n in sorted(info.counts.items()))
    head = (f"{info.not_shown:,} more task(s) not shown (--limit N, --status S); "
            if info.not_shown else "")
    return f"{head}tasks by status: {counts or 'none'}"


def task_table(tasks: list[TaskInfo], verbose: bool = False) -> Any:
    """A table of tasks: name, retry, status, start, duration, exit code.

    With ``verbose``, also group, node and message.
    """
    heads = ["Task", "Retry", "Status", "Start", "Duration", "Exit Code"]
    progress = any(t.progress for t in tasks)
    waits = any(t.waiting for t in tasks)
    heads += ["Progress"] * progress + ["Waiting For"] * waits
    if verbose:
        heads += ["Group", "Node", "Message"]
    rows: list[list[tuple[str, str]]] = []
    for t in tasks:
        status = t.status.name + (" (cached)" if t.reused else "")
        row = [(safe(t.name), ""), (str(t.retry), ""), (status, _style(t.status.name)),
               (_when(t.started_at), ""), (_dur(t.duration), ""),
               ("-" if t.exit_code is None else str(t.exit_code), "")]
        if progress:
            row.append((safe(t.progress or ""), ""))
        if waits:
            row.append((safe(waiting_text(t.waiting) if t.waiting else ""), ""))
        if verbose:
            row += [(safe(t.group), ""), (safe(t.node or "-"), ""), (safe(t.message or ""), "")]
        rows.append(row)
    return _table(heads, rows)


def _table(heads: list[str], rows: list[list[tuple[str, str]]]) -> Any:
    """Single-line ``(text, style)`` cells under ``heads``, as a borderless rich ``Table``.

    When every line fits the console, the lines are laid out here instead: what rich prints
    for that table, about 15 times faster (``osmo query`` of 1,000 tasks spent ~1 s in rich's
    column measuring and wrapping). Wider tables take rich's ``Table``, which wraps cells.
    """
    from rich.cells import cell_len
    from rich.table import Table
    from rich.text import Text

    widths = [cell_len(h) for h in heads]
    for row in rows:
        for i, (cell, _) in enumerate(row):
            widths[i] = max(widths[i], cell_len(cell))
    if sum(widths) + 2 * (len(widths) - 1) > console.width:
        table = Table(box=None, pad_edge=False)
        for head in heads:
            table.add_column(head)
        for row in rows:
            table.add_row(*(Text(cell, style) for cell, style in row))
        return table
    text = Text(no_wrap=True, overflow="ignore")
    lines = [[(h, "table.header") for h in heads], *rows]
    for n, row in enumerate(lines):
        gap = "table.header" if n == 0 else ""  # rich pads header cells in their style
        for i, (cell, style) in enumerate(row):
            if i:
                text.append(" ", gap)
                text.append(" ", gap)
            text.append(cell + " " * (widths[i] - cell_len(cell)), style or None)
        if n < len(lines) - 1:
            text.append("\n")
    return text


def waiting_text(waiting: TaskWaiting) -> str:
    """``pool 'gpu' has no online worker since 12:03; fails at 12:33 unless that changes``."""
    text = waiting.reason
    if waiting.since is not None:
        text += f" since {_clock(waiting.since)}"
    if waiting.fails_at is not None:
        text += f"; fails at {_clock(waiting.fails_at)} unless that changes"
    return text


def _clock(ts: float) -> str:
    """A local time of day, with the date when it is not today."""
    same_day = time.localtime(ts)[:3] == time.localtime()[:3]
    return time.strftime("%H:%M" if same_day else "%Y/%m/%d %H:%M", time.localtime(ts))


def workflows_table(rows: list[WorkflowInfo]) -> Table:
    """A table of workflows for ``osmo list``."""
    from rich.table import Table

    table = Table(box=None, pad_edge=False)
    for col in ("Workflow ID", "Status", "Submitted", "Duration", "Pool", "By"):
        table.add_column(col)
    for w in rows:
        table.add_row(safe(w.id), w.status.name, _when(w.submitted_at), _dur(_elapsed(w)),
                      safe(w.pool or "-"), safe(w.submitted_by or "-"))
    return table


def format_log(r: LogRecord) -> str:
    """OSMO's log line: ``YYYY/MM/DD HH:MM:SS [task] text`` (retries, osmo lines marked)."""
    who = safe(r.task or "workflow")
    if r.retry:
        who += f" retry-{r.retry}"
    tag = f"[{who}][osmo]" if r.stream == "osmo" else f"[{who}]"
    return f"{_when(r.ts)} {tag} {r.text}"


def events_text(events: list[EventInfo]) -> str:
    """``osmo workflow events``: one line per event, OSMO style, oldest first.

    ``YYYY/MM/DD HH:MM:SS  [task retry-N]  STATUS  on NODE  message``; the workflow's own
    events are marked ``[workflow]``.
    """
    lines = []
    for e in events:
        who = safe(e.task) + (f" retry-{e.retry}" if e.retry else "") if e.task else "workflow"
        waiting = e.status in ("PENDING", "WAITING", "SCHEDULING")
        where = f"  on {safe(e.node)}" if e.node and not waiting else ""
        message = f"  {safe(e.message)}" if e.message else ""
        lines.append(f"{_when(e.at)}  [{who}]  {e.status}{where}{message}")
    return "\n".join(lines)


def print_json(data: Any) -> None:
    """Print JSON (dataclasses and enums converted) to stdout."""

    def default(o: Any) -> Any:
        if hasattr(o, "__dataclass_fields__"):
            return asdict(o)
        if hasattr(o, "name"):
            return o.name
        raise TypeError(type(o).__name__)

    sys.stdout.write(json.dumps(data, default=default, indent=2) + "\n")


def info_dict(info: WorkflowInfo) -> dict[str, Any]:
    """A JSON-ready dict of a workflow with its tasks."""
    out = asdict(info)
    out["status"] = info.status.name
    if info.matched is None:  # every task is in it: no counts (as before they existed)
        del out["counts"], out["matched"]
    for t, src in zip(out["tasks"], info.tasks, strict=True):
        t["status"] = src.status.name
        t["duration"] = src.duration
    return out


def print_error(message: str) -> None:
    """``error: message`` on stderr (the message is printed literally, never as markup)."""
    from rich.text import Text

    lines = "\n".join(safe(line) for line in message.split("\n"))  # keep the line breaks only
    err_console.print(Text("error: ", style="red") + Text(lines))


@contextmanager
def live_progress() -> Iterator[Callable[[WorkflowInfo], None]]:
    """A live-redrawn progress view on a terminal; yields the function that updates it."""
    from rich.console import Group
    from rich.live import Live
    from rich.text import Text

    with Live(console=console._get(), refresh_per_second=8, transient=False) as live:

        def update(info: WorkflowInfo) -> None:
            done = sum(t.status.terminal for t in info.tasks)
            head = Text(f"{safe(info.id)}  {info.status.name}  {done}/{len(info.tasks)} tasks "
                        "done")
            live.update(Group(head, task_table(info.tasks)))

        yield update


@contextmanager
def transfer_progress(what: str) -> Iterator[Callable[[int, int], None] | None]:
    """A bar with bytes, rate and time left for a transfer, on a terminal only.

    Yields the ``(done, total)`` callback to hand the SDK (``osmo.sdk.transfer.Progress``;
    it may be called from several threads), or None when stdout is no terminal: piped and
    JSON output stay clean. A transfer under :data:`TRANSFER_BAR_MIN` bytes shows nothing.
    """
    if not console.is_terminal:
        yield None
        return
    lock = threading.Lock()
    shown: list[Any] = []  # [the rich Progress, its task id] once the bar is up

    def update(done: int, total: int) -> None:
        with lock:
            if not shown:
                if total < TRANSFER_BAR_MIN:
                    return
                from rich.progress import (
                    BarColumn,
                    DownloadColumn,
                    Progress,
                    TextColumn,
                    TimeRemainingColumn,
                    TransferSpeedColumn,
                )

                bar = Progress(TextColumn("{task.description}", markup=False), BarColumn(),
                               DownloadColumn(), TransferSpeedColumn(), TimeRemainingColumn(),
                               console=console._get())
                bar.start()
                shown.extend([bar, bar.add_task(safe(what), total=total)])
            shown[0].update(shown[1], completed=done, total=total)

    try:
        yield update
    finally:
        with lock:
            if shown:
                shown[0].stop()


def _gib(n: float) -> str:
    return f"{n / 2**30:.1f}Gi"


def resource_table(rows: list[dict[str, Any]], *, by: str) -> Table:
    """Nodes or pools with cpu/gpu/memory as used/total.

    A node that serves several platforms (a cluster node's gpu and cpu nodes) has a line
    per platform under its own (``  platform gpu``), with that platform's used/total.
    """
    from rich.table import Table

    table = Table(box=None, pad_edge=False)
    first = (["Node", "Pool", "Platform", "Status", "Runtime"] if by == "node"
             else ["Pool", "Nodes", "Platforms", "Runtimes"])
    warm = by == "node" and any(r.get("warm") for r in rows)
    for col in (*first, "CPU", "GPU", "Memory", "Sandbox", *(["Warm"] if warm else [])):
        table.add_column(col)
    for r in rows:
        platforms = r.get("platforms") or {}
        head = ([safe(r["node"]), safe(r["pool"]),
                 safe(", ".join(platforms) or r["platform"] or "-"),
                 safe(r.get("status", "online")), safe(r.get("runtime") or "-")] if by == "node"
                else [safe(r["pool"]), str(r["nodes"]), safe(", ".join(platforms)),
                      safe(", ".join(r.get("runtimes", ())) or "-")])
        table.add_row(*head, *_amounts(r["used"], r["total"]), safe(_sandbox(r)),
                      *([_warm(r.get("warm") or [])] if warm else []))
        if by == "node" and len(platforms) > 1:
            for name, amounts in platforms.items():
                table.add_row(f"  platform {safe(name)}", "", safe(name), "", "",
                              *_amounts(amounts["used"], amounts["total"]), "",
                              *([""] if warm else []))
    return table


def _amounts(used: dict[str, Any], total: dict[str, Any]) -> tuple[str, str, str]:
    """CPU, GPU and memory as used/total."""
    return (f"{used['cpu']:g}/{total['cpu']:g}", f"{used['gpu']}/{total['gpu']}",
            f"{_gib(used['memory'])}/{_gib(total['memory'])}")


def _warm(runners: list[dict[str, Any]]) -> str:
    """A node's warm runners: ``sim.rollout@1 x3 (91Mi)`` for each, one a line."""
    return "\n".join(f"{safe(str(r['type']))} x{r['started']} ({r['rss'] / 2**20:.0f}Mi)"
                     for r in runners) or "-"


def _sandbox(row: dict[str, Any]) -> str:
    """A node's sandbox: ``bwrap``, ``none (why)``; a pool's as summed by ``osmo pool list``."""
    why = row.get("sandbox_why")
    return f"{row.get('sandbox', '-')} ({why})" if why else str(row.get("sandbox", "-"))


def _param_line(name: str, p: dict[str, Any]) -> str:
    default = "required" if p["required"] else f"default {p['default']!r}"
    bounds = [f"choices {p['choices']}"] if p["choices"] else []
    bounds += [f"{k} {p[k]:g}" for k in ("min", "max") if p[k] is not None]
    extra = f", {', '.join(bounds)}" if bounds else ""
    return f"  {name}: {p['type']} ({default}{extra})" + (f" - {p['help']}" if p["help"] else "")


def plugin_table(rows: list[dict[str, Any]], *, verbose: bool = False) -> Table:
    """Installed task types; a broken one shows its error in red instead of a description."""
    from rich.table import Table
    from rich.text import Text

    table = Table(box=None, pad_edge=False, header_style="bold")
    for col in ("Type", "Version", "Extra", "Description"):
        table.add_column(col)
    for row in rows:
        if row["error"]:
            about = Text(f"BROKEN: {row['error']}", style="red")
        else:
            lines = [row["description"] or "-"]
            if verbose:
                lines += [_param_line(n, p) for n, p in row["params"].items()] or ["  (no params)"]
            about = Text("\n".join(lines))
        table.add_row(row["name"], row["version"] or "-", row["extra"] or "-", about)
    return table
