"""Jinja templating of spec files: the only module of osmo that imports ``jinja2``.

It owns rendering the whole file in a sandbox with ``StrictUndefined``, bounded in output size
(``isolation.MAX_RENDERED``), loop size (:data:`MAX_RANGE`), bracket nesting
(:data:`MAX_NESTING`) and time (checked as loops run). Special tokens (``{{output}}``...) are
protected before rendering and restored after, so ``--set output=...`` has no effect on them.
Every jinja error becomes a :class:`Diagnostic`. The context comes from ``osmo.spec.values``.

It runs only in the child processes of ``osmo.spec.isolation``, which bound its memory and
wall time from outside; the checks here just fail earlier, with a position.

Positions in diagnostics found *after* rendering (YAML and schema errors) refer to the rendered
document, which is line-for-line identical to the source when the file uses no ``{% %}``
blocks; ``osmo submit --dry-run`` prints it.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from typing import Any

import jinja2
from jinja2.sandbox import SandboxedEnvironment

from osmo.errors import Diagnostic
from osmo.names import did_you_mean
from osmo.spec import isolation, tokens

__all__ = ["MAX_NESTING", "MAX_RANGE", "nesting_message", "render"]

MAX_RANGE = 100_000  # items of one range()
MAX_NESTING = 30  # brackets inside one {{ }} or {% %}; jinja's parser recurses per level
MAX_UNDEFINED = 20  # undefined variables reported from one file
_TEMPLATE_FILE = "<template>"


class _LimitExceededError(Exception):
    """A sandbox bound was hit; the message says which."""


class _Deadline:
    """The wall-time budget of one rendering, checked as loops and output chunks go by."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self._at = time.monotonic() + seconds

    def check(self) -> None:
        if time.monotonic() > self._at:
            raise _LimitExceededError(isolation.time_message(self.seconds))


class _BoundedRange:
    """``range()`` for templates: refuses huge ranges and checks the time budget as it runs."""

    def __init__(self, deadline: _Deadline, *args: int) -> None:
        self._range = range(*args)
        if len(self._range) > MAX_RANGE:
            raise _LimitExceededError(f"range() of {len(self._range)} items exceeds the "
                                      f"template limit of {MAX_RANGE}")
        self._deadline = deadline

    def __len__(self) -> int:
        return len(self._range)

    def __getitem__(self, index: Any) -> Any:
        return self._range[index]

    def __iter__(self) -> Iterator[int]:
        for n, value in enumerate(self._range):
            if n % 1000 == 0:
                self._deadline.check()
            yield value


class _Sandbox(SandboxedEnvironment):
    """The sandbox, with ``*`` and ``**`` bounded so one expression cannot exhaust memory."""

    intercepted_binops = frozenset(["*", "**"])

    def call_binop(self, context: Any, operator: str, left: Any, right: Any) -> Any:
        if operator == "*":
            for seq, n in ((left, right), (right, left)):
                if isinstance(seq, str | list | tuple) and isinstance(n, int) and (
                        len(seq) * n > isolation.MAX_RENDERED):
                    raise _LimitExceededError("a repeated string or list is too large")
        if operator == "**" and isinstance(right, int | float) and abs(right) > 1000:
            raise _LimitExceededError("exponents above 1000 are not allowed in templates")
        return super().call_binop(context, operator, left, right)


_JINJA_SPAN = re.compile(r"\{\{.*?\}\}|\{%.*?%\}")


def _find(source_lines: list[str], name: str, lineno: int | None) -> tuple[int, int]:
    """Line and column of ``name`` inside a ``{{ }}``/``{% %}`` of the source.

    Line ``lineno`` (jinja's) is preferred when given.
    """
    word = re.compile(rf"\b{re.escape(name)}\b")
    order = [lineno] if lineno else []
    for number in order + list(range(1, len(source_lines) + 1)):
        if 0 < number <= len(source_lines):
            for span in _JINJA_SPAN.finditer(source_lines[number - 1]):
                match = word.search(span.group(0))
                if match:
                    return number, span.start() + match.start() + 1
    return lineno or 1, 1


def _undefined_name(exc: jinja2.UndefinedError) -> str | None:
    """The variable named by jinja's "'x' is undefined" (None for a missing attribute)."""
    match = re.fullmatch(r"'([^']+)' is undefined", exc.message or "")
    return match.group(1) if match else None


def _undefined_diag(name: str, exc: BaseException, context: dict[str, Any], file: str,
                    lines: list[str]) -> Diagnostic:
    line, col = _find(lines, name, _template_line(exc) or None)
    hint = did_you_mean(name, context)
    return Diagnostic(file, line, col, f"undefined template variable '{name}'{hint}; define "
                      f"it under 'default-values:' or pass --set {name}=...")


def _template_line(exc: BaseException) -> int:
    tb, line = exc.__traceback__, 0
    while tb is not None:
        if tb.tb_frame.f_code.co_filename == _TEMPLATE_FILE:
            line = tb.tb_lineno
        tb = tb.tb_next
    return line


def _run(template: jinja2.Template, context: dict[str, Any], deadline: _Deadline) -> str:
    parts, size = [], 0
    for chunk in template.generate(context):
        size += len(chunk)
        if size > isolation.MAX_RENDERED:
            raise _LimitExceededError(
                f"rendered spec exceeds {isolation.MAX_RENDERED // 2**20} MiB")
        deadline.check()
        parts.append(chunk)
    return "".join(parts)


def nesting_message() -> str:
    """What a template nested too deeply for the parser is told (the limit named)."""
    return (f"template expressions nest too deeply: at most {MAX_NESTING} levels of "
            "brackets (very long chains of operators count too); split the expression")


_SPAN_START = re.compile(r"\{\{|\{%")
_OPEN, _CLOSE, _QUOTES = "([{", ")]}", "'\""


def _too_deep(text: str) -> tuple[int, int] | None:
    """Where (line, col) a tag first nests brackets deeper than :data:`MAX_NESTING`.

    Tags are ``{{ }}``/``{% %}``; string literals are skipped; None if nowhere. Checked before jinja
    parses, since its parser recurses once per level and would fail without a position.
    """
    pos = 0
    while (start := _SPAN_START.search(text, pos)) is not None:
        i, depth, quote = start.end(), 0, ""
        while i < len(text):
            c = text[i]
            if quote:
                quote = "" if c == quote else quote
                i += 1 if c == "\\" else 0
            elif c in _QUOTES:
                quote = c
            elif depth == 0 and text.startswith(("}}", "%}"), i):
                break
            elif c in _OPEN:
                depth += 1
                if depth > MAX_NESTING:
                    line = text.count("\n", 0, i) + 1
                    return line, i - text.rfind("\n", 0, i)
            elif c in _CLOSE:
                depth = max(depth - 1, 0)
            i += 1
        pos = i + 2
    return None


def render(text: str, file: str, context: dict[str, Any], *,
           seconds: float = isolation.MAX_SECONDS) -> tuple[str | None, list[Diagnostic]]:
    """Render ``text`` with ``context`` in the sandbox; special tokens pass through untouched.

    Only ``osmo.spec.isolation`` calls this, in a child process under memory and time limits
    (``seconds`` is its time limit, checked here too so that loops stop with a position).

    Returns:
        the rendered text (None on any error) and the diagnostics.
    """
    protected, saved = tokens.protect(text)
    deep = _too_deep(protected)
    if deep is not None:
        return None, [Diagnostic(file, deep[0], deep[1], nesting_message())]
    deadline = _Deadline(seconds)
    env = _Sandbox(undefined=jinja2.StrictUndefined, keep_trailing_newline=True, autoescape=False)
    env.globals["range"] = lambda *args: _BoundedRange(deadline, *args)
    try:
        template = env.from_string(protected)
    except jinja2.TemplateSyntaxError as exc:
        return None, [Diagnostic(file, exc.lineno or 1, 1, f"template syntax error: {exc.message}")]
    rendered, diags = _render_all(template, context, deadline, file, protected.splitlines())
    return (None if rendered is None else tokens.restore(rendered, saved)), diags


def _render_all(template: jinja2.Template, context: dict[str, Any], deadline: _Deadline, file: str,
                lines: list[str]) -> tuple[str | None, list[Diagnostic]]:
    """Render, reporting every undefined variable the rendering actually evaluates.

    Each undefined name is reported, then bound to a permissive placeholder and the template
    rendered again (at most :data:`MAX_UNDEFINED` times). Only names that are evaluated count,
    so a variable inside an ``{% if x is defined %}`` branch not taken is not an error. Any
    other error after an undefined name is taken as its consequence and not reported.
    """
    values = dict(context)
    diags: list[Diagnostic] = []
    for _ in range(MAX_UNDEFINED):
        try:
            rendered = _run(template, values, deadline)
            return (None, diags) if diags else (rendered, [])
        except jinja2.UndefinedError as exc:
            name = _undefined_name(exc)
            if name is None or name in values:
                return None, diags or [_error_diag(exc, file)]
            diags.append(_undefined_diag(name, exc, context, file, lines))
            values[name] = jinja2.ChainableUndefined(name=name)
        except Exception as exc:  # any failure inside user template code
            return None, diags or [_error_diag(exc, file)]
    return None, diags


def _error_diag(exc: BaseException, file: str) -> Diagnostic:
    return Diagnostic(file, _template_line(exc) or 1, 1, f"template error: {_describe(exc)}")


def _describe(exc: BaseException) -> str:
    if isinstance(exc, jinja2.UndefinedError):
        return f"{exc.message}; check the name or define it under 'default-values:'"
    if isinstance(exc, _LimitExceededError | jinja2.TemplateError):
        return str(exc)
    if isinstance(exc, MemoryError):
        return isolation.memory_message()
    if isinstance(exc, RecursionError):
        return nesting_message()
    return f"{type(exc).__name__}: {exc}"
