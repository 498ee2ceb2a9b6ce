"""Image ids per workflow, remembered across workflows while podman's image store is unchanged.

A retag changes the store's stamp, so the next workflow sees the moved tag; a workflow keeps
the id its first task resolved.
"""

from __future__ import annotations

import uuid

from osmo.runtime.container import ContainerEngine, ImageInfo
from osmo.runtime.container.images import ImageIds


class CountingEngine(ContainerEngine):
    """The real engine, counting its ``image inspect`` calls."""

    inspections = 0

    def image(self, image: str) -> ImageInfo | None:
        self.inspections += 1
        return super().image(image)


def test_an_id_is_inspected_again_only_after_the_image_store_changed(
        engine: ContainerEngine, images: dict[str, str]) -> None:
    counting = CountingEngine(engine.engine)
    assert counting.store_stamp() is not None  # podman: its images.json
    ids = ImageIds(counting)
    tag = f"localhost/osmo-test-ids/{uuid.uuid4().hex[:12]}:1"
    first, second = images["alpine:3.18"], images["ubuntu:24.04"]
    engine.call("tag", first, tag)
    try:
        assert ids.known("wf-0", tag) == first and counting.inspections == 1
        for n in range(1, 11):
            assert ids.known(f"wf-{n}", tag) == first
        # other sessions on this machine may change the store meanwhile: most lookups hit
        assert counting.inspections < 6, counting.inspections
        engine.call("tag", second, tag)  # the same name, another image
        assert ids.known("wf-new", tag) == second
        assert ids.known("wf-0", tag) == first  # a workflow keeps what it resolved
        progress: list[str] = []
        assert ids.resolve("wf-later", tag, pull=False, auth=None,
                           progress=progress.append) == second
        assert progress == []
    finally:
        engine.call("untag", tag, tag)  # only this name (no name: every name of it)
