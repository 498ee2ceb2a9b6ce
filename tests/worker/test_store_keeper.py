"""The worker's store keeper on a real artifact store: what a collection removes and keeps."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from osmo.artifacts import ArtifactStore, Manifest
from osmo.layout import Home
from osmo.worker import store_keeper
from osmo.worker.held_inputs import HeldInputs
from osmo.worker.store_keeper import StoreKeeper

KIB = 1024


def _output(store: ArtifactStore, root: Path, name: str, size: int) -> Manifest:
    folder = root / name
    folder.mkdir(parents=True)
    (folder / "data").write_bytes(name.encode()[:1] * size)
    return store.ingest(folder)


@pytest.fixture
def no_grace(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(store_keeper, "GRACE", 0.0)


def test_a_collection_keeps_protected_outputs_and_the_newest_cache(
        tmp_path: Path, no_grace: None) -> None:
    store = ArtifactStore(tmp_path / "artifacts")
    held = HeldInputs(None, store)  # type: ignore[arg-type] - never fetches here
    unacked = _output(store, tmp_path / "out", "a", 100 * KIB)  # not taken by the server yet
    old, new = (_output(store, tmp_path / "out", n, 100 * KIB) for n in ("b", "c"))
    held.hold(unacked)
    held.hold(old)
    held.hold(new)
    with ThreadPoolExecutor(1) as io:
        keeper = StoreKeeper(Home(tmp_path), store, held, 300 * KIB, lambda: [unacked], io)
        removed, freed = keeper.collect()  # down to 3/4 of the limit: 225 KiB
    assert (removed, freed) == (1, 100 * KIB)  # only the oldest cached output went
    assert store.size() == 200 * KIB
    assert [m.digest for m in held.snapshot()] == [unacked.digest, new.digest]
    assert not held.holds(old)  # a task needing it fetches it again


def test_a_collection_never_removes_what_is_protected_even_over_the_limit(
        tmp_path: Path, no_grace: None) -> None:
    store = ArtifactStore(tmp_path / "artifacts")
    held = HeldInputs(None, store)  # type: ignore[arg-type]
    inputs = [_output(store, tmp_path / "out", n, 100 * KIB) for n in ("d", "e", "f")]
    with ThreadPoolExecutor(1) as io:
        keeper = StoreKeeper(Home(tmp_path), store, held, 50 * KIB, lambda: inputs, io)
        assert keeper.collect() == (0, 0)
    assert store.size() == 300 * KIB


def test_nothing_younger_than_the_grace_is_removed(tmp_path: Path) -> None:
    store = ArtifactStore(tmp_path / "artifacts")
    held = HeldInputs(None, store)  # type: ignore[arg-type]
    _output(store, tmp_path / "out", "g", 100 * KIB)  # stored just now, named by nothing yet
    with ThreadPoolExecutor(1) as io:
        keeper = StoreKeeper(Home(tmp_path), store, held, 10 * KIB, list, io)
        assert keeper.collect() == (0, 0)
