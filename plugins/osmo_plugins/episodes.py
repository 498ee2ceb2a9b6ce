"""The MCAP episode format shared by every robotics plugin: how rollouts are written and read.

Format 2, Foxglove-native: a file opens in Foxglove (or rerun) as it is. One MCAP file holds
the episodes of one rollout shard or one evaluation run::

    /episode/step   one message per env step, protobuf ``osmo.EpisodeStep``: episode, t,
                    observation[], action[] (float32), reward (float64), done, terminated,
                    truncated; Foxglove's Plot panel plots ``/episode/step.reward``,
                    ``.observation[0]``, ``.action[1]``, ``.done`` directly
    /camera/rgb     optional, one ``foxglove.RawImage`` (rgb8) per step, at the step's time

Log times are the simulation clock: step ``t`` of an episode that began at clock ``c`` is
stamped ``(c + t)·dt``, and the clock runs on across episodes, so times are monotonic over the
file and deterministic (the same rollout writes the same messages). The step's message holds
the observation the action was chosen from and what the step returned.

Metadata records: ``osmo.episodes`` (``format`` "2", env, policy, seed, sizes, fps), one
``osmo.episode`` per episode (its boundaries: episode, seed, return, length, terminated,
truncated, start_ns, end_ns) and ``osmo.lineage`` (who made the file).

Files of format 1 (JSON blocks of 100 steps) still read, through
:mod:`osmo_plugins._episodes_v1`; any other version fails with a message naming it.

The file is written by the Foxglove SDK (:mod:`osmo_plugins.foxglove_io`; its Rust MCAP writer
keeps one message per step within the recording budget, see bench/bench_datagen.py) and read
with :class:`osmo.record.McapFile` plus the protobuf schemas the file declares. This module
must not import gymnasium, mujoco, torch or lerobot.
"""

from __future__ import annotations

import functools
import uuid
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from osmo.record import LINEAGE_METADATA, Lineage, McapFile
from osmo_plugins._base import Committing
from osmo_plugins._episodes_v1 import read_v1
from osmo_plugins._stepcodec import STEP_FIELDS, encode_steps
from osmo_plugins.foxglove_io import FoxgloveMcapWriter, ProtoSchema, protobuf_decoder

__all__ = [
    "EPISODE_METADATA",
    "FORMAT_VERSION",
    "FRAME_TOPIC",
    "METADATA_NAME",
    "STEP_TOPIC",
    "Episode",
    "EpisodeWriter",
    "episode_files",
    "read_episodes",
    "step_schema",
    "task_lineage",
]

FORMAT_VERSION = "2"
READABLE = ("1", FORMAT_VERSION)
STEP_TOPIC = "/episode/step"
FRAME_TOPIC = "/camera/rgb"
METADATA_NAME = "osmo.episodes"
EPISODE_METADATA = "osmo.episode"
STEP_SCHEMA_NAME = "osmo.EpisodeStep"
IMAGE_SCHEMA_NAME = "foxglove.RawImage"


@functools.cache
def step_schema() -> ProtoSchema:
    """The ``osmo.EpisodeStep`` protobuf schema (built once, on first use)."""
    return ProtoSchema(STEP_SCHEMA_NAME, STEP_FIELDS)


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


def task_lineage(ctx: Any) -> Lineage | None:
    """The lineage osmo stamps into MCAP files written by the task of ``ctx``.

    The task-context API hands lineage out only inside ``ctx.mcap_writer`` (a JSON MCAP
    writer), so an unused one is opened for its ``lineage`` and discarded unwritten.
    """
    probe = ctx.mcap_writer(f".lineage-{uuid.uuid4().hex[:8]}.mcap")
    try:
        return getattr(probe, "lineage", None)
    finally:
        probe.abort()


class EpisodeWriter(Committing):
    """Writes episodes to a new episode MCAP file at ``path`` (it appears there on close).

    Call :meth:`step` for every step and :meth:`end` after each episode, then :meth:`close`
    (or use it as a context manager: an exception discards the file). Steps are encoded and
    written ``block`` at a time (:mod:`osmo_plugins._stepcodec` says why), still one message
    per step.

    Args:
        path: the file to write.
        metadata: the ``osmo.episodes`` record (env, policy, seed, ...); strings only.
        dt: seconds per env step (the simulation clock).
        with_frames: register the camera channel.
        lineage: stamped as the ``osmo.lineage`` record (see :func:`task_lineage`).
        block: steps buffered before they are encoded and written.
    """

    def __init__(self, path: Path | str, metadata: Mapping[str, str], *, dt: float,
                 with_frames: bool = False, lineage: Lineage | None = None,
                 block: int = 100) -> None:
        self._file = FoxgloveMcapWriter(path)
        self._log_step = self._file.protobuf_channel(STEP_TOPIC, step_schema())
        self._log_frame = self._file.raw_image_channel(FRAME_TOPIC) if with_frames else None
        self._meta = {"format": FORMAT_VERSION, **metadata}
        self._lineage = lineage
        self._dt_ns = max(1, int(round(dt * 1e9)))
        self._clock = 0  # steps written so far
        self._episodes: list[dict[str, str]] = []
        self._block = max(1, int(block))
        self._rows: list[tuple[Any, ...]] = []
        self._frames: list[tuple[np.ndarray, int]] = []

    @classmethod
    def for_task(cls, ctx: Any, name: str, metadata: Mapping[str, str], *, dt: float,
                 with_frames: bool = False) -> EpisodeWriter:
        """A writer for ``name`` under the task's output, stamped with its lineage."""
        return cls(Path(ctx.output) / name, metadata, dt=dt, with_frames=with_frames,
                   lineage=task_lineage(ctx))

    def step(self, episode: int, t: int, observation: Any, action: Any, reward: float,
             terminated: bool, truncated: bool, frame: np.ndarray | None = None) -> None:
        """Record one step: the observation the action was chosen from, and its outcome."""
        rows = self._rows
        rows.append((episode, t, observation, action, reward, terminated, truncated))
        if frame is not None and self._log_frame is not None:
            self._frames.append((np.ascontiguousarray(frame, np.uint8), len(rows) - 1))
        if len(rows) >= self._block:
            self.flush()

    def flush(self) -> None:
        """Encode and write the buffered steps (and frames); the clock moves on by as many."""
        if not self._rows:
            return
        dt, first = self._dt_ns, self._clock
        for i, message in enumerate(encode_steps(self._rows)):
            self._log_step(message, (first + i) * dt)
        if self._log_frame is not None:
            for frame, i in self._frames:
                self._log_frame(frame, (first + i) * dt)
        self._clock += len(self._rows)
        self._rows, self._frames = [], []

    def end(self, episode: int, seed: int, total: float, length: int, terminated: bool,
            truncated: bool) -> None:
        """Close the episode whose ``length`` steps were the last ones recorded.

        Its boundaries and summary become an ``osmo.episode`` record.
        """
        self.flush()
        start = max(0, self._clock - length) * self._dt_ns
        self._episodes.append({
            "episode": str(episode), "seed": str(seed), "return": repr(float(total)),
            "length": str(length), "terminated": str(bool(terminated)).lower(),
            "truncated": str(bool(truncated)).lower(), "start_ns": str(start),
            "end_ns": str(max(start, (self._clock - 1) * self._dt_ns))})

    def abort(self) -> None:
        """Discard the file."""
        self._file.abort()

    def close(self) -> None:
        """Write the metadata records and finish the file."""
        self.flush()
        self._file.add_metadata(METADATA_NAME, self._meta)
        for record in self._episodes:
            self._file.add_metadata(EPISODE_METADATA, record)
        if self._lineage is not None:
            self._file.add_metadata(LINEAGE_METADATA, self._lineage.to_metadata())
        self._file.close()


def episode_files(folders: list[Path] | tuple[Path, ...]) -> list[Path]:
    """Every ``*.mcap`` under the folders, sorted by folder order then path."""
    out: list[Path] = []
    for folder in folders:
        folder = Path(folder)
        out.extend([folder] if folder.is_file() else sorted(folder.rglob("*.mcap")))
    return out


def read_episodes(path: Path | str) -> Iterator[Episode]:
    """Yield the episodes of one episode MCAP file (format 2, or 1), in episode order.

    Raises:
        osmo.record.RecordError: not a readable MCAP; ValueError: not an episode file, a
            format version this osmo cannot read, or inconsistent steps.
    """
    with McapFile(path) as f:
        records = f.metadata(METADATA_NAME)
        if not records:
            raise ValueError(f"{path}: no {METADATA_NAME} metadata; not an osmo episode file")
        meta = records[-1][1]
        version = meta.get("format", "")
        if version not in READABLE:
            raise ValueError(f"{path}: episode format version {version!r} cannot be read by "
                             f"this osmo (it reads versions {', '.join(READABLE)}); "
                             "upgrade osmo")
        episodes = list(read_v1(f, meta) if version == "1" else _read_v2(f, meta, path))
    yield from episodes


def _decoder(f: McapFile, topic: str, schema_name: str, path: Path | str) -> Any:
    """The protobuf decoder of ``topic`` from the schema the file declares, or None."""
    for channel in f.channels():
        if channel.topic != topic:
            continue
        if channel.message_encoding != "protobuf" or channel.schema_name != schema_name:
            raise ValueError(f"{path}: {topic} holds {channel.message_encoding} "
                             f"{channel.schema_name!r}, not protobuf {schema_name}")
        return protobuf_decoder(schema_name, channel.schema, path)
    return None


def _image(msg: Any, path: Path | str) -> np.ndarray:
    if msg.encoding != "rgb8" or msg.step < msg.width * 3:
        raise ValueError(f"{path}: a camera frame is {msg.encoding!r} with step {msg.step}; "
                         "episode frames are rgb8")
    rows = np.frombuffer(msg.data, np.uint8)
    if rows.size != msg.step * msg.height:
        raise ValueError(f"{path}: a {msg.width}x{msg.height} frame holds {rows.size} bytes")
    return rows.reshape(msg.height, msg.step)[:, : msg.width * 3].reshape(
        msg.height, msg.width, 3)


def _read_v2(f: McapFile, meta: dict[str, str], path: Path | str) -> Iterator[Episode]:
    step = _decoder(f, STEP_TOPIC, STEP_SCHEMA_NAME, path)
    if step is None:
        return
    frame = _decoder(f, FRAME_TOPIC, IMAGE_SCHEMA_NAME, path)
    steps: dict[int, list[Any]] = {}
    at: dict[int, tuple[int, int]] = {}
    images: dict[int, np.ndarray] = {}
    for m in f.messages([STEP_TOPIC, FRAME_TOPIC]):
        if m.topic == STEP_TOPIC:
            s = step(m.data)
            steps.setdefault(s.episode, []).append(s)
            at[m.log_time_ns] = (s.episode, s.t)
        elif frame is not None:
            images[m.log_time_ns] = _image(frame(m.data), path)
    seeds = {int(r["episode"]): int(r.get("seed", "-1"))
             for _, r in f.metadata(EPISODE_METADATA) if r.get("episode", "").isdigit()}
    frames: dict[int, dict[int, np.ndarray]] = {}
    for stamp, image in images.items():
        if stamp in at:
            episode, t = at[stamp]
            frames.setdefault(episode, {})[t] = image
    for index in sorted(steps):
        yield _episode(index, steps[index], frames.get(index), seeds.get(index, -1), meta, path)


def _episode(index: int, steps: list[Any], frames: dict[int, np.ndarray] | None, seed: int,
             meta: dict[str, str], path: Path | str) -> Episode:
    steps.sort(key=lambda s: s.t)
    if [s.t for s in steps] != list(range(len(steps))):
        raise ValueError(f"{path}: episode {index} does not hold steps 0..{len(steps) - 1}")
    try:
        observations = np.array([s.observation for s in steps], np.float32)
        actions = np.array([s.action for s in steps], np.float32)
    except ValueError as exc:
        raise ValueError(f"{path}: episode {index} changes observation or action size") \
            from exc
    images = None
    if frames:
        if len(frames) != len(steps):
            raise ValueError(f"{path}: episode {index} has {len(frames)} frames for "
                             f"{len(steps)} steps")
        images = np.stack([frames[t] for t in range(len(steps))])
    return Episode(index=index, seed=seed, observations=observations, actions=actions,
                   rewards=np.array([s.reward for s in steps], np.float32),
                   terminated=steps[-1].terminated, truncated=steps[-1].truncated,
                   frames=images, meta=dict(meta))
