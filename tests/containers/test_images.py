"""The offline test images: what the tutorials need is in them, and building is idempotent."""

from __future__ import annotations

import subprocess
import tarfile
import time
from pathlib import Path

import pytest

from tests.containers import images as test_images
from tests.containers.images import TEST_IMAGE_LABEL, ensure_images, podman


def in_image(env: dict[str, str], image: str, script: str, shell: str = "sh") -> str:
    return podman("run", "--rm", "--pull=never", image, shell, "-c", script, env=env)


def test_alpine_has_the_tools_of_the_tutorials(images: dict[str, str],
                                               podman_env: dict[str, str]) -> None:
    out = in_image(podman_env, "alpine:3.18", "which sh nc sleep echo cat hostname; "
                   "echo x > /tmp/w && cat /tmp/w; ls -ld /tmp | cut -c1-10")
    assert out.split() == ["/bin/sh", "/bin/nc", "/bin/sleep", "/bin/echo", "/bin/cat",
                           "/bin/hostname", "x", "drwxrwxrwt"]


@pytest.mark.parametrize("image", ["ubuntu:22.04", "ubuntu:24.04"])
def test_ubuntu_has_bash_with_brace_expansion(images: dict[str, str],
                                              podman_env: dict[str, str], image: str) -> None:
    out = in_image(podman_env, image, 'for i in {1..3}; do echo "s_$i"; done; echo "✓"; '
                   "mkdir -p /tmp/a/b; wc -l < /etc/passwd", shell="bash")
    assert out.split() == ["s_1", "s_2", "s_3", "✓", "2"]


def test_python_image_runs_this_python(python_image: str, podman_env: dict[str, str]) -> None:
    import sys
    out = in_image(podman_env, python_image, "python3 -c 'import json, sqlite3, ssl, zlib, sys; "
                   "print(\"%d.%d\" % sys.version_info[:2])'")
    assert out.strip() == f"{sys.version_info.major}.{sys.version_info.minor}"


def test_images_are_labelled_and_named_as_in_the_tutorials(images: dict[str, str],
                                                           podman_env: dict[str, str]) -> None:
    for name in ("alpine:3.18", "ubuntu:22.04", "ubuntu:24.04"):
        ident = podman("image", "inspect", "--format", "{{.Id}}", name, env=podman_env).strip()
        assert images[name] == f"sha256:{ident}"
    label = podman("image", "inspect", "--format", f'{{{{index .Labels "{TEST_IMAGE_LABEL}"}}}}',
                   "alpine:3.18", env=podman_env)
    assert label.strip() == "busybox"


def test_ensure_is_idempotent(images: dict[str, str], podman_env: dict[str, str]) -> None:
    before = podman("images", "-q", "--no-trunc", env=podman_env).split()
    assert ensure_images(podman_env) == images
    assert podman("images", "-q", "--no-trunc", env=podman_env).split() == before


def test_a_foreign_image_under_a_tutorial_name_is_left_alone(
        images: dict[str, str], podman_env: dict[str, str], tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A developer's real image keeps its name; a stale test image of ours is retagged."""
    foreign, stale = (f"localhost/osmo-test-{kind}-{time.monotonic_ns()}:1"
                      for kind in ("foreign", "stale"))
    rootfs = tmp_path / "rootfs.tar"
    with tarfile.open(rootfs, "w") as tar:
        info = tarfile.TarInfo("marker")
        tar.addfile(info)
    podman("import", str(rootfs), foreign, env=podman_env)
    podman("import", f"--change=LABEL={TEST_IMAGE_LABEL}=old", str(rootfs), stale, env=podman_env)
    foreign_id, stale_id = (podman("image", "inspect", "--format", "{{.Id}}", name,
                                   env=podman_env).strip() for name in (foreign, stale))
    try:
        monkeypatch.setitem(test_images.NAMES, "busybox", (foreign, stale))
        names = ensure_images(podman_env, ("busybox",))
        assert names[foreign] == f"sha256:{foreign_id}"
        assert names[stale] == images["alpine:3.18"]
    finally:
        subprocess.run(["podman", "untag", stale, stale], capture_output=True, env=podman_env)
        subprocess.run(["podman", "rmi", foreign_id, stale_id], capture_output=True,
                       env=podman_env)
