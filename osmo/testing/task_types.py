"""The task-type conformance kit: :func:`check_task_type`, for task-type authors.

Run it in a plugin's tests::

    from osmo.testing import check_task_type
    from mypkg.tasks import rollout

    def test_rollout_conforms(tmp_path):
        files = check_task_type(rollout, params={"episodes": 2})
        assert "rollout.mcap" in files

It checks what osmo relies on, the way osmo uses it, and fails with an ``AssertionError``
that lists every problem found:

1. the declared attributes (``name``, ``version``, ``description``, ``resources``,
   ``extra``, ``params``) have the right types, and ``run`` takes one argument;
2. the parameter schema is sound: each entry is a ``Param`` of a usable type, ``min`` is
   not above ``max``, choices are of the type, and every default passes its own ``Param``;
3. the given ``params`` pass the schema exactly as a spec's would at submit;
4. ``run(ctx)`` returns (does not raise) with a real ``TaskContext`` whose ``output`` is a
   fresh folder, and writes at least one file there.

A class is instantiated with no arguments first, as the registry does. The run happens in
the calling process (use ``pytest``'s ``tmp_path`` as ``workdir`` to keep the outputs).
"""

from __future__ import annotations

import inspect
import os
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

__all__ = ["check_task_type"]


def _params_problems(schema: Mapping[str, Any], params: Mapping[str, Any]) -> list[str]:
    from osmo.params import REQUIRED, value_problem

    problems = [f"param '{n}' is not declared (declared: {', '.join(schema) or 'none'})"
                for n in params if n not in schema]
    problems += [f"param '{n}' {p}" for n, v in params.items() if n in schema
                 if (p := value_problem(schema[n], v))]
    problems += [f"required param '{n}' is not given" for n, p in schema.items()
                 if p.default is REQUIRED and n not in params]
    return problems


def _run(obj: Any, params: Mapping[str, Any], inputs: Sequence[Path], root: Path) -> list[str]:
    from osmo.params import fill_defaults
    from osmo.tasktypes.context import RunContext

    output, work = root / "output", root / "work"
    output.mkdir(parents=True)
    work.mkdir()
    ctx = RunContext(params=fill_defaults(obj.params, params), inputs=list(inputs),
                     input_named={p.name: p for p in inputs}, output=output, workdir=work,
                     workflow_id="conformance-1", task="check", attempt_id="conformance-1:check:0",
                     plugin=f"{obj.name}@{obj.version}", env={})
    cwd = os.getcwd()
    os.chdir(work)  # the runner runs a task in its work folder
    try:
        result = obj.run(ctx)
    except Exception as exc:
        raise AssertionError(f"run(ctx) raised {type(exc).__name__}: {exc}") from exc
    finally:
        os.chdir(cwd)
    if result is not None:
        raise AssertionError(f"run(ctx) returned {result!r}; it must return None (write "
                             "results under ctx.output)")
    files = sorted(str(p.relative_to(output)) for p in output.rglob("*") if p.is_file())
    if not files:
        raise AssertionError("run(ctx) wrote nothing under ctx.output; a task hands its results "
                             "downstream only through files there")
    return files


def check_task_type(obj: Any, params: Mapping[str, Any] | None = None, *,
                    inputs: Sequence[str | os.PathLike[str]] = (),
                    workdir: str | os.PathLike[str] | None = None) -> list[str]:
    """Check that ``obj`` is a working task type (see the module docstring).

    Args:
        obj: the task type (an instance, a class, or a ``@task_type`` function).
        params: parameters to run it with, as a spec would give them (defaults filled in).
        inputs: input folders, in order (``ctx.input_named`` uses their folder names).
        workdir: where to make ``output/`` and ``work/`` (kept); default: a temporary
            folder, removed afterwards.

    Returns:
        the files written under ``ctx.output``, relative and sorted.

    Raises:
        AssertionError: with every problem found, or the error ``run`` raised (chained).
    """
    from osmo.tasktypes.registry import shape_problems

    if inspect.isclass(obj):
        obj = obj()
    problems = shape_problems(obj)
    if not problems:
        problems = _params_problems(obj.params, params or {})
    if problems:
        raise AssertionError(f"{obj!r} is not a conforming task type:\n  - "
                             + "\n  - ".join(problems))
    folders = [Path(p).absolute() for p in inputs]
    missing = [str(p) for p in folders if not p.is_dir()]
    if missing:
        raise AssertionError(f"input folders do not exist: {', '.join(missing)}")
    if workdir is not None:
        return _run(obj, params or {}, folders, Path(workdir).absolute())
    root = Path(tempfile.mkdtemp(prefix="osmo-check-"))
    try:
        return _run(obj, params or {}, folders, root)
    finally:
        shutil.rmtree(root, ignore_errors=True)
