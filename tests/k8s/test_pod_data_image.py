"""osmo's own image runs a pod's data side (issue #28 item 2): the offline ``osmo`` test image
(``tests/containers/images.py``) runs ``python3 -m osmo.runtime.kubernetes.podside`` under
podman, as the task's non-root uid, against a node's pod-data API on loopback: the fetch
writes the attempt's files into the pod's volume, the collector sends its output back
(``podside_image.py``).

The image built from the chart's Dockerfile runs the same scenario in
``tests/helm/test_dockerfile_build.py``.
"""

from __future__ import annotations

from pathlib import Path

from tests.containers.conftest import podman_env  # noqa: F401 - fixture
from tests.containers.images import KINDS_OSMO, OSMO_IMAGE, ensure_images
from tests.k8s.podside_image import fetch_and_collect

UID = 1000


def test_the_osmo_image_fetches_and_collects_as_a_non_root_uid(
        podman_env: dict[str, str], tmp_path: Path) -> None:  # noqa: F811
    ensure_images(podman_env, KINDS_OSMO)
    fetch_and_collect(podman_env, OSMO_IMAGE, UID, tmp_path)
