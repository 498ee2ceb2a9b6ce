"""The MCAP episode format (format 2, Foxglove-native): written by the Foxglove SDK, decoded
message by message with the schemas the file declares, read back exactly; format 1 files
still convert."""

from __future__ import annotations

import base64
from pathlib import Path
from typing import Any

import pytest

np = pytest.importorskip("numpy")
pytest.importorskip("foxglove")
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory  # noqa: E402
from osmo_plugins._stepcodec import encode_steps  # noqa: E402
from osmo_plugins.episodes import (  # noqa: E402
    EPISODE_METADATA,
    FRAME_TOPIC,
    METADATA_NAME,
    STEP_TOPIC,
    EpisodeWriter,
    episode_files,
    read_episodes,
    step_schema,
)

from osmo.record import Lineage, LineageMcapWriter, McapFile, RecordError  # noqa: E402

DT = 0.04
DT_NS = 40_000_000


def _write(path: Path, frames: bool, lineage: Lineage | None = None) -> None:
    rng = np.random.default_rng(0)
    with EpisodeWriter(path, {"env": "Fake-v0", "policy": "random"}, dt=DT,
                       with_frames=frames, lineage=lineage, block=4) as w:
        for ep, length in enumerate((3, 5)):
            for t in range(length):
                frame = rng.integers(0, 255, (8, 6, 3), dtype=np.uint8) if frames else None
                w.step(ep, t, [t, ep, 0.5], [0.1 * t], 1.0, False, t == length - 1, frame)
            w.end(ep, 100 + ep, float(length), length, False, True)


def _decoder(schema_name: str, schema: bytes) -> Any:
    """A protobuf class built only from the schema the file declares (no osmo code)."""
    pool = descriptor_pool.DescriptorPool()
    for proto in descriptor_pb2.FileDescriptorSet.FromString(schema).file:
        pool.Add(proto)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


@pytest.mark.parametrize("frames", [False, True])
def test_round_trip(tmp_path: Path, frames: bool) -> None:
    path = tmp_path / "e.mcap"
    _write(path, frames)
    eps = list(read_episodes(path))
    assert [e.length for e in eps] == [3, 5]
    assert [e.seed for e in eps] == [100, 101]
    assert eps[1].observations.shape == (5, 3) and eps[1].actions.shape == (5, 1)
    assert eps[1].observations[4].tolist() == [4, 1, 0.5]
    assert eps[1].actions[:, 0].tolist() == pytest.approx([0, 0.1, 0.2, 0.3, 0.4])
    assert eps[0].truncated and not eps[0].terminated
    assert eps[0].meta["env"] == "Fake-v0" and eps[0].meta["format"] == "2"
    if frames:
        assert eps[1].frames is not None and eps[1].frames.shape == (5, 8, 6, 3)
    else:
        assert eps[1].frames is None


def test_decodes_message_by_message_with_the_declared_schemas(tmp_path: Path) -> None:
    path = tmp_path / "e.mcap"
    _write(path, True)
    with McapFile(path) as f:
        chans = {c.topic: c for c in f.channels()}
        messages = f.messages()
    assert set(chans) == {STEP_TOPIC, FRAME_TOPIC}
    assert all(c.message_encoding == "protobuf" and c.schema_encoding == "protobuf"
               for c in chans.values())
    assert chans[STEP_TOPIC].schema_name == "osmo.EpisodeStep"
    assert chans[FRAME_TOPIC].schema_name == "foxglove.RawImage"
    assert chans[STEP_TOPIC].message_count == 8  # one message per step
    step = _decoder("osmo.EpisodeStep", chans[STEP_TOPIC].schema)
    image = _decoder("foxglove.RawImage", chans[FRAME_TOPIC].schema)
    stamps = [m.log_time_ns for m in messages]
    assert stamps == sorted(stamps)
    steps = [(m.log_time_ns, step.FromString(m.data)) for m in messages if m.topic == STEP_TOPIC]
    # the simulation clock: step n of the file at n·dt, running on across episodes
    assert [s for s, _ in steps] == [n * DT_NS for n in range(8)]
    assert [(s.episode, s.t) for _, s in steps] == [(0, 0), (0, 1), (0, 2)] + [
        (1, t) for t in range(5)]
    last = steps[7][1]
    assert list(last.observation) == [4, 1, 0.5] and last.action[0] == pytest.approx(0.4)
    assert (last.reward, last.done, last.truncated, last.terminated) == (1.0, True, True, False)
    assert [s.done for _, s in steps].count(True) == 2
    frames = [(m.log_time_ns, image.FromString(m.data)) for m in messages
              if m.topic == FRAME_TOPIC]
    assert [s for s, _ in frames] == [s for s, _ in steps]  # a frame at its step's time
    for stamp, img in frames:
        assert (img.width, img.height, img.encoding, img.step) == (6, 8, "rgb8", 18)
        assert len(img.data) == 8 * 18 and img.frame_id == "camera"
        assert img.timestamp.seconds * 10**9 + img.timestamp.nanos == stamp


def test_episode_boundaries_and_lineage_are_metadata(tmp_path: Path) -> None:
    path = tmp_path / "e.mcap"
    lineage = Lineage(workflow_id="wf-1", task="rollout-0", attempt_id="a1",
                      plugin="sim.rollout@1", params={"episodes": 2})
    _write(path, False, lineage)
    with McapFile(path) as f:
        (_, meta), = f.metadata(METADATA_NAME)
        ends = [m for _, m in f.metadata(EPISODE_METADATA)]
    assert meta == {"format": "2", "env": "Fake-v0", "policy": "random"}
    assert [(e["episode"], e["seed"], e["length"], e["start_ns"], e["end_ns"]) for e in ends] == [
        ("0", "100", "3", "0", str(2 * DT_NS)), ("1", "101", "5", str(3 * DT_NS), str(7 * DT_NS))]
    assert ends[1]["truncated"] == "true" and float(ends[1]["return"]) == 5.0
    from osmo.record import read_lineage

    assert read_lineage(path) == lineage


@pytest.mark.parametrize(("obs_dim", "act_dim"), [(1, 1), (3, 2), (40, 7), (0, 1)])
def test_the_step_encoder_agrees_with_the_protobuf_library(obs_dim: int, act_dim: int) -> None:
    """Fixed-layout messages (zeros written too) decode to exactly what was encoded."""
    rng = np.random.default_rng(obs_dim)
    rows = [(e, t, rng.normal(size=obs_dim), rng.normal(size=act_dim).astype(np.float32), r,
             term, trunc)
            for e, t, r, term, trunc in [(0, 0, 0.0, False, False), (1, 7, -2.5, True, False),
                                         (2**32 - 1, 2**32 - 1, 1e300, False, True),
                                         (5, 3, float("-inf"), True, True)]]
    cls = _decoder("osmo.EpisodeStep", step_schema().data)
    for row, data in zip(rows, encode_steps(rows), strict=True):
        msg = cls.FromString(data)
        assert (msg.episode, msg.t, msg.reward, msg.terminated, msg.truncated) == (
            row[0], row[1], row[4], row[5], row[6])
        assert msg.done == (row[5] or row[6])
        assert list(msg.observation) == row[2].astype(np.float32).tolist()
        assert list(msg.action) == row[3].tolist()


def test_changing_sizes_within_a_file_is_refused() -> None:
    with pytest.raises(ValueError, match="sizes must stay the same"):
        encode_steps([(0, 0, [1.0, 2.0], [0.0], 0.0, False, False),
                      (0, 1, [1.0], [0.0], 0.0, False, False)])


def _write_v1(path: Path) -> None:
    """A file as osmo wrote it before format 2: JSON blocks of packed tensors."""
    def tensor(a: Any) -> dict[str, Any]:
        return {"dtype": a.dtype.str, "shape": list(a.shape),
                "data": base64.b64encode(a.tobytes()).decode()}

    with LineageMcapWriter(path, None) as mcap:
        steps = mcap.add_json_channel("/episode/steps", "osmo.EpisodeSteps", {"type": "object"})
        end = mcap.add_json_channel("/episode/end", "osmo.EpisodeEnd", {"type": "object"})
        frames = mcap.add_json_channel("/camera/rgb", "foxglove.RawImage", {"type": "object"})
        mcap.add_metadata(METADATA_NAME, {"format": "1", "env": "Old-v0"})
        obs = np.arange(6, dtype="<f4").reshape(3, 2)
        mcap.write(steps, {"episode": 0, "t0": 0, "n": 3, "observation": tensor(obs),
                           "action": tensor(obs[:, :1] * 2), "reward": tensor(np.ones(3)),
                           "terminated": [False, False, True], "truncated": [False] * 3}, 0)
        for t in range(3):
            mcap.write(frames, {"episode": 0, "t": t, "width": 2, "height": 1, "encoding": "rgb8",
                                "data": base64.b64encode(bytes([t] * 6)).decode()}, t)
        mcap.write(end, {"episode": 0, "seed": 9, "return": 3.0, "length": 3}, 3)


def test_format_1_files_still_convert(tmp_path: Path) -> None:
    path = tmp_path / "old.mcap"
    _write_v1(path)
    (ep,) = read_episodes(path)
    assert ep.observations.tolist() == [[0, 1], [2, 3], [4, 5]]
    assert ep.actions[:, 0].tolist() == [0, 4, 8] and ep.seed == 9 and ep.terminated
    assert ep.frames is not None and ep.frames.shape == (3, 1, 2, 3)
    assert ep.frames[2].max() == 2 and ep.meta["format"] == "1"


def test_an_unknown_version_is_named(tmp_path: Path) -> None:
    path = tmp_path / "future.mcap"
    with LineageMcapWriter(path, None) as mcap:
        mcap.add_metadata(METADATA_NAME, {"format": "3"})
    with pytest.raises(ValueError, match=r"episode format version '3' cannot be read by this "
                                         r"osmo \(it reads versions 1, 2\)"):
        list(read_episodes(path))


def test_not_an_episode_file(tmp_path: Path) -> None:
    path = tmp_path / "plain.mcap"
    with LineageMcapWriter(path, None) as mcap:
        mcap.add_json_channel("/x", "X", {"type": "object"})
    with pytest.raises(ValueError, match="not an osmo episode file"):
        list(read_episodes(path))


def test_hostile_files_fail_clearly(tmp_path: Path) -> None:
    lying = tmp_path / "lying.mcap"  # says format 2, but its steps are JSON
    with LineageMcapWriter(lying, None) as mcap:
        ch = mcap.add_json_channel(STEP_TOPIC, "osmo.EpisodeStep", {"type": "object"})
        mcap.add_metadata(METADATA_NAME, {"format": "2"})
        mcap.write(ch, {"episode": 0}, 0)
    with pytest.raises(ValueError, match="holds json 'osmo.EpisodeStep', not protobuf"):
        list(read_episodes(lying))
    good = tmp_path / "e.mcap"
    _write(good, True)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(RecordError, match="cut.mcap"):
        list(read_episodes(cut))


def test_a_failed_recording_leaves_no_file(tmp_path: Path) -> None:
    path = tmp_path / "e.mcap"
    with pytest.raises(RuntimeError, match="boom"), EpisodeWriter(path, {}, dt=DT) as w:
        w.step(0, 0, [1.0], [1.0], 1.0, False, False)
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_episode_files_orders_by_folder(tmp_path: Path) -> None:
    (tmp_path / "b").mkdir()
    (tmp_path / "a").mkdir()
    for p in ("b/2.mcap", "b/1.mcap", "a/0.mcap"):
        (tmp_path / p).write_bytes(b"")
    got = episode_files([tmp_path / "b", tmp_path / "a"])
    assert [p.relative_to(tmp_path).as_posix() for p in got] == ["b/1.mcap", "b/2.mcap", "a/0.mcap"]

