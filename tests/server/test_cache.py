"""The cache policy: which placed attempts have a fingerprint (``osmo.server.cache.key``) and which
may take an earlier success (``reuses``). Pure rules, tables of cases."""

from __future__ import annotations

import dataclasses

import pytest

from osmo.record import LineageInput
from osmo.scheduler.types import PrepareAttempt
from osmo.server.cache import fingerprint, key, reuses
from osmo.spec.model import GroupSpec, InputSpec, OutputSpec, TaskSpec, WorkflowSpec
from osmo.store.submission import Submission

UP = LineageInput("up", "wf-1", "sha256:" + "a" * 64)
TASK = TaskSpec(name="t", command=("true",), inputs=(InputSpec(task="up"),))
CMD = PrepareAttempt("wf-1:t:0", "wf-1", "t", 0, "local", {"up": "/runs/up"}, {}, run=True)


def test_a_free_attempt_with_known_inputs_has_its_fingerprint() -> None:
    assert key(CMD, TASK, [UP]) == fingerprint(TASK, [("up", UP.manifest_digest)])
    # cache: false does not stop its success from being recorded (reuses decides taking one)
    assert key(CMD, dataclasses.replace(TASK, cache=False), [UP]) == key(CMD, TASK, [UP])


@pytest.mark.parametrize(("cmd", "task", "sources"), [
    (dataclasses.replace(CMD, run=False), TASK, [UP]),  # held by a group barrier
    (CMD, dataclasses.replace(TASK, inputs=(InputSpec(url="s3://b/x"),)), [UP]),
    (CMD, dataclasses.replace(TASK, outputs=(OutputSpec(url="s3://b/y"),)), [UP]),
    (CMD, TASK, [None]),  # an input whose manifest is not recorded
], ids=["barrier", "url-input", "url-output", "unknown-input"])
def test_what_always_runs(cmd: PrepareAttempt, task: TaskSpec,
                          sources: list[LineageInput | None]) -> None:
    assert key(cmd, task, sources) is None


SOURCE = TaskSpec(name="source", command=("true",))
SINK = TaskSpec(name="sink", command=("true",), inputs=(InputSpec(task="source"),))
TYPED = TaskSpec(name="typed", type="tasks:numbers")


def _spec(cache: bool | None = None) -> WorkflowSpec:
    return WorkflowSpec("wf", tuple(GroupSpec(t.name, (t,)) for t in (SOURCE, SINK, TYPED)),
                        cache=cache)


@pytest.mark.parametrize(("task", "workflow", "submitted", "expected"), [
    (SINK, None, None, False),  # a bare command task that feeds none: runs, as in OSMO
    (SOURCE, None, None, True),  # its output feeds another task
    (TYPED, None, None, True),  # a typed task
    (SINK, None, True, True),  # --reuse
    (SOURCE, None, False, False),  # --no-cache
    (dataclasses.replace(SINK, cache=True), None, None, True),  # the task's cache: true
    (dataclasses.replace(SOURCE, cache=False), None, True, False),  # cache: false over --reuse
    (dataclasses.replace(SINK, cache=True), None, False, False),  # --no-cache over all
    (SINK, True, None, True),  # the workflow's cache: true
    (TYPED, False, True, False),  # the workflow's cache: false, over --reuse and the default
    (dataclasses.replace(SINK, cache=True), False, None, True),  # the task's word first
], ids=["leaf", "feeds", "typed", "reuse", "no-cache", "task-true", "task-false-over-reuse",
        "no-cache-over-task", "workflow-true", "workflow-false", "task-over-workflow"])
def test_who_reuses(task: TaskSpec, workflow: bool | None, submitted: bool | None,
                    expected: bool) -> None:
    assert reuses(_spec(workflow), task, submitted=submitted) is expected


def test_the_submission_is_read_from_the_stored_options() -> None:
    assert [Submission.from_dict(o).reuses for o in (
        {}, {"reuse": True}, {"no_cache": True}, {"reuse": False, "no_cache": False})] == [
        None, True, False, None]


IMAGE_TASK = dataclasses.replace(TASK, image="alpine:3.18")
ID_A, ID_B = "sha256:" + "1" * 64, "sha256:" + "2" * 64


def test_a_contained_task_is_fingerprinted_by_its_image_id_not_its_tag() -> None:
    by_a = key(CMD, IMAGE_TASK, [UP], contained=True, image_id=ID_A)
    by_b = key(CMD, IMAGE_TASK, [UP], contained=True, image_id=ID_B)
    retagged = dataclasses.replace(IMAGE_TASK, image="localhost/other:2")
    assert by_a is not None and by_b is not None and by_a != by_b  # the tag moved: rerun
    assert by_a == key(CMD, retagged, [UP], contained=True, image_id=ID_A)
    # an image the server cannot name is not cached; a process task keeps its tag
    assert key(CMD, IMAGE_TASK, [UP], contained=True, image_id=None) is None
    assert key(CMD, IMAGE_TASK, [UP]) == fingerprint(
        IMAGE_TASK, [("up", UP.manifest_digest)])
