"""Jinja templating of spec files: the only module of osmo that imports ``jinja2``.

It owns the rendering context (``default-values`` overridden by ``--set``/``--set-string``)
and rendering the whole file in a sandbox with ``StrictUndefined``, bounded in output size
(:data:`MAX_RENDERED`), loop size (:data:`MAX_RANGE`) and time (:data:`MAX_SECONDS`). Special
tokens (``{{output}}``...) are protected before rendering and restored after, so ``--set
output=...`` has no effect on them. Every jinja error becomes a :class:`Diagnostic`.

Positions in diagnostics found *after* rendering (YAML and schema errors) refer to the rendered
document, which is line-for-line identical to the source when the file uses no ``{% %}``
blocks; ``osmo submit --dry-run`` prints it.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator, Sequence
from typing import Any

import jinja2
from jinja2.sandbox import SandboxedEnvironment

from osmo.errors import Diagnostic
from osmo.spec import tokens
from osmo.spec.reader import did_you_mean
from osmo.spec.yamlnodes import Map, load_nodes, to_plain

__all__ = ["MAX_RANGE", "MAX_RENDERED", "MAX_SECONDS", "build_context", "render"]

MAX_RENDERED = 16 * 1024 * 1024  # characters of rendered text
MAX_RANGE = 100_000  # items of one range()
MAX_SECONDS = 10.0  # wall time of one rendering
MAX_UNDEFINED = 20  # undefined variables reported from one file
_TEMPLATE_FILE = "<template>"


class _LimitExceededError(Exception):
    """A sandbox bound was hit; the message says which."""


class _BoundedRange:
    """``range()`` for templates: refuses huge ranges and checks the time budget as it runs."""

    def __init__(self, deadline: float, *args: int) -> None:
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
                _check_time(self._deadline)
            yield value


def _check_time(deadline: float) -> None:
    if time.monotonic() > deadline:
        raise _LimitExceededError(f"template rendering took longer than {MAX_SECONDS:g}s")


class _Sandbox(SandboxedEnvironment):
    """The sandbox, with ``*`` and ``**`` bounded so one expression cannot exhaust memory."""

    intercepted_binops = frozenset(["*", "**"])

    def call_binop(self, context: Any, operator: str, left: Any, right: Any) -> Any:
        if operator == "*":
            for seq, n in ((left, right), (right, left)):
                if isinstance(seq, str | list | tuple) and isinstance(n, int) and (
                        len(seq) * n > MAX_RENDERED):
                    raise _LimitExceededError("a repeated string or list is too large")
        if operator == "**" and isinstance(right, int | float) and abs(right) > 1000:
            raise _LimitExceededError("exponents above 1000 are not allowed in templates")
        return super().call_binop(context, operator, left, right)


def _cast(value: str) -> Any:
    for kind in (int, float):
        try:
            return kind(value)
        except ValueError:
            pass
    return value


def _split_items(file: str, flag: str,
                 items: Sequence[str]) -> tuple[dict[str, str], list[Diagnostic]]:
    out: dict[str, str] = {}
    diags = []
    for item in items:
        name, eq, value = item.partition("=")
        if not eq or not name.strip():
            diags.append(Diagnostic(file, 0, 0, f"{flag} {item!r}: expected NAME=VALUE"))
        else:
            out[name.strip()] = value
    return out, diags


def _default_values_block(text: str) -> str | None:
    """The top-level ``default-values:`` block, with earlier lines blanked so that line
    numbers stay those of the file (the raw file may not be YAML before rendering)."""
    lines = text.splitlines()
    for start, line in enumerate(lines):
        if re.match(r"default-values\s*:", line):
            end = start + 1
            while end < len(lines) and not re.match(r"[^\s#]", lines[end]):
                end += 1
            return "\n" * start + "\n".join(lines[start:end]) + "\n"
    return None


def build_context(text: str, file: str, set_values: Sequence[str] = (),
                  set_strings: Sequence[str] = ()) -> tuple[dict[str, Any], list[Diagnostic]]:
    """The template context: ``default-values`` of ``text``, then ``--set`` (cast to int,
    then float, else kept as a string), then ``--set-string`` (kept as a string)."""
    context: dict[str, Any] = {}
    diags: list[Diagnostic] = []
    block = _default_values_block(text)
    if block is not None:
        root, diags = load_nodes(block, file)
        values = root.get("default-values") if isinstance(root, Map) else None
        if isinstance(values, Map):
            context.update(to_plain(values))
    sets, bad = _split_items(file, "--set", set_values)
    strings, bad2 = _split_items(file, "--set-string", set_strings)
    context.update({k: _cast(v) for k, v in sets.items()})
    context.update(strings)
    return context, diags + bad + bad2


_JINJA_SPAN = re.compile(r"\{\{.*?\}\}|\{%.*?%\}")


def _find(source_lines: list[str], name: str, lineno: int | None) -> tuple[int, int]:
    """Line and column of ``name`` inside a ``{{ }}``/``{% %}`` of the source, preferring
    line ``lineno`` (jinja's) when given."""
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


def _run(template: jinja2.Template, context: dict[str, Any], deadline: float) -> str:
    parts, size = [], 0
    for chunk in template.generate(context):
        size += len(chunk)
        if size > MAX_RENDERED:
            raise _LimitExceededError(f"rendered spec exceeds {MAX_RENDERED // 2**20} MiB")
        _check_time(deadline)
        parts.append(chunk)
    return "".join(parts)


def render(text: str, file: str, context: dict[str, Any]) -> tuple[str | None, list[Diagnostic]]:
    """Render ``text`` with ``context`` in the sandbox; special tokens pass through untouched.

    Returns:
        the rendered text (None on any error) and the diagnostics.
    """
    protected, saved = tokens.protect(text)
    deadline = time.monotonic() + MAX_SECONDS
    env = _Sandbox(undefined=jinja2.StrictUndefined, keep_trailing_newline=True, autoescape=False)
    env.globals["range"] = lambda *args: _BoundedRange(deadline, *args)
    try:
        template = env.from_string(protected)
    except jinja2.TemplateSyntaxError as exc:
        return None, [Diagnostic(file, exc.lineno or 1, 1, f"template syntax error: {exc.message}")]
    rendered, diags = _render_all(template, context, deadline, file, protected.splitlines())
    return (None if rendered is None else tokens.restore(rendered, saved)), diags


def _render_all(template: jinja2.Template, context: dict[str, Any], deadline: float, file: str,
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
    return f"{type(exc).__name__}: {exc}"
