"""Spec edges refused at ``validate`` with their position instead of failing at start."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.conftest import Osmo, write

SPEC = """workflow:
  name: edge
  tasks:
  - name: a
    command: [cat, /]
    files:
    - path: %s
      contents: x
"""


@pytest.mark.parametrize("path", ["/", ".", "/etc/", "./"])
def test_a_file_path_that_names_a_folder_is_refused_before_anything_runs(
        osmo: Osmo, tmp_path: Path, path: str) -> None:
    spec = write(tmp_path / "edge.yaml", SPEC % f"'{path}'")
    for verb in ("validate", "submit"):
        r = osmo(verb, str(spec))
        assert r.code == 2, r
        assert f"{spec}:7:13: file path '{path}' in task 'a' names a folder, not a file" in r.err
    assert osmo("list", "--format", "json", check=True).json() == []
