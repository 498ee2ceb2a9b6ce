"""Manifest records: validation, canonical JSON round trip, stable digest."""

from __future__ import annotations

import hashlib
import json

import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

import osmo.artifacts
from osmo.artifacts import ArtifactCorrupted, Entry, Manifest, OutputRejected
from osmo.errors import InfrastructureError, OsmoError, UsageError

D1 = "sha256:" + hashlib.sha256(b"one").hexdigest()
D2 = "sha256:" + hashlib.sha256(b"two").hexdigest()


def test_public_names_are_exported_and_documented() -> None:
    assert sorted(osmo.artifacts.__all__) == [
        "ArtifactCorrupted", "ArtifactStore", "DEFAULT_GRACE", "Entry", "Manifest",
        "OutputRejected"]
    for name in osmo.artifacts.__all__:
        obj = getattr(osmo.artifacts, name)
        assert isinstance(obj, float) or obj.__doc__, name


def test_exceptions_derive_from_osmo_error() -> None:
    assert issubclass(ArtifactCorrupted, InfrastructureError)
    assert issubclass(OutputRejected, OsmoError)
    err = ArtifactCorrupted(D1, "/store/blob", D2)
    assert err.exit_code == 3 and err.digest == D1 and err.path == "/store/blob"
    assert D1 in str(err) and "/store/blob" in str(err)


def test_entries_are_sorted_and_sized() -> None:
    m = Manifest((Entry("b", D2, 3), Entry("a/x", D1, 5)))
    assert [e.path for e in m.entries] == ["a/x", "b"]
    assert m.size == 8
    assert m.get("b") == Entry("b", D2, 3) and m.get("nope") is None


def test_round_trip_and_stable_digest() -> None:
    m = Manifest((Entry("a/x", D1, 5), Entry("b", D2, 3)))
    text = m.to_json()
    assert Manifest.from_json(text) == m
    assert Manifest.from_json(json.dumps(json.loads(text), indent=2)) == m  # layout-agnostic
    assert m.digest == "sha256:" + hashlib.sha256(text.encode()).hexdigest()
    assert Manifest((Entry("b", D2, 3), Entry("a/x", D1, 5))).digest == m.digest
    assert Manifest((Entry("b", D2, 4), Entry("a/x", D1, 5))).digest != m.digest
    assert json.loads(text) == {"version": 1, "entries": [
        {"path": "a/x", "digest": D1, "size": 5}, {"path": "b", "digest": D2, "size": 3}]}


def test_empty_manifest() -> None:
    m = Manifest(())
    assert Manifest.from_json(m.to_json()) == m and m.size == 0


@pytest.mark.parametrize("path", ["", "/abs", "a/../b", "..", "./a", "a//b", "a/", "a\\b",
                                  "a\0b", "."])
def test_bad_paths_are_refused(path: str) -> None:
    with pytest.raises(UsageError, match="invalid artifact path"):
        Entry(path, D1, 1)


@pytest.mark.parametrize("digest", ["", D1[7:], "md5:" + D1[7:], D1.upper(), D1 + "0",
                                    D1[:-1], "sha256:" + "g" * 64])
def test_bad_digests_are_refused(digest: str) -> None:
    with pytest.raises(UsageError, match="invalid artifact digest"):
        Entry("a", digest, 1)


@pytest.mark.parametrize("size", [-1, 1.5, True, "3"])
def test_bad_sizes_are_refused(size: object) -> None:
    with pytest.raises(UsageError, match="invalid size"):
        Entry("a", D1, size)  # type: ignore[arg-type]


@pytest.mark.parametrize("paths", [["a", "a"], ["a", "a/b"], ["a/b/c", "a-x", "a/b"]])
def test_conflicting_paths_are_refused(paths: list[str]) -> None:
    with pytest.raises(UsageError, match="twice|both a file and a folder"):
        Manifest(tuple(Entry(p, D1, 1) for p in paths))


@pytest.mark.parametrize("text", [
    "", "[]", "{}", '{"version": 2, "entries": []}', '{"version": 1}',
    '{"version": 1, "entries": {}}', '{"version": 1, "entries": [{"path": "a"}]}',
    '{"version": 1, "entries": [{"path": "../a", "digest": "' + D1 + '", "size": 1}]}',
])
def test_from_json_rejects_bad_text(text: str) -> None:
    with pytest.raises(InfrastructureError, match="invalid artifact manifest"):
        Manifest.from_json(text)


_names = st.text(st.characters(blacklist_characters="/\\\0", blacklist_categories=("Cs",)),
                 min_size=1, max_size=8).filter(lambda s: s not in (".", ".."))


_ran: list[int] = []


@given(st.dictionaries(st.lists(_names, min_size=1, max_size=3).map("/".join),
                       st.tuples(st.binary(max_size=8), st.integers(0, 2**40)), max_size=8))
def _round_trips(files: dict[str, tuple[bytes, int]]) -> None:
    paths = set(files)
    # a file that is also the folder of another entry is not a manifest: not this property
    assume(not any(p.startswith(q + "/") for p in paths for q in paths))
    m = Manifest(tuple(Entry(p, "sha256:" + hashlib.sha256(c).hexdigest(), n)
                       for p, (c, n) in files.items()))
    again = Manifest.from_json(m.to_json())
    assert again == m and again.digest == m.digest
    _ran.append(len(files))


def test_round_trip_property() -> None:
    _ran.clear()
    _round_trips()
    # hypothesis runs 100 examples by default; most must have reached the assertion, and
    # some of them with several files (otherwise the property was tested vacuously)
    assert len(_ran) >= 50, f"only {len(_ran)} examples ran"
    assert sum(1 for n in _ran if n >= 3) >= 10, _ran


_byte_names = st.binary(min_size=1, max_size=12).filter(
    lambda b: b"/" not in b and b"\0" not in b and b"\\" not in b and b not in (b".", b".."))


@given(st.lists(_byte_names, min_size=1, max_size=6, unique=True))
def test_any_byte_name_round_trips_exactly(names: list[bytes]) -> None:
    import os

    m = Manifest(tuple(Entry(os.fsdecode(n), D1, 1) for n in names))
    text = m.to_json()
    assert text.isascii()  # valid in any JSON reader, whatever the bytes
    again = Manifest.from_json(text)
    assert sorted(os.fsencode(e.path) for e in again.entries) == sorted(names)
    assert again.digest == m.digest


def test_a_surrogate_that_names_no_byte_is_refused() -> None:
    with pytest.raises(UsageError, match="stands for no byte"):
        Entry("bad\ud800", D1, 1)
