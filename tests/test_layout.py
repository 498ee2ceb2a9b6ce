"""The home layout: one object names every path under OSMO_HOME; unusable names are refused."""

from __future__ import annotations

from pathlib import Path

import pytest

from osmo.errors import UsageError
from osmo.layout import Home


@pytest.mark.parametrize("name", ["a/b", "..", "."])
def test_unusable_names_fail(tmp_path: Path, name: str) -> None:
    with pytest.raises(UsageError, match="unusable name for a folder"):
        Home(tmp_path).attempt("wf-1", name, 0)
    with pytest.raises(UsageError):
        Home(tmp_path).attempt(name, "t", 0)
    with pytest.raises(UsageError):
        Home(tmp_path).dataset_version(name, 1)


def test_an_empty_name_fails(tmp_path: Path) -> None:
    with pytest.raises(UsageError):
        Home(tmp_path).attempt("wf-1", "", 0)


def test_attempt_ids_map_to_their_folders(tmp_path: Path) -> None:
    home = Home(tmp_path)
    dirs = home.attempt_of("wf-1:t:2")
    assert dirs is not None and dirs.root == tmp_path.absolute() / "runs" / "wf-1" / "t" / "2"
    assert dirs.url_inputs == dirs.root.with_name("2.inputs")
    assert home.run_record("wf-1") == tmp_path / "runs" / "wf-1" / "run.mcap"
    for malformed in ("garbage", "wf-1:t:x", "wf-1:..:0", "a/b:t:0", ":t:0"):
        assert home.attempt_of(malformed) is None, malformed
