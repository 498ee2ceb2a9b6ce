"""Reading episode files of format 1 (osmo before the Foxglove-native layout), read-only.

Format 1 packed up to 100 steps per JSON message on ``/episode/steps`` (observation, action
and reward as base64 little-endian tensors ``{"dtype", "shape", "data"}``), one summary per
episode on ``/episode/end`` and frames as JSON ``foxglove.RawImage`` with base64 data on
``/camera/rgb``. Files written that way still convert (``lerobot.dataset``, ``osmo view``);
nothing writes them any more.
"""

from __future__ import annotations

import base64
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from osmo.record import McapFile

__all__ = ["read_v1", "unpack"]

STEP_TOPIC, END_TOPIC, FRAME_TOPIC = "/episode/steps", "/episode/end", "/camera/rgb"


def unpack(tensor: Mapping[str, Any]) -> np.ndarray:
    """The array of a format-1 packed tensor."""
    raw = base64.b64decode(tensor["data"])
    return np.frombuffer(raw, dtype=np.dtype(tensor["dtype"])).reshape(tensor["shape"])


def _frame(msg: Mapping[str, Any]) -> np.ndarray:
    raw = np.frombuffer(base64.b64decode(msg["data"]), dtype=np.uint8)
    return raw.reshape(int(msg["height"]), int(msg["width"]), 3)


def read_v1(f: McapFile, meta: dict[str, str]) -> Iterator[Any]:
    """Yield the :class:`~osmo_plugins.episodes.Episode` s of an open format-1 file."""
    from osmo_plugins.episodes import Episode

    steps: dict[int, list[dict[str, Any]]] = {}
    frames: dict[int, list[tuple[int, np.ndarray]]] = {}
    ends: dict[int, dict[str, Any]] = {}
    for m in f.messages([STEP_TOPIC, END_TOPIC, FRAME_TOPIC]):
        if m.topic == STEP_TOPIC:
            steps.setdefault(m.value["episode"], []).append(m.value)  # blocks
        elif m.topic == END_TOPIC:
            ends[m.value["episode"]] = m.value
        else:
            frames.setdefault(m.value["episode"], []).append((m.value["t"], _frame(m.value)))
    for index in sorted(steps):
        blocks = sorted(steps[index], key=lambda b: b["t0"])

        def column(key: str, blocks: list[dict[str, Any]] = blocks) -> np.ndarray:
            return np.concatenate([unpack(b[key]) for b in blocks])

        yield Episode(
            index=index, seed=int(ends.get(index, {}).get("seed", -1)),
            observations=column("observation").astype(np.float32),
            actions=column("action").astype(np.float32),
            rewards=column("reward").astype(np.float32),
            terminated=bool(blocks[-1]["terminated"][-1]),
            truncated=bool(blocks[-1]["truncated"][-1]),
            frames=(np.stack([img for _, img in sorted(frames[index], key=lambda p: p[0])])
                    if index in frames else None),
            meta=dict(meta))
