"""The spec pipeline: read → render (Jinja) → YAML nodes → parse → validate → model.

Owns ``load_spec``, ``render_spec`` and ``spec_from_dict``. Every problem found on the way is
collected and raised as one :class:`SpecError`; no foreign exception escapes. Positions refer
to the rendered document, which is line-for-line the source when no ``{% %}`` block is used.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from osmo.errors import Diagnostic, SpecError
from osmo.spec import isolation, yamlnodes
from osmo.spec.files import read_spec_file
from osmo.spec.localfiles import LocalFiles
from osmo.spec.model import WorkflowSpec
from osmo.spec.parse import parse_document
from osmo.spec.reader import Ctx
from osmo.spec.shapes import Reduced, expand, reduce_tasks
from osmo.spec.typed import TypeResolver, apply_resolved, check_types
from osmo.spec.validate import validate
from osmo.spec.values import split_items

__all__ = ["load_spec", "render_spec", "spec_from_dict"]

_STRING = "<string>"


def _source(path: str | os.PathLike[str] | None, text: str | None,
            filename: str | None) -> tuple[str, str, Path]:
    """(text, file name for messages, folder that ``localpath`` is relative to)."""
    if path is None:
        if text is None:
            raise SpecError([Diagnostic(filename or _STRING, 0, 0, "no spec given: pass a "
                                        "file path or text")])
        name = filename or _STRING
        base = Path(filename).parent if filename and not filename.startswith("<") else Path()
        return text, name, base
    name = filename or os.fspath(path)
    return read_spec_file(path, name), name, Path(path).parent


def _render(text: str, file: str, set_values: Sequence[str], set_strings: Sequence[str],
            extra: list[Diagnostic]) -> str:
    """The rendered text; templates run in a child under memory and time limits."""
    rendered, diags = isolation.render(text, file, set_values, set_strings)
    if rendered is None or extra:
        raise SpecError(diags + extra)
    return rendered


def _with_env(spec: WorkflowSpec, env: dict[str, str]) -> WorkflowSpec:
    """``--set-env``: add/override variables in every task's environment."""
    if not env:
        return spec
    groups = tuple(
        dataclasses.replace(g, tasks=tuple(
            dataclasses.replace(t, environment={**t.environment, **env}) for t in g.tasks))
        for g in spec.groups)
    return dataclasses.replace(spec, groups=groups)


def _build(text: str, file: str, local: LocalFiles, env: dict[str, str],
           types: TypeResolver | None) -> WorkflowSpec:
    """Rendered YAML text → validated model (raises SpecError with every problem)."""
    root, diags = yamlnodes.load_nodes(text, file)
    if root is None and diags:
        raise SpecError(diags)
    ctx = Ctx(file, diags)
    spec = _check(ctx, root, local, types)
    if spec is None:
        raise SpecError(ctx.diags)
    return _with_env(spec, env)


def _check(ctx: Ctx, root: yamlnodes.Node | None, local: LocalFiles,
           types: TypeResolver | None, reduced: Reduced | None = None) -> WorkflowSpec | None:
    """Parse and validate a node tree; None when ``ctx`` holds a problem afterwards.

    ``reduced``: the tree is of ``reduced.data``; its tasks are put back before validation.
    """
    parsed = parse_document(ctx, root, local)
    if parsed is not None and reduced is not None:
        if ctx.diags:
            return None
        expand(ctx, parsed, reduced)
    if parsed is not None:
        if types is not None:
            parsed.spec = apply_resolved(parsed.spec, check_types(ctx, parsed, types))
        validate(ctx, parsed)
    return None if ctx.diags or parsed is None else parsed.spec


def load_spec(path: str | os.PathLike[str] | None = None, *, text: str | None = None,
              filename: str | None = None, set_values: Sequence[str] = (),
              set_strings: Sequence[str] = (), set_env: Sequence[str] = (),
              types: TypeResolver | None = None,
              allow_localpath: Sequence[str | os.PathLike[str]] = (),
              deny_localpath: Sequence[str | os.PathLike[str]] = ()) -> WorkflowSpec:
    """Read, render, parse and validate a workflow spec.

    Args:
        path: the spec file; ``localpath`` entries are relative to its folder, and must stay
            inside its tree (``osmo.spec.localfiles``).
        text: the spec's text instead of a file (``localpath`` then relative to the folder of
            ``filename`` if it is a path, else the current folder).
        filename: the name used in diagnostics (defaults to ``path`` or ``<string>``).
        set_values: ``NAME=VALUE`` template overrides (``--set``), cast to int, float or str.
        set_strings: ``NAME=VALUE`` template overrides kept as strings (``--set-string``).
        set_env: ``NAME=VALUE`` added to every task's environment (``--set-env``).
        types: [ext] resolves ``type:`` names; when given, typed tasks are checked against
            their types (params, resources) and get ``TaskSpec.resolved``. Without it,
            ``type``/``params`` are not checked (see ``osmo.spec.typed``).
        allow_localpath: more folders whose files ``localpath`` may name (``--allow-localpath``).
        deny_localpath: folders no ``localpath`` may name, even inside an allowed one (the
            ``OSMO_HOME`` in effect is always one of them).

    Returns:
        the validated model.

    Raises:
        SpecError: with every problem found, each as ``file:line:col: message``. Positions
            refer to the rendered document (identical to the source without ``{% %}`` blocks).
    """
    source, file, base_dir = _source(path, text, filename)
    env, env_diags = split_items(file, "--set-env", set_env)
    rendered = _render(source, file, set_values, set_strings, env_diags)
    local = LocalFiles.under(base_dir, allow=allow_localpath, deny=deny_localpath)
    return _build(rendered, file, local, env, types)


def render_spec(path: str | os.PathLike[str] | None = None, *, text: str | None = None,
                filename: str | None = None, set_values: Sequence[str] = (),
                set_strings: Sequence[str] = ()) -> str:
    """The spec after templating (what ``osmo submit --dry-run`` prints).

    Raises:
        SpecError: when the file cannot be read or the template fails.
    """
    source, file, _ = _source(path, text, filename)
    return _render(source, file, set_values, set_strings, [])


def spec_from_dict(d: dict[str, Any], *, filename: str = "<stored>",
                   types: TypeResolver | None = None) -> WorkflowSpec:
    """The model from plain data such as ``spec_to_dict`` returns (no templating).

    ``types`` is as for :func:`load_spec`. Data names no ``localpath`` (it reads no local
    file: a ``localpath`` is a spec error).

    Raises:
        SpecError: if the data is not a valid spec.
    """
    if not isinstance(d, dict):
        raise SpecError([Diagnostic(filename, 0, 0, "a stored spec must be a mapping")])
    # Valid data is checked without YAML text (fast: no dump, no parse); data with a problem
    # is checked again the YAML way, so its messages carry positions in that text.
    # Tasks written alike are parsed once (osmo.spec.shapes).
    reduced = reduce_tasks(d)
    root = yamlnodes.from_plain(d if reduced is None else reduced.data, filename)
    if root is not None:
        spec = _check(Ctx(filename, []), root, LocalFiles.none(), types, reduced)
        if spec is not None:
            return spec
    try:
        text = yamlnodes.dump(d)
    except TypeError as exc:
        raise SpecError([Diagnostic(filename, 0, 0, str(exc))]) from None
    return _build(text, filename, LocalFiles.none(), {}, types)
