"""The MCAP episode format shared by every robotics plugin: how rollouts are written and read.

One MCAP file holds the episodes of one shard. Channels (JSON encoding, JSON-Schema schemas,
so Foxglove and rerun show them without a plugin)::

    /episode/steps     a block of up to ``block`` consecutive env steps of one episode:
                       episode, t0, n, observation (n×obs_dim), action (n×act_dim), reward (n),
                       terminated[n], truncated[n]; the three arrays are packed tensors
                       ``{"dtype": "<f4", "shape": [...], "data": base64 little-endian}``
    /episode/end       one per episode: episode, seed, return, length, terminated, truncated
    /camera/rgb        optional, one per step: a foxglove.RawImage (rgb8, base64 data)

plus one metadata record ``osmo.episodes`` (env, policy, seed, shard, obs/action sizes, fps).
Log times are synthetic and deterministic (step count × the env's dt; a block is stamped with
its first step), so the same rollout writes the same messages. Steps travel in blocks because
one message per step cost as much as the simulation itself (one MCAP record and one JSON
encoding per step, ~30 µs), and arrays are packed because formatting floats as JSON text
(~0.5–0.9 µs each) alone cost 20% of a 1-DoF env's step; observations and actions are float32
(what LeRobot stores), rewards float64. See bench/bench_datagen.py.

This module imports only numpy and :mod:`osmo.record`; it must not import gymnasium, mujoco,
torch or lerobot.
"""

from __future__ import annotations

import base64
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from osmo.record import McapFile

__all__ = [
    "END_TOPIC",
    "FORMAT_VERSION",
    "FRAME_TOPIC",
    "METADATA_NAME",
    "STEP_TOPIC",
    "Episode",
    "EpisodeWriter",
    "episode_files",
    "pack",
    "read_episodes",
    "unpack",
]

FORMAT_VERSION = "1"
STEP_TOPIC = "/episode/steps"
END_TOPIC = "/episode/end"
FRAME_TOPIC = "/camera/rgb"
METADATA_NAME = "osmo.episodes"

_NUMBERS = {"type": "array", "items": {"type": "number"}}
_TENSOR = {"type": "object", "properties": {
    "dtype": {"type": "string", "enum": ["<f4", "<f8"]},
    "shape": {"type": "array", "items": {"type": "integer"}},
    "data": {"type": "string", "contentEncoding": "base64"}}}
_FLAGS = {"type": "array", "items": {"type": "boolean"}}
STEP_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "osmo.EpisodeSteps",
    "description": "consecutive steps t0, t0+1, ... of one episode; row i is step t0+i",
    "properties": {
        "episode": {"type": "integer"}, "t0": {"type": "integer"}, "n": {"type": "integer"},
        "observation": _TENSOR, "action": _TENSOR, "reward": _TENSOR,
        "terminated": _FLAGS, "truncated": _FLAGS,
    },
    "required": ["episode", "t0", "n", "observation", "action", "reward", "terminated",
                 "truncated"],
}
END_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "osmo.EpisodeEnd",
    "properties": {
        "episode": {"type": "integer"}, "seed": {"type": "integer"},
        "return": {"type": "number"}, "length": {"type": "integer"},
        "terminated": {"type": "boolean"}, "truncated": {"type": "boolean"},
    },
}
RAW_IMAGE_SCHEMA: dict[str, Any] = {  # foxglove.RawImage, JSON flavour (bytes as base64)
    "type": "object",
    "title": "foxglove.RawImage",
    "properties": {
        "timestamp": {"type": "object", "properties": {
            "sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
        "frame_id": {"type": "string"}, "width": {"type": "integer"},
        "height": {"type": "integer"}, "encoding": {"type": "string"},
        "step": {"type": "integer"},
        "data": {"type": "string", "contentEncoding": "base64"},
    },
}


@dataclass
class Episode:
    """One episode read back: arrays over time (``frames`` is None without rendering)."""

    index: int
    seed: int
    observations: np.ndarray  # (T, obs_dim) float32
    actions: np.ndarray  # (T, act_dim) float32
    rewards: np.ndarray  # (T,) float32
    terminated: bool
    truncated: bool
    frames: np.ndarray | None = None  # (T, H, W, 3) uint8
    meta: dict[str, str] = field(default_factory=dict)

    @property
    def length(self) -> int:
        """Number of steps."""
        return int(self.rewards.shape[0])

    @property
    def total_reward(self) -> float:
        """Sum of rewards."""
        return float(self.rewards.sum())


def pack(array: np.ndarray) -> dict[str, Any]:
    """A little-endian numeric array as a JSON-safe packed tensor."""
    return {"dtype": array.dtype.str, "shape": list(array.shape),
            "data": base64.b64encode(np.ascontiguousarray(array).tobytes()).decode("ascii")}


def unpack(tensor: Mapping[str, Any]) -> np.ndarray:
    """The array of a packed tensor (see :func:`pack`)."""
    raw = base64.b64decode(tensor["data"])
    return np.frombuffer(raw, dtype=np.dtype(tensor["dtype"])).reshape(tensor["shape"])


class EpisodeWriter:
    """Writes episodes into an open ``osmo.record`` JSON MCAP writer (e.g. ``ctx.mcap_writer``).

    Steps are buffered and written in blocks of ``block``; :meth:`end` flushes an episode's
    last block, so call it for every episode (or :meth:`flush` before closing the file).

    Args:
        writer: a :class:`osmo.record.JsonMcapWriter` (or subclass), not yet closed.
        metadata: the ``osmo.episodes`` record (env, policy, seed, ...); strings only.
        dt: seconds per env step, for log times.
        with_frames: register the camera channel.
        block: steps per ``/episode/steps`` message.
    """

    def __init__(self, writer: Any, metadata: Mapping[str, str], *, dt: float,
                 with_frames: bool = False, block: int = 100) -> None:
        self._w = writer
        self._dt_ns = max(1, int(round(dt * 1e9)))
        self._clock = 0
        self._block = max(1, int(block))
        self._buf: list[tuple[Any, Any, float, bool, bool]] = []
        self._buf_start = (0, 0, 0)  # episode, t0, clock of the first buffered step
        self._step = writer.add_json_channel(STEP_TOPIC, "osmo.EpisodeSteps", STEP_SCHEMA)
        self._end = writer.add_json_channel(END_TOPIC, "osmo.EpisodeEnd", END_SCHEMA)
        self._frame = (writer.add_json_channel(FRAME_TOPIC, "foxglove.RawImage",
                                               RAW_IMAGE_SCHEMA) if with_frames else None)
        writer.add_metadata(METADATA_NAME, {"format": FORMAT_VERSION, **metadata})

    def step(self, episode: int, t: int, observation: Any, action: Any, reward: float,
             terminated: bool, truncated: bool, frame: np.ndarray | None = None) -> None:
        """Record one step: the observation the action was chosen from, and its outcome."""
        if self._buf and self._buf_start[0] != episode:
            self.flush()
        if not self._buf:
            self._buf_start = (episode, t, self._clock)
        self._buf.append((observation, action, reward, terminated, truncated))
        stamp = self._clock * self._dt_ns
        self._clock += 1
        if frame is not None and self._frame is not None:
            self._write_frame(episode, t, stamp, frame)
        if len(self._buf) >= self._block:
            self.flush()

    def _write_frame(self, episode: int, t: int, stamp: int, frame: np.ndarray) -> None:
        h, w = int(frame.shape[0]), int(frame.shape[1])
        self._w.write(self._frame, {
            "timestamp": {"sec": stamp // 1_000_000_000, "nsec": stamp % 1_000_000_000},
            "frame_id": "camera", "episode": episode, "t": t, "width": w, "height": h,
            "encoding": "rgb8", "step": w * 3,
            "data": base64.b64encode(np.ascontiguousarray(frame, np.uint8)).decode()}, stamp)

    def flush(self) -> None:
        """Write the buffered steps as one block."""
        if not self._buf:
            return
        episode, t0, clock = self._buf_start
        obs, act, rew, term, trunc = zip(*self._buf, strict=True)
        self._buf = []
        n = len(obs)
        self._w.write(self._step, {
            "episode": episode, "t0": t0, "n": n,
            "observation": pack(np.asarray(obs, "<f4").reshape(n, -1)),
            "action": pack(np.asarray(act, "<f4").reshape(n, -1)),
            "reward": pack(np.asarray(rew, "<f8")), "terminated": [bool(x) for x in term],
            "truncated": [bool(x) for x in trunc]}, clock * self._dt_ns)

    def end(self, episode: int, seed: int, total: float, length: int, terminated: bool,
            truncated: bool) -> None:
        """Flush the episode's steps and record its summary."""
        self.flush()
        self._w.write(self._end, {
            "episode": episode, "seed": seed, "return": float(total), "length": length,
            "terminated": bool(terminated), "truncated": bool(truncated)},
            max(0, self._clock - 1) * self._dt_ns)


def episode_files(folders: list[Path] | tuple[Path, ...]) -> list[Path]:
    """Every ``*.mcap`` under the folders, sorted by folder order then path."""
    out: list[Path] = []
    for folder in folders:
        folder = Path(folder)
        out.extend([folder] if folder.is_file() else sorted(folder.rglob("*.mcap")))
    return out


def _decode_frame(msg: Mapping[str, Any]) -> np.ndarray:
    raw = np.frombuffer(base64.b64decode(msg["data"]), dtype=np.uint8)
    return raw.reshape(int(msg["height"]), int(msg["width"]), 3)


def read_episodes(path: Path | str) -> Iterator[Episode]:
    """Yield the episodes of one episode MCAP file, in episode order.

    Raises:
        osmo.record.RecordError: not a readable MCAP; ValueError: not an episode file.
    """
    with McapFile(path) as f:
        meta_records = f.metadata(METADATA_NAME)
        if not meta_records:
            raise ValueError(f"{path}: no {METADATA_NAME} metadata; not an osmo episode file")
        meta = meta_records[-1][1]
        steps: dict[int, list[dict[str, Any]]] = {}
        frames: dict[int, list[tuple[int, np.ndarray]]] = {}
        ends: dict[int, dict[str, Any]] = {}
        for m in f.messages([STEP_TOPIC, END_TOPIC, FRAME_TOPIC]):
            if m.topic == STEP_TOPIC:
                steps.setdefault(m.value["episode"], []).append(m.value)  # blocks
            elif m.topic == END_TOPIC:
                ends[m.value["episode"]] = m.value
            else:
                frames.setdefault(m.value["episode"], []).append(
                    (m.value["t"], _decode_frame(m.value)))
    for index in sorted(steps):
        blocks = sorted(steps[index], key=lambda b: b["t0"])
        end = ends.get(index, {})

        def column(key: str, blocks: list[dict[str, Any]] = blocks) -> np.ndarray:
            return np.concatenate([unpack(b[key]) for b in blocks])

        yield Episode(
            index=index, seed=int(end.get("seed", -1)),
            observations=column("observation").astype(np.float32),
            actions=column("action").astype(np.float32),
            rewards=column("reward").astype(np.float32),
            terminated=bool(blocks[-1]["terminated"][-1]),
            truncated=bool(blocks[-1]["truncated"][-1]),
            frames=(np.stack([img for _, img in sorted(frames[index], key=lambda p: p[0])])
                    if index in frames else None),
            meta=dict(meta))
