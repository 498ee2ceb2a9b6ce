"""The cache policy (``osmo.server.cache.key``): which placed attempts may be served from the
cache, and with which fingerprint. Pure rules, a table of cases."""

from __future__ import annotations

import dataclasses

import pytest

from osmo.record import LineageInput
from osmo.scheduler.types import PrepareAttempt
from osmo.server.cache import fingerprint, key
from osmo.spec.model import InputSpec, OutputSpec, TaskSpec

UP = LineageInput("up", "wf-1", "sha256:" + "a" * 64)
TASK = TaskSpec(name="t", command=("true",), inputs=(InputSpec(task="up"),))
CMD = PrepareAttempt("wf-1:t:0", "wf-1", "t", 0, "local", {"up": "/runs/up"}, {}, run=True)


def test_a_free_attempt_with_known_inputs_has_its_fingerprint() -> None:
    assert key(CMD, TASK, [UP], no_cache=False) == fingerprint(TASK, [("up", UP.manifest_digest)])


@pytest.mark.parametrize(("cmd", "task", "sources", "no_cache"), [
    (dataclasses.replace(CMD, run=False), TASK, [UP], False),  # held by a group barrier
    (CMD, dataclasses.replace(TASK, cache=False), [UP], False),  # cache: false
    (CMD, TASK, [UP], True),  # --no-cache
    (CMD, dataclasses.replace(TASK, inputs=(InputSpec(url="s3://b/x"),)), [UP], False),
    (CMD, dataclasses.replace(TASK, outputs=(OutputSpec(url="s3://b/y"),)), [UP], False),
    (CMD, TASK, [None], False),  # an input whose manifest is not recorded
], ids=["barrier", "cache-false", "no-cache", "url-input", "url-output", "unknown-input"])
def test_what_always_runs(cmd: PrepareAttempt, task: TaskSpec,
                          sources: list[LineageInput | None], no_cache: bool) -> None:
    assert key(cmd, task, sources, no_cache=no_cache) is None


IMAGE_TASK = dataclasses.replace(TASK, image="alpine:3.18")
ID_A, ID_B = "sha256:" + "1" * 64, "sha256:" + "2" * 64


def test_a_contained_task_is_fingerprinted_by_its_image_id_not_its_tag() -> None:
    by_a = key(CMD, IMAGE_TASK, [UP], no_cache=False, contained=True, image_id=ID_A)
    by_b = key(CMD, IMAGE_TASK, [UP], no_cache=False, contained=True, image_id=ID_B)
    retagged = dataclasses.replace(IMAGE_TASK, image="localhost/other:2")
    assert by_a is not None and by_b is not None and by_a != by_b  # the tag moved: rerun
    assert by_a == key(CMD, retagged, [UP], no_cache=False, contained=True, image_id=ID_A)
    # an image the server cannot name is not cached; a process task keeps its tag
    assert key(CMD, IMAGE_TASK, [UP], no_cache=False, contained=True, image_id=None) is None
    assert key(CMD, IMAGE_TASK, [UP], no_cache=False) == fingerprint(
        IMAGE_TASK, [("up", UP.manifest_digest)])
