"""Lineage targets are checked where they are read: a ``dataset:`` reference goes through
``osmo.names.parse_ref`` in ``osmo.server.lineage_query`` itself, whoever calls it."""

from __future__ import annotations

from pathlib import Path

import pytest

from osmo.errors import NotFoundError, UsageError
from osmo.server.lineage_query import resolve_target
from osmo.store.sqlite import Store


@pytest.mark.parametrize("target", ["dataset:../x", "dataset:x:../../y", "dataset:",
                                    "dataset:x:99999999999999999999999", "dataset:a/b:1"])
def test_a_hostile_dataset_reference_is_a_usage_error(tmp_path: Path, target: str) -> None:
    with pytest.raises(UsageError):
        resolve_target(Store(tmp_path / "state.db"), target)


def test_a_valid_reference_to_nothing_is_not_found(tmp_path: Path) -> None:
    with pytest.raises(NotFoundError, match="dataset 'cubes:gold' does not exist"):
        resolve_target(Store(tmp_path / "state.db"), "dataset:cubes:gold")
