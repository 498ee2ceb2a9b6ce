"""An in-process stand-in for osmo's TaskContext, for testing plugin logic without a server."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from osmo.record import LineageMcapWriter
from osmo.tasktypes.api import REQUIRED, TaskCancelled


@dataclass
class FakeContext:
    """Implements the TaskContext protocol over local folders."""

    params: Mapping[str, Any]
    output: Path
    workdir: Path
    inputs: list[Path] = field(default_factory=list)
    input_named: dict[str, Path] = field(default_factory=dict)
    workflow_id: str = "test-1"
    task: str = "task"
    attempt_id: str = "a1"
    log: logging.Logger = field(default_factory=lambda: logging.getLogger("osmo.test.plugin"))
    progress_calls: list[tuple[float, float | None, str]] = field(default_factory=list)
    cancel: bool = False

    def progress(self, done: float, total: float | None = None, message: str = "") -> None:
        self.progress_calls.append((done, total, message))

    def cancelled(self) -> bool:
        return self.cancel

    def check_cancelled(self) -> None:
        if self.cancel:
            raise TaskCancelled("cancelled")

    def mcap_writer(self, path: str | Path, *, metadata: Mapping[str, str] | None = None) -> Any:
        writer = LineageMcapWriter(Path(self.output) / path, None)
        if metadata:
            writer.add_metadata("osmo.task", dict(metadata))
        return writer


def make_ctx(task_type: Any, tmp: Path, name: str, inputs: list[Path] | None = None,
             **params: Any) -> FakeContext:
    """A context for ``task_type`` with defaults filled in and ``params`` overriding them."""
    values = {k: p.default for k, p in task_type.params.items()}
    values.update(params)
    missing = [k for k, v in values.items() if v is REQUIRED]
    assert not missing, f"missing params {missing}"
    out, work = tmp / name / "out", tmp / name / "work"
    out.mkdir(parents=True)
    work.mkdir(parents=True)
    return FakeContext(params=values, output=out, workdir=work, inputs=list(inputs or []),
                       input_named={p.parent.name: p for p in inputs or []}, task=name)
