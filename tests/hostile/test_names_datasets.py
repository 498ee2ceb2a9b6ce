"""Hostile dataset names and tags at every entry point: CLI, SDK, spec, and the raw server API.

A dataset name names a folder under ``OSMO_HOME/datasets``; before names were checked,
``/abs/dir/ds`` and ``../../x/ds`` made the server write outside its home. Every entry point
now refuses them with the one message of ``osmo.names`` (exit 2), before anything is stored.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest

import osmo as osmo_pkg
from osmo.errors import SpecError, UsageError
from osmo.sdk import transfer
from osmo.sdk.connect import Connection, connect
from tests.conftest import Osmo, write


def _hostile(tmp: Path) -> dict[str, str]:
    return {"absolute": str(tmp / "escape" / "ds"), "dotdot": "../../escape/ds",
            "dots": "..", "empty": "", "newline": "a\nb", "escape-seq": "\x1b]0;owned\x07",
            "long": "d" * 5000, "slash": "a/b", "digit-first": "1st"}


HOSTILE_KEYS = ["absolute", "dotdot", "dots", "empty", "newline", "escape-seq", "long", "slash",
                "digit-first"]
BAD_TAGS = ["", "../x", "latest", "12", "a b", "t" * 5000, "a\nb"]


@pytest.fixture(scope="module")
def home(shared_osmo: Osmo, tmp_path_factory: pytest.TempPathFactory) -> Osmo:
    """A server with one good dataset version, ``good:1``."""
    src = tmp_path_factory.mktemp("src")
    (src / "a.txt").write_text("a\n")
    shared_osmo("dataset", "upload", "good", str(src), check=True)
    return shared_osmo


def raw_api(osmo: Osmo) -> Iterator[Connection]:
    """An API connection to ``osmo``'s server that sends requests as written (no client-side
    checks), for a fixture to yield from."""
    conn = connect(home=osmo.home)
    yield conn
    conn.close()


@pytest.fixture
def raw(home: Osmo) -> Iterator[Connection]:
    yield from raw_api(home)


def _outside(tmp: Path) -> list[Path]:
    return [p for p in (tmp / "escape").rglob("*")] if (tmp / "escape").exists() else []


@pytest.mark.parametrize("key", HOSTILE_KEYS)
def test_cli_upload_refuses_a_hostile_name(home: Osmo, tmp_path: Path, key: str) -> None:
    name = _hostile(tmp_path)[key]
    src = write(tmp_path / "src" / "f.txt", "x\n").parent
    r = home("dataset", "upload", name, str(src))
    assert r.code == 2, r
    assert "dataset name" in r.err and "Traceback" not in r.err
    assert "\x1b" not in r.err and "\n" not in r.err.strip()  # the bad name is escaped
    assert not _outside(tmp_path)


@pytest.mark.parametrize("verb", ["info", "download", "tag", "list"])
def test_cli_dataset_verbs_refuse_hostile_names(home: Osmo, tmp_path: Path, verb: str) -> None:
    name = _hostile(tmp_path)["dotdot"]
    args = {"info": [name], "download": [name, "-o", str(tmp_path / "out")],
            "tag": [name, "gold"], "list": [name]}[verb]
    r = home("dataset", verb, *args)
    assert r.code == 2 and "dataset name '../../escape/ds' is not a valid name" in r.err, r


@pytest.mark.parametrize("tag", BAD_TAGS)
def test_cli_tag_refuses_a_hostile_tag(home: Osmo, tag: str) -> None:
    r = home("dataset", "tag", "good:1", tag)
    assert r.code == 2 and "dataset tag" in r.err, r


def test_sdk_refuses_hostile_names_before_calling(home: Osmo, tmp_path: Path) -> None:
    with osmo_pkg.Client(home=home.home) as client:
        for name in _hostile(tmp_path).values():
            with pytest.raises(UsageError, match="dataset name"):
                client.upload_dataset(name, tmp_path)
            with pytest.raises(UsageError, match="dataset name"):
                client.dataset(name)
        with pytest.raises(UsageError, match="dataset tag"):
            client.tag_dataset("good:1", "../x")
        assert client.dataset("good:1")["version"] == 1


def test_spec_outputs_and_inputs_refuse_hostile_names(home: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "wf.yaml", (
        "workflow:\n  name: ds\n  tasks:\n  - name: a\n    command: [echo]\n    outputs:\n"
        "    - dataset: {name: ../../escape/ds}\n  - name: b\n    command: [echo]\n"
        "    inputs:\n    - dataset: {name: '/etc:1'}\n"))
    for verb in ("validate", "submit"):
        r = home(verb, str(spec))
        assert r.code == 2, r
        assert f"{spec}:7:23: dataset name '../../escape/ds' is not a valid name" in r.err
        assert f"{spec}:11:23: dataset name '/etc' is not a valid name" in r.err


@pytest.mark.parametrize("key", HOSTILE_KEYS)
def test_server_api_refuses_a_hostile_upload(raw: Connection, tmp_path: Path, key: str) -> None:
    """The whole attack, sent raw: upload under a hostile name, then a task reads it."""
    name = _hostile(tmp_path)[key]
    src = write(tmp_path / "src" / "f.txt", "x\n").parent
    offer = transfer.upload(raw.api, src, home=raw.home)
    try:
        with pytest.raises(UsageError, match="dataset name"):
            raw.api.call("dataset_upload", {"name": name, "manifest": offer.manifest.to_json(),
                                             "source": offer.source, "metadata": {}})
    finally:
        offer.close()
    spec = {"workflow": {"name": "reader", "tasks": [
        {"name": "r", "command": ["ls"], "inputs": [{"dataset": {"name": name}}]}]}}
    with pytest.raises(SpecError, match="dataset name"):
        raw.api.call("submit", {"spec": spec})
    assert not _outside(tmp_path)


@pytest.mark.parametrize("verb,request_", [
    ("dataset_info", {"ref": "../../escape/ds"}),
    ("dataset_info", {"ref": "good:../1"}),
    ("dataset_download", {"ref": "/etc"}),
    ("dataset_list", {"name": "a/b"}),
    ("dataset_tag", {"ref": "good:1", "tag": "../x"}),
    ("dataset_tag", {"ref": "good:1", "tag": "latest"}),
    ("dataset_tag", {"ref": "good:1", "tag": "x" * 5000}),
    ("dataset_tag", {"ref": "../good:1", "tag": "gold"}),
])
def test_server_api_refuses_hostile_refs_and_tags(raw: Connection, verb: str,
                                                  request_: dict[str, str]) -> None:
    with pytest.raises(UsageError):
        raw.api.call(verb, request_)
    assert [d["tags"] for d in json.loads(json.dumps(raw.api.call("dataset_list", {})))] \
        == [[]]  # nothing was tagged
