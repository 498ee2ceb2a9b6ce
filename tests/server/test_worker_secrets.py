"""What a worker is given for an attempt: a registry credential only for a worker that runs
the task in its image, and only the one of the registry that image is on."""

from __future__ import annotations

from osmo.server.worker_access import has_secrets, task_secrets
from osmo.spec.model import TaskSpec

STORED = {"registry://nvcr.io": {"username": "u", "password": "nv-pw"},
          "registry://docker.io": {"username": "u", "password": "hub-pw"}}


def _none(url: str) -> dict[str, str] | None:
    return None


def test_a_container_worker_gets_the_credential_of_its_image_registry_only() -> None:
    task = TaskSpec("t", command=("true",), image="nvcr.io/nvidia/pytorch:24.01-py3")
    assert has_secrets(task, STORED.get, _none, containers="container")
    got = task_secrets(task, STORED.get, _none, containers="container")
    assert got["secrets"] == {"registry://nvcr.io": STORED["registry://nvcr.io"]}
    short = TaskSpec("t", command=("true",), image="alpine:3.18")  # Docker Hub
    assert set(task_secrets(short, STORED.get, _none, containers="container")["secrets"]) == {
        "registry://docker.io"}


def test_no_registry_credential_for_a_process_worker_a_typed_task_on_pods_or_no_image() -> None:
    image = TaskSpec("t", command=("true",), image="nvcr.io/x:1")
    assert not has_secrets(image, STORED.get, _none, containers=None)
    assert task_secrets(image, STORED.get, _none, containers=None)["secrets"] == {}
    typed = TaskSpec("t", type="osmo.demo", image="nvcr.io/x:1")
    assert not has_secrets(typed, STORED.get, _none, containers="kubernetes")  # a process there
    in_image = task_secrets(typed, STORED.get, _none, containers="container")  # its image here
    assert in_image["secrets"] == {"registry://nvcr.io": STORED["registry://nvcr.io"]}
    bare = TaskSpec("t", command=("true",))
    assert task_secrets(bare, STORED.get, _none, containers="container")["secrets"] == {}
    elsewhere = TaskSpec("t", command=("true",), image="quay.io/x:1")
    assert not has_secrets(elsewhere, STORED.get, _none, containers="container")
