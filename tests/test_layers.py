"""The import layers of DESIGN.md, package by package: lower layers never import higher ones.

spec → graph → scheduler (pure) → adapters (store, transport, artifacts, runtimes, record,
...) → workers → server composition → SDK → CLI, over a bottom layer of leaf modules that
import nothing else of osmo. Every ``import`` counts, also one inside a function (a lazy
import is still a dependency) or under ``TYPE_CHECKING``. Plugins are reached only through
entry points: no module of ``osmo`` imports ``osmo_plugins``.
"""

from __future__ import annotations

import ast
import functools
import subprocess
import sys
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import REPO

PACKAGE = REPO / "osmo"

LAYERS: tuple[tuple[str, frozenset[str]], ...] = (
    ("bottom", frozenset({"errors", "names", "status", "config", "params", "layout",
                          "version"})),
    ("spec", frozenset({"spec"})),
    ("graph", frozenset({"graph"})),
    ("scheduler", frozenset({"scheduler"})),
    ("adapters", frozenset({"executor", "options", "store", "transport", "artifacts", "runtime",
                            "record", "urls", "tasktypes"})),
    ("workers", frozenset({"worker"})),
    ("server", frozenset({"server"})),
    ("sdk", frozenset({"sdk", "testing", "__init__"})),
    ("cli", frozenset({"cli", "__main__"})),
)
"""Bottom to top. A part is a subpackage or a top-level module of ``osmo`` (``__init__``
is the package's lazy public facade)."""

RANK = {part: rank for rank, (_, parts) in enumerate(LAYERS) for part in parts}

APART: dict[str, frozenset[str]] = {
    "sdk": frozenset({"server", "worker", "runtime"}),
}
"""Lower parts a part must not import although its layer is above theirs: the SDK is a
client of a server, wherever that server runs, so it holds nothing of one (what it shares
with the server, such as ``ServerOptions``, lives in a lower part)."""

# Known exceptions, each with its reason; the test fails when one is no longer needed.
ALLOWED: dict[tuple[str, str], str] = {}


def _part(module: str) -> str:
    """The layer part of ``osmo.a.b`` (``a``), of ``osmo`` itself (``__init__``)."""
    pieces = module.split(".")
    return pieces[1] if len(pieces) > 1 else "__init__"


def _module_of(path: Path) -> str:
    rel = path.relative_to(REPO).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imported(tree: ast.AST) -> Iterator[tuple[str, int]]:
    """Every module an ``import`` names (``from osmo import x``: ``osmo.x`` when x is a
    module, else ``osmo``), with its line."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module == "osmo":
                for alias in node.names:
                    sub = PACKAGE / alias.name
                    is_module = sub.is_dir() or sub.with_suffix(".py").is_file()
                    yield (f"osmo.{alias.name}" if is_module else "osmo"), node.lineno
            else:
                yield node.module, node.lineno
        elif isinstance(node, ast.ImportFrom) and node.level:
            raise AssertionError(f"relative import at line {node.lineno}: use absolute ones")


@functools.cache
def _edges() -> dict[tuple[str, str], list[str]]:
    """(importing part, imported part) → where, for imports across parts."""
    edges: dict[tuple[str, str], list[str]] = defaultdict(list)
    for path in sorted(PACKAGE.rglob("*.py")):
        source = _part(_module_of(path)) if path.parent != PACKAGE else path.stem
        for name, line in _imported(ast.parse(path.read_text(), str(path))):
            if name.split(".")[0] == "osmo_plugins":
                edges[(source, "osmo_plugins")].append(f"{path.relative_to(REPO)}:{line}")
            elif name == "osmo" or name.startswith("osmo."):
                target = _part(name)
                if target != source:
                    edges[(source, target)].append(f"{path.relative_to(REPO)}:{line}")
    return edges


def test_every_part_has_a_layer() -> None:
    parts = {p.stem if p.is_file() else p.name for p in PACKAGE.iterdir()
             if (p.suffix == ".py" or (p / "__init__.py").is_file())}
    assert parts - RANK.keys() == set(), "add the new part to LAYERS (and to DESIGN.md)"
    assert RANK.keys() - parts == set(), "LAYERS names a part that does not exist"


def test_no_layer_imports_a_higher_one() -> None:
    upward = []
    for (source, target), where in sorted(_edges().items()):
        if target == "osmo_plugins" or (source, target) in ALLOWED:
            continue
        if RANK[target] > RANK[source]:
            upward.append(f"{source} ({LAYERS[RANK[source]][0]}) imports {target} "
                          f"({LAYERS[RANK[target]][0]}) at {', '.join(where)}")
    assert upward == []


def test_parts_kept_apart_do_not_import_each_other() -> None:
    crossing = [f"{source} imports {target} at {', '.join(where)}"
                for (source, target), where in sorted(_edges().items())
                if target in APART.get(source, ()) and (source, target) not in ALLOWED]
    assert crossing == []


def _loaded_by(modules: list[str], parts: list[str]) -> list[str]:
    """The modules of ``osmo.<part>`` a fresh interpreter holds after importing ``modules``."""
    code = ("import sys\n" + "".join(f"import {m}\n" for m in modules)
            + "print('\\n'.join(m for m in sys.modules if m.split('.')[:2] in "
              f"{[['osmo', part] for part in parts]!r}))")
    return subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                          text=True, check=True).stdout.split()


def test_importing_the_sdk_loads_no_server_worker_or_runtime_module() -> None:
    """What the rule above means at run time: ``import osmo.sdk.*`` stays a client's import."""
    sdk = sorted(_module_of(p) for p in (PACKAGE / "sdk").glob("*.py"))
    assert _loaded_by(sdk, sorted(APART["sdk"])) == []


def test_starting_the_cli_loads_no_scheduler_server_or_runtime_module() -> None:
    """Every ``osmo`` command imports ``osmo.cli.main`` first: what only a server or a runtime
    needs is imported where it runs (the scheduler's types alone cost ~16 modules, ~40 ms)."""
    assert _loaded_by(["osmo.cli.main"], ["runtime", "scheduler", "server", "spec", "store"]) == []


def test_the_core_reaches_plugins_only_through_entry_points() -> None:
    reaching = {src: where for (src, dst), where in _edges().items() if dst == "osmo_plugins"
                and (src, dst) not in ALLOWED}
    assert reaching == {}


@pytest.mark.parametrize("layer", [name for name, _ in LAYERS])
def test_parts_of_one_layer_form_no_cycle(layer: str) -> None:
    parts = dict(LAYERS)[layer]
    graph = {p: {t for (s, t) in _edges() if s == p and t in parts} for p in parts}
    done: set[str] = set()

    def visit(part: str, path: tuple[str, ...]) -> None:
        assert part not in path, f"import cycle: {' → '.join((*path, part))}"
        if part in done:
            return
        for nxt in sorted(graph[part]):
            visit(nxt, (*path, part))
        done.add(part)

    for part in sorted(parts):
        visit(part, ())


def test_every_allowed_exception_is_still_needed() -> None:
    assert set(ALLOWED) <= set(_edges())
