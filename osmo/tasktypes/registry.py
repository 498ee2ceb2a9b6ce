"""Finding task types by the name a spec writes, lazily, and listing the installed ones.

A task's ``type:`` is one of:

- an **installed type**: the name of an entry point of the ``osmo.task_types`` group
  (``"sim.rollout" = "osmo_plugins.sim.rollout:ROLLOUT [sim]"`` in a plugin's
  ``pyproject.toml``). The optional ``[extra]`` after the object reference is the standard
  entry-point syntax for extras; osmo reads it to say ``pip install "osmo[sim]"`` when the
  type's dependencies are missing (a type that loads says it itself: ``TaskType.extra``);
- a **custom type**: ``"module:attr"`` (``mypkg.tasks:rollout``). The module is imported
  with the given search folders first on ``sys.path`` (for a YAML file, its folder).

The object found may be a :class:`~osmo.tasktypes.api.TaskType` instance (a function wrapped
by ``@task_type`` is one) or a class with the same attributes, which is instantiated without
arguments. Nothing is imported until a name is resolved; ``import osmo`` never loads plugins.

Custom modules are imported *in isolation* (:class:`Resolver`): the search folders are on
``sys.path`` only during the import, and the modules loaded from them are dropped afterwards,
so a long-running server can resolve ``tasks:x`` for two projects that both have a
``tasks.py``, and an edited module is read afresh at the next submit.
"""

from __future__ import annotations

import functools
import importlib
import importlib.metadata
import importlib.util
import inspect
import os
import sys
import threading
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from osmo.errors import UsageError
from osmo.names import object_ref
from osmo.tasktypes.api import Param, TaskType
from osmo.tasktypes.params import schema_problems

__all__ = ["GROUP", "Resolver", "TaskTypeError", "TypeEntry", "builtin_type", "entry_points",
           "extra_of",
           "import_failure", "is_custom", "list_types", "ref_of", "resolve", "shape_problems"]

GROUP = "osmo.task_types"
"""The entry-point group plugins register their task types in."""

_IMPORT_LOCK = threading.RLock()


class TaskTypeError(UsageError):
    """A task type cannot be found, imported, or does not have the shape of a task type."""


@dataclass(frozen=True)
class TypeEntry:
    """One installed task type as ``osmo plugins list`` shows it.

    Attributes:
        name: the entry-point name (what ``type:`` says).
        ref: the object reference (``module:attr``).
        version, description, extra: from the type (None/"" when it could not be loaded).
        params: its parameter schema (empty when broken).
        error: why it could not be loaded (None when it loads), with a pip hint if known.
        distribution: the installed distribution that registers it.
    """

    name: str
    ref: str
    version: str | None = None
    description: str = ""
    extra: str | None = None
    params: Mapping[str, Param] = field(default_factory=dict)
    error: str | None = None
    distribution: str | None = None


def is_custom(ref: str) -> bool:
    """True for a ``module:attr`` reference, False for an installed type's name."""
    return ":" in ref


_SHIPPED = ("osmo", "osmo_plugins")  # the packages of osmo's own distribution


@functools.cache  # where a package was imported from does not change while we run
def shipped_packages() -> dict[str, Path]:
    """The folders of osmo's own packages (``osmo``, ``osmo_plugins``) this process uses.

    A typed task that runs in its image is shown these, read-only, and nothing else of the
    install (``osmo.runtime.container.layout``): the image brings Python and the libraries.
    """
    out = {}
    for name in _SHIPPED:
        spec = importlib.util.find_spec(name)  # locates it without importing it
        if spec is not None and spec.submodule_search_locations:
            out[name] = Path(next(iter(spec.submodule_search_locations))).resolve()
    return out


_entries_seen: dict[str, tuple[tuple[tuple[str, int], ...],
                                importlib.metadata.EntryPoint | None]] = {}


def _installed(ref: str) -> importlib.metadata.EntryPoint | None:
    """The entry point of the installed type ``ref`` (None: none, or a custom type).

    Kept while no folder of ``sys.path`` changed (their mtimes, which any distribution
    installed or removed there changes: ``importlib.metadata`` keeps its own lookups by the
    same rule), so a pool asks it for each attempt without reading every installed
    distribution's entry points each time.
    """
    if is_custom(ref):
        return None
    stamp = _path_stamp()
    seen = _entries_seen.get(ref)
    if seen is None or seen[0] != stamp:
        seen = _entries_seen[ref] = (stamp, entry_points().get(ref))
    return seen[1]


def builtin_type(ref: str) -> bool:
    """Whether ``ref`` names a type osmo ships (an entry point of osmo's own distribution).

    Its import code is osmo's own, trusted as osmo is: a sandboxed warm runner may import it
    (``osmo.runtime.process.warm``). A custom type, or another distribution's, is not.
    """
    ep = _installed(ref)
    return (ep is not None and ep.dist is not None and ep.dist.name == "osmo"
            and ep.module.split(".", 1)[0] in _SHIPPED)


def entry_target(ref: str) -> str | None:
    """An installed type's ``module:attr`` (its entry point's; None: not installed, custom).

    What a runner in a task's image imports: the image has osmo's code, not the node's
    package metadata.
    """
    ep = _installed(ref)
    return f"{ep.module}:{ep.attr}" if ep is not None else None


def _path_stamp() -> tuple[tuple[str, int], ...]:
    """Each ``sys.path`` folder with its mtime (-1: missing)."""
    stamp = []
    for folder in sys.path:
        try:
            stamp.append((folder, os.stat(folder or ".").st_mtime_ns))
        except OSError:
            stamp.append((folder, -1))
    return tuple(stamp)


def entry_points(group: str = GROUP) -> dict[str, importlib.metadata.EntryPoint]:
    """The installed entry points of ``group`` by name (the first on ``sys.path`` wins)."""
    found: dict[str, importlib.metadata.EntryPoint] = {}
    for ep in importlib.metadata.entry_points(group=group):
        found.setdefault(ep.name, ep)  # the first distribution on sys.path wins
    return found


def extra_of(ep: importlib.metadata.EntryPoint) -> str | None:
    """The extra an entry point names (``module:attr [extra]``), None without one."""
    return ep.extras[0] if ep.extras else None


def import_failure(what: str, module: str, exc: BaseException, extra: str | None) -> str:
    """Why importing ``module`` for ``what`` failed; a pip hint when a dependency is missing."""
    if isinstance(exc, ModuleNotFoundError) and exc.name and not (
            module == exc.name or module.startswith(exc.name + ".")):
        hint = f"; install it with: pip install \"osmo[{extra}]\"" if extra else ""
        return f"{what} needs module '{exc.name}', which is not installed{hint}"
    if isinstance(exc, ModuleNotFoundError):
        return f"{what}: cannot import module '{module}' ({exc})"
    return f"{what}: importing '{module}' failed: {type(exc).__name__}: {exc}"


def shape_problems(obj: Any) -> list[str]:
    """What keeps ``obj`` from being a task type (empty when it has the declared shape)."""
    problems = []
    for attr, kinds in (("name", str), ("version", str), ("description", str)):
        if not isinstance(getattr(obj, attr, None), kinds):
            problems.append(f"'{attr}' must be a string, got {getattr(obj, attr, None)!r}")
    if not isinstance(getattr(obj, "resources", None), Mapping):
        problems.append("'resources' must be a mapping like {'cpu': 2}")
    extra = getattr(obj, "extra", None)
    if extra is not None and not isinstance(extra, str):
        problems.append(f"'extra' must be a string or None, got {extra!r}")
    problems += schema_problems(getattr(obj, "params", None))
    run = getattr(obj, "run", None)
    if not callable(run):
        problems.append("'run' must be a method run(ctx)")
    else:
        try:
            inspect.signature(run).bind(object())
        except TypeError:
            problems.append(f"'run' must take exactly one argument (ctx); it is run"
                            f"{inspect.signature(run)}")
        except ValueError:  # no signature (builtin): trust it
            pass
    return problems


def _checked(obj: Any, what: str) -> TaskType:
    if inspect.isclass(obj):
        try:
            obj = obj()
        except Exception as exc:
            raise TaskTypeError(f"{what}: cannot create it with no arguments: "
                                f"{type(exc).__name__}: {exc}") from exc
    problems = shape_problems(obj)
    if problems:
        raise TaskTypeError(f"{what} is not a task type: " + "; ".join(problems))
    return obj  # type: ignore[no-any-return]


@contextmanager
def _search(paths: Sequence[str]) -> Iterator[None]:
    """Import with ``paths`` first on sys.path, then forget what it loaded from them.

    Modules imported earlier (e.g. by the user's own script) stay.
    """
    if not paths:
        yield
        return
    roots = tuple(os.path.join(os.path.abspath(p), "") for p in paths)
    with _IMPORT_LOCK:
        saved, before = list(sys.path), set(sys.modules)
        sys.path[:0] = [os.path.abspath(p) for p in paths]
        importlib.invalidate_caches()
        try:
            yield
        finally:
            sys.path[:] = saved
            for name in set(sys.modules) - before:
                if str(getattr(sys.modules[name], "__file__", None) or "").startswith(roots):
                    del sys.modules[name]


def _module_root(module: Any) -> str | None:
    """The folder that must be on sys.path to import ``module`` (None if installed)."""
    file = getattr(module, "__file__", None)
    if not file:
        return None
    root = os.path.dirname(os.path.abspath(file))
    depth = module.__name__.count(".") + (1 if os.path.basename(file) == "__init__.py" else 0)
    for _ in range(depth):
        root = os.path.dirname(root)
    parts = root.split(os.sep)
    return None if "site-packages" in parts or "dist-packages" in parts else root


def _unreadable_hint(exc: BaseException, folders: Sequence[str]) -> str:
    """Why a module may not be found: a folder on the search path this process cannot read.

    A root server or worker runs its sandboxed tasks as ``nobody`` on the host
    (``osmo.runtime.sandbox``), so a project folder only its owner may read (a home folder
    made 0700) is there but unreadable to the task.
    """
    if not isinstance(exc, ModuleNotFoundError):
        return ""
    shut = [f for f in dict.fromkeys(folders)
            if f and os.path.isdir(f) and not os.access(f, os.R_OK | os.X_OK)]
    if not shut:
        return ""
    return (f"; this task cannot read {', '.join(shut)} (uid {os.getuid()} here: a server or "
            "worker running as root runs its tasks as nobody on the host). Make the folder "
            "readable by others (chmod o+rx) or run osmo as your own user")


def _load_custom(ref: str, paths: Sequence[str]) -> tuple[TaskType, str | None]:
    module_name, _, attr = ref.partition(":")
    what = f"task type '{ref}'"
    if not module_name or not attr:
        raise TaskTypeError(f"{what}: write a custom type as 'module:attr' (e.g. tasks:rollout)")
    with _search(paths):
        try:
            module = importlib.import_module(module_name)
        except Exception as exc:
            where = f" (searched {', '.join(paths)} first)" if paths else ""
            raise TaskTypeError(import_failure(what, module_name, exc, None) + where
                                + _unreadable_hint(exc, [*paths, *sys.path])) from exc
        obj: Any = module
        for part in attr.split("."):
            if not hasattr(obj, part):
                from osmo.spec.reader import did_you_mean

                names = [n for n in dir(obj) if not n.startswith("_")]
                raise TaskTypeError(f"{what}: module '{module_name}' has no attribute '{attr}'"
                                    f"{did_you_mean(part, names)}")
            obj = getattr(obj, part)
        return _checked(obj, what), _module_root(module)


def _load_installed(name: str) -> TaskType:
    from osmo.spec.reader import did_you_mean

    eps = entry_points()
    ep = eps.get(name)
    if ep is None:
        known = ", ".join(sorted(eps)) or "none are installed"
        raise TaskTypeError(f"unknown task type '{name}'{did_you_mean(name, eps)}; installed "
                            f"types: {known}. A custom type is written 'module:attr'")
    try:
        obj = ep.load()
    except Exception as exc:
        raise TaskTypeError(import_failure(f"task type '{name}'", ep.module, exc,
                                            extra_of(ep))) from exc
    return _checked(obj, f"task type '{name}' ({ep.value})")


def resolve(ref: str, *, paths: Sequence[str] = ()) -> TaskType:
    """The task type named ``ref`` (an installed name or ``module:attr``).

    Args:
        ref: what a spec's ``type:`` says.
        paths: folders searched first for a custom type's module.

    Raises:
        TaskTypeError: unknown, not importable (with the ``pip install`` hint when an extra
            is known), or not shaped like a task type.
    """
    if not isinstance(ref, str) or not ref.strip():
        raise TaskTypeError("a task type is named by a non-empty string")
    return _load_custom(ref, paths)[0] if is_custom(ref) else _load_installed(ref)


class Resolver:
    """Resolves types for one validation (a spec, a submission), caching each name.

    Implements ``osmo.spec.typed.TypeResolver``.

    Args:
        paths: folders searched first for custom (``module:attr``) types.
    """

    def __init__(self, paths: Sequence[str] = ()) -> None:
        self.paths = tuple(os.path.abspath(p) for p in paths)
        self._cache: dict[str, tuple[TaskType, str | None] | TaskTypeError] = {}

    def _lookup(self, ref: str) -> tuple[TaskType, str | None]:
        if ref not in self._cache:
            try:
                if not isinstance(ref, str) or not ref.strip():
                    raise TaskTypeError("a task type is named by a non-empty string")
                self._cache[ref] = (_load_custom(ref, self.paths) if is_custom(ref)
                                    else (_load_installed(ref), None))
            except TaskTypeError as exc:
                self._cache[ref] = exc
        found = self._cache[ref]
        if isinstance(found, TaskTypeError):
            raise found
        return found

    def resolve(self, ref: str) -> TaskType:
        """As :func:`resolve`, with this resolver's paths; raises :class:`TaskTypeError`."""
        return self._lookup(ref)[0]

    def paths_for(self, ref: str) -> tuple[str, ...]:
        """The folder a resolved custom type's module is imported from.

        Empty for an installed type or a module installed in site-packages.
        """
        root = self._lookup(ref)[1]
        return (root,) if root else ()


def list_types() -> list[TypeEntry]:
    """Every installed task type, sorted by name; broken ones carry their import error."""
    out = []
    for name, ep in sorted(entry_points().items()):
        dist = ep.dist.name if ep.dist is not None else None
        try:
            obj = _load_installed(name)
        except TaskTypeError as exc:
            out.append(TypeEntry(name, ep.value, extra=extra_of(ep), error=str(exc),
                                 distribution=dist))
            continue
        out.append(TypeEntry(name, ep.value, obj.version, obj.description, obj.extra,
                             dict(obj.params), None, dist))
    return out


def ref_of(obj: Any) -> str:
    """The ``module:attr`` reference of a task-type object (for ``Workflow.task(type=obj)``).

    Raises:
        TaskTypeError: the object is not found in its module's globals, or lives in
            ``__main__`` (a worker cannot import the script being run).
    """
    try:
        return object_ref(obj)
    except UsageError as exc:
        raise TaskTypeError(str(exc)) from None
