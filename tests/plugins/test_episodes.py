"""The MCAP episode format: written through osmo.record, read back exactly."""

from __future__ import annotations

from pathlib import Path

import pytest

np = pytest.importorskip("numpy")

from osmo_plugins.episodes import (  # noqa: E402
    END_TOPIC,
    FRAME_TOPIC,
    METADATA_NAME,
    STEP_TOPIC,
    EpisodeWriter,
    episode_files,
    read_episodes,
)

from osmo.record import LineageMcapWriter, McapFile  # noqa: E402


def _write(path: Path, frames: bool) -> None:
    rng = np.random.default_rng(0)
    with LineageMcapWriter(path, None) as mcap:
        w = EpisodeWriter(mcap, {"env": "Fake-v0", "policy": "random"}, dt=0.04,
                          with_frames=frames)
        for ep, length in enumerate((3, 5)):
            for t in range(length):
                frame = rng.integers(0, 255, (8, 6, 3), dtype=np.uint8) if frames else None
                w.step(ep, t, [t, ep, 0.5], [0.1 * t], 1.0, False, t == length - 1, frame)
            w.end(ep, 100 + ep, float(length), length, False, True)


@pytest.mark.parametrize("frames", [False, True])
def test_round_trip(tmp_path: Path, frames: bool) -> None:
    path = tmp_path / "e.mcap"
    _write(path, frames)
    eps = list(read_episodes(path))
    assert [e.length for e in eps] == [3, 5]
    assert [e.seed for e in eps] == [100, 101]
    assert eps[1].observations.shape == (5, 3) and eps[1].actions.shape == (5, 1)
    assert eps[1].observations[4].tolist() == [4, 1, 0.5]
    assert eps[0].truncated and not eps[0].terminated
    assert eps[0].meta["env"] == "Fake-v0" and eps[0].meta["format"] == "1"
    if frames:
        assert eps[1].frames is not None and eps[1].frames.shape == (5, 8, 6, 3)
    else:
        assert eps[1].frames is None


def test_channels_have_json_schemas(tmp_path: Path) -> None:
    path = tmp_path / "e.mcap"
    _write(path, True)
    with McapFile(path) as f:
        chans = {c.topic: c for c in f.channels()}
        assert f.metadata(METADATA_NAME)
    assert set(chans) == {STEP_TOPIC, END_TOPIC, FRAME_TOPIC}
    assert all(c.schema_encoding == "jsonschema" and c.message_encoding == "json"
               for c in chans.values())
    assert chans[FRAME_TOPIC].schema_name == "foxglove.RawImage"
    assert chans[STEP_TOPIC].message_count == 2  # one block per episode (block=100)


def test_not_an_episode_file(tmp_path: Path) -> None:
    path = tmp_path / "plain.mcap"
    with LineageMcapWriter(path, None) as mcap:
        mcap.add_json_channel("/x", "X", {"type": "object"})
    with pytest.raises(ValueError, match="not an osmo episode file"):
        list(read_episodes(path))


def test_episode_files_orders_by_folder(tmp_path: Path) -> None:
    (tmp_path / "b").mkdir()
    (tmp_path / "a").mkdir()
    for p in ("b/2.mcap", "b/1.mcap", "a/0.mcap"):
        (tmp_path / p).write_bytes(b"")
    got = episode_files([tmp_path / "b", tmp_path / "a"])
    assert [p.relative_to(tmp_path).as_posix() for p in got] == ["b/1.mcap", "b/2.mcap", "a/0.mcap"]
