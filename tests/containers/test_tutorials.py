"""OSMO's tutorials (``osmo_tutorials/``): unmodified copies, valid specs, and run unmodified
in containers through ``osmo submit`` with the offline test images.

One server (``--runtime container``) runs them all; after each, no container or network of
that server may be left. The expected lines are what each tutorial prints in its image;
``{{output}}`` is ``/osmo/data/output`` and ``{{input:N}}`` ``/osmo/data/input/N`` there.
The communication tutorial's client calls ``nc`` once: it prints the server's ``hello`` only
if its peer starts after the lead (the group runs on its own network, ``{{host:server}}``
is the lead's name on it).
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.runtime.container import ContainerEngine
from osmo.spec.loader import load_spec
from tests.conftest import Osmo
from tests.containers.images import NAMES
from tests.containers.submitting import (
    check_serial_tutorial,
    container_osmo,
    leftovers,
    owner_labels,
    submitted_id,
    task_lines,
    tasks,
)

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


@pytest.fixture(scope="module")
def tutorial_osmo(podman_env: dict[str, str], images: dict[str, str],
                  tmp_path_factory: pytest.TempPathFactory) -> Iterator[Osmo]:
    runner = container_osmo(tmp_path_factory.mktemp("tutorials") / "home", podman_env)
    runner("server", "start", "--cpus", "8", check=True)  # group_tasks needs 3 slots at once
    yield runner
    runner.stop_server()


def run(osmo: Osmo, engine: ContainerEngine, name: str) -> tuple[dict[str, list[str]],
                                                                  dict[str, dict]]:
    """Submit a tutorial, wait; its tasks' lines and query rows (nothing may be left)."""
    r = osmo("submit", str(TUTORIALS / name), "--wait", timeout=300)
    wf_id = submitted_id(r.out)
    lines, rows = task_lines(osmo, wf_id), tasks(osmo, wf_id)
    assert r.code == 0, f"{r.out}{r.err}{lines}{rows}"
    assert {row["status"] for row in rows.values()} == {"COMPLETED"}, f"{rows}{lines}"
    assert leftovers(engine, owner_labels(osmo)) == ([], [])
    return lines, rows


def test_hello_world(tutorial_osmo: Osmo, engine: ContainerEngine) -> None:
    lines, _ = run(tutorial_osmo, engine, "hello_world.yaml")
    assert lines["hello"] == ["Hello from OSMO!"]


def test_serial_workflow(tutorial_osmo: Osmo, engine: ContainerEngine) -> None:
    lines, rows = run(tutorial_osmo, engine, "serial_workflow.yaml")
    assert len(lines["task1"]) == 1 and re.fullmatch(r"Hello from task1 \S+", lines["task1"][0])
    assert lines["task2"] == ["Hello from task2 /osmo/data/output", "Reading from task 1",
                              "a line: Data from task 1"]
    check_serial_tutorial(lines, rows)


def test_parallel_tasks(tutorial_osmo: Osmo, engine: ContainerEngine) -> None:
    lines, _ = run(tutorial_osmo, engine, "parallel_tasks.yaml")
    for name in ("task-a", "task-b", "task-c"):
        assert lines[name] == [f"Hello from {name}"]


def test_combination_workflow_simple(tutorial_osmo: Osmo, engine: ContainerEngine) -> None:
    lines, rows = run(tutorial_osmo, engine, "combination_workflow_simple.yaml")
    samples = [f"sample_{i},value_{i}" for i in range(1, 11)]
    assert lines["generate-data"] == ["Generating training data...",
                                      "✓ Training data generation complete!"]
    csv = Path(rows["generate-data"]["output"]) / "data" / "training_data.csv"
    assert csv.read_text().splitlines() == samples
    assert lines["train-model-a"] == ["Training Model A...", *samples, "✓ Model A complete!"]
    # OSMO's group semantics: a lead (generate-data, train-model-a) finishing stops its
    # peers, which may not have printed everything (or anything) yet
    assert is_prefix(lines.get("validate-data", []),
                     ["Validating training data...", "✓ Validation passed!"])
    assert is_prefix(lines.get("train-model-b", []), [
        "Training Model B...", "10 /osmo/data/input/0/data/training_data.csv",
        "✓ Model B complete!"])
    assert rows["validate-data"]["status"] == rows["train-model-b"]["status"] == "COMPLETED"


def is_prefix(lines: list[str], expected: list[str]) -> bool:
    return lines == expected[:len(lines)]


def test_group_tasks(tutorial_osmo: Osmo, engine: ContainerEngine) -> None:
    lines, _ = run(tutorial_osmo, engine, "group_tasks.yaml")
    for n, first in ((1, 1), (2, 6), (3, 11)):
        assert lines[f"processor-{n}"] == [
            f"Processor {n}: Starting...",
            *(f"Processor {n}: Processing item {i}" for i in range(first, first + 5)),
            f"Processor {n}: Complete"]


def test_group_tasks_communication(tutorial_osmo: Osmo, engine: ContainerEngine) -> None:
    lines, _ = run(tutorial_osmo, engine, "group_tasks_communication.yaml")
    assert lines["client"] == ["Client: Starting...", "Calling server at server...",
                               "Received from server: hello", "Client: Complete"]
    assert lines["server"] == ["Server: Starting...", "Server: Complete"]
