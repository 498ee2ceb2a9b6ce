"""Helpers for task-type tests: write a module or an installed-looking distribution."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest


def write_dist(root: Path, name: str, entry_points: dict[str, str]) -> Path:
    """A minimal ``*.dist-info`` under ``root`` registering ``osmo.task_types`` entry points."""
    info = root / f"{name}-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n")
    lines = "".join(f"{k} = {v}\n" for k, v in entry_points.items())
    (info / "entry_points.txt").write_text(f"[osmo.task_types]\n{lines}")
    return root


@pytest.fixture
def on_path(tmp_path: Path) -> Iterator[Path]:
    """A folder put on sys.path for this test (modules imported from it are forgotten)."""
    root = tmp_path / "site"
    root.mkdir()
    sys.path.insert(0, str(root))
    before = set(sys.modules)
    yield root
    sys.path.remove(str(root))
    for name in set(sys.modules) - before:
        if str(getattr(sys.modules[name], "__file__", "") or "").startswith(str(root)):
            del sys.modules[name]
