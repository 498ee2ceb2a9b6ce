"""OSMO's tutorials (``osmo_tutorials/``): unmodified copies, valid specs, and runnable in the
offline test images through ``ContainerRuntime``.

The runs here are a sketch of the worker's container layout, not osmo's engine: each group
gets its own network (its tasks reachable by name), ``{{output}}`` is a writable bind at
``/osmo/data/output``, ``{{input:N}}`` a read-only bind at ``/osmo/data/input/N``, ``files:``
read-only binds at their declared paths. The end-to-end runs through ``osmo submit`` belong to
the integration (issue 14); these show the images and the layout are enough.

A group's lead starts first and its peers once it has printed its first line: the
communication tutorial's client calls ``nc`` once, and fails if it runs before the server
listens (the start barrier alone does not order that; the integration must).
"""

from __future__ import annotations

import hashlib
import os
import re
import time
from pathlib import Path

import pytest

from osmo.runtime.container import (
    DATA_OUTPUT,
    ContainerEngine,
    ContainerRun,
    Mount,
    data_input,
    safe_name,
)
from osmo.runtime.container_runtime import ContainerRuntime
from osmo.spec.loader import load_spec
from osmo.spec.model import TaskSpec, WorkflowSpec
from osmo.spec.tokens import substitute
from tests.containers.images import NAMES
from tests.containers.running import Run, start

TUTORIALS = Path(__file__).parent / "osmo_tutorials"


def manifest() -> dict[str, str]:
    """File name → sha256, from the README's table."""
    rows = re.findall(r"^\| (\S+\.yaml) \| \S+ \| ([0-9a-f]{64}) \|$",
                      (TUTORIALS / "README.md").read_text(), re.M)
    return dict(rows)


def test_copies_are_unmodified_and_keep_their_license() -> None:
    files = manifest()
    assert sorted(files) == sorted(p.name for p in TUTORIALS.glob("*.yaml"))
    assert len(files) == 6
    for name, digest in files.items():
        data = (TUTORIALS / name).read_bytes()
        assert hashlib.sha256(data).hexdigest() == digest, name
        assert b"SPDX-License-Identifier: Apache-2.0" in data
    assert "Apache License" in (TUTORIALS / "LICENSE").read_text()


@pytest.mark.parametrize("name", sorted(manifest()))
def test_each_is_a_valid_osmo_spec_naming_a_test_image(name: str) -> None:
    spec = load_spec(TUTORIALS / name)
    known = {image for names in NAMES.values() for image in names}
    assert {t.image for t in spec.all_tasks()} <= known


class TutorialRun:
    """Runs a spec's groups in order, each on its own network (see the module docstring)."""

    def __init__(self, runtime: ContainerRuntime, engine: ContainerEngine,
                 labels: dict[str, str], folder: Path) -> None:
        self.runtime, self.engine, self.labels, self.folder = runtime, engine, labels, folder
        self.outputs: dict[str, Path] = {}
        self.finished: dict[str, tuple[int, str, str]] = {}

    def run(self, spec: WorkflowSpec) -> dict[str, tuple[int, str, str]]:
        stamp = str(time.monotonic_ns())
        for group in spec.groups:
            network = safe_name(spec.name, group.name, stamp)
            self.engine.create_network(network, self.labels)
            try:
                lead = self._start(group.lead, network, stamp)
                lead.read_until(b"\n")
                runs = [(group.lead.name, lead)]
                runs += [(t.name, self._start(t, network, stamp)) for t in group.tasks
                         if t is not group.lead]
                for name, started in runs:
                    code = started.finish(timeout=180)
                    self.finished[name] = (code, started.out.decode(), started.err.decode())
            finally:
                self.engine.remove_network(network)
        return self.finished

    def _start(self, task: TaskSpec, network: str, stamp: str) -> Run:
        root = self.folder / task.name
        out = root / "output"
        out.mkdir(parents=True)
        self.outputs[task.name] = out
        upstream = [i.task for i in task.inputs]
        mounts = [Mount(out, DATA_OUTPUT, read_only=False)]
        mounts += [Mount(self.outputs[str(name)], data_input(n)) for n, name in enumerate(upstream)]

        def resolve(token: str) -> str | None:
            kind, _, arg = token.partition(":")
            if kind == "output":
                return DATA_OUTPUT
            if kind == "input":
                return data_input(int(arg) if arg.isdigit() else upstream.index(arg))
            return arg if kind == "host" else None

        for spec_file in task.files:
            host = root / "files" / spec_file.path.lstrip("/")
            host.parent.mkdir(parents=True, exist_ok=True)
            host.write_text(substitute(spec_file.contents, resolve))
            mounts.append(Mount(host, spec_file.path))
        assert task.image is not None
        run = ContainerRun(
            image=task.image, name=safe_name(task.name, stamp),
            argv=tuple(substitute(w, resolve) for w in (*task.command, *task.args)),
            mounts=tuple(mounts), user=f"{os.getuid()}:{os.getgid()}", labels=self.labels,
            network=network, aliases=(task.name,), hostname=task.name)
        env = {k: substitute(v, resolve) for k, v in task.environment.items()}
        return start(self.runtime, run, root, env)


@pytest.fixture
def tutorial(runtime: ContainerRuntime, engine: ContainerEngine, images: dict[str, str],
             labels: dict[str, str], tmp_path: Path) -> TutorialRun:
    return TutorialRun(runtime, engine, labels, tmp_path)


def lines(result: tuple[int, str, str]) -> list[str]:
    code, out, err = result
    assert code == 0, f"exit {code}; stdout={out!r} stderr={err!r}"
    return out.splitlines()


def test_hello_world(tutorial: TutorialRun) -> None:
    done = tutorial.run(load_spec(TUTORIALS / "hello_world.yaml"))
    assert lines(done["hello"]) == ["Hello from OSMO!"]


def test_serial_workflow(tutorial: TutorialRun) -> None:
    done = tutorial.run(load_spec(TUTORIALS / "serial_workflow.yaml"))
    assert lines(done["task1"]) == ["Hello from task1 task1"]
    assert lines(done["task2"]) == ["Hello from task2 /osmo/data/output", "Reading from task 1",
                                    "a line: Data from task 1"]
    assert lines(done["task3"]) == ["Hello from task3 /osmo/data/output", "Reading from task 1",
                                    "a line: Data from task 1", "Reading from task 2",
                                    "a line: Data from task 2"]
    for n in (1, 2, 3):
        assert (tutorial.outputs[f"task{n}"] / "test_read.txt").read_text() == f"Data from task {n}\n"


def test_parallel_tasks(tutorial: TutorialRun) -> None:
    done = tutorial.run(load_spec(TUTORIALS / "parallel_tasks.yaml"))
    for name in ("task-a", "task-b", "task-c"):
        assert lines(done[name]) == [f"Hello from {name}"]


def test_combination_workflow_simple(tutorial: TutorialRun) -> None:
    done = tutorial.run(load_spec(TUTORIALS / "combination_workflow_simple.yaml"))
    samples = [f"sample_{i},value_{i}" for i in range(1, 11)]
    assert lines(done["generate-data"]) == ["Generating training data...",
                                            "✓ Training data generation complete!"]
    csv = tutorial.outputs["generate-data"] / "data" / "training_data.csv"
    assert csv.read_text().splitlines() == samples
    assert lines(done["validate-data"]) == ["Validating training data...", "✓ Validation passed!"]
    assert lines(done["train-model-a"]) == ["Training Model A...", *samples, "✓ Model A complete!"]
    assert lines(done["train-model-b"]) == [
        "Training Model B...", "10 /osmo/data/input/0/data/training_data.csv",
        "✓ Model B complete!"]


def test_group_tasks(tutorial: TutorialRun) -> None:
    done = tutorial.run(load_spec(TUTORIALS / "group_tasks.yaml"))
    for n, first in ((1, 1), (2, 6), (3, 11)):
        assert lines(done[f"processor-{n}"]) == [
            f"Processor {n}: Starting...",
            *(f"Processor {n}: Processing item {i}" for i in range(first, first + 5)),
            f"Processor {n}: Complete"]


def test_group_tasks_communication(tutorial: TutorialRun) -> None:
    done = tutorial.run(load_spec(TUTORIALS / "group_tasks_communication.yaml"))
    assert lines(done["client"]) == ["Client: Starting...", "Calling server at server...",
                                     "Received from server: hello", "Client: Complete"]
    assert lines(done["server"]) == ["Server: Starting...", "Server: Complete"]
