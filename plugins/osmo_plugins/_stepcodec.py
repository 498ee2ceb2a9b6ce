"""Encoding blocks of ``osmo.EpisodeStep`` protobuf messages with numpy, many at a time.

Why not ``message(...).SerializeToString()`` per step: inside a simulation loop that costs
~5 µs a step here (the protobuf code is cold in the cache between env steps), 16% of a MuJoCo
pendulum's step on its own, against a recording budget of 15% for everything. The schema's
fields are chosen so that every message of a file has one fixed layout — ``fixed32``
counters, ``double`` reward, one-byte bools, packed float arrays of the file's sizes — so a
block of steps is one numpy structured array whose bytes are the messages back to back,
each field written with its tag even when zero (legal protobuf; a proto3 encoder merely
omits zeros). Any protobuf decoder reads them with the schema the file declares; the tests
decode every message with the protobuf library as the oracle.

Pure numpy; knows the field list of ``osmo.EpisodeStep`` and nothing about MCAP.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["STEP_FIELDS", "encode_steps"]

STEP_FIELDS: tuple[tuple[str, str, bool], ...] = (
    ("episode", "fixed32", False), ("t", "fixed32", False),
    ("observation", "float", True), ("action", "float", True),
    ("reward", "double", False), ("done", "bool", False),
    ("terminated", "bool", False), ("truncated", "bool", False))
"""``osmo.EpisodeStep``: (name, protobuf type, repeated), numbered 1, 2, ... in order."""

_WIRE = {"fixed32": (5, "<u4"), "double": (1, "<f8"), "bool": (0, "u1")}


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        low, n = n & 0x7F, n >> 7
        out.append(low | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _layout(sizes: dict[str, int]) -> tuple[np.dtype, dict[str, bytes]]:
    """The structured dtype of one message, and the constant prefix bytes of each field."""
    fields: list[tuple[Any, ...]] = []
    prefixes: dict[str, bytes] = {}
    for number, (name, kind, repeated) in enumerate(STEP_FIELDS, start=1):
        if repeated:  # packed: tag, byte length, the floats
            prefix = _varint(number << 3 | 2) + _varint(4 * sizes[name])
            fields += [(f"_{name}", "u1", (len(prefix),)), (name, "<f4", (sizes[name],))]
        else:
            wire, dtype = _WIRE[kind]
            prefix = _varint(number << 3 | wire)
            fields += [(f"_{name}", "u1", (len(prefix),)), (name, dtype)]
        prefixes[f"_{name}"] = prefix
    return np.dtype(fields), prefixes


def encode_steps(rows: Sequence[tuple[Any, ...]]) -> list[bytes]:
    """Encode steps as one ``osmo.EpisodeStep`` message each.

    A step is ``(episode, t, observation, action, reward, terminated, truncated)``.

    Raises:
        ValueError: the observation or action size changes between the rows.
    """
    episode, t, observations, actions, reward, terminated, truncated = zip(*rows, strict=True)
    try:
        obs = np.array(observations, np.float32).reshape(len(rows), -1)
        act = np.array(actions, np.float32).reshape(len(rows), -1)
    except ValueError as exc:
        raise ValueError("observation and action sizes must stay the same within a "
                         "file") from exc
    dtype, prefixes = _layout({"observation": obs.shape[1], "action": act.shape[1]})
    block: np.ndarray = np.zeros(len(rows), dtype)
    for name, prefix in prefixes.items():
        block[name] = np.frombuffer(prefix, np.uint8)
    ended = np.array(terminated, bool), np.array(truncated, bool)
    block["episode"], block["t"], block["reward"] = episode, t, reward
    block["observation"], block["action"] = obs, act
    block["done"] = ended[0] | ended[1]
    block["terminated"], block["truncated"] = ended
    raw, size = block.tobytes(), dtype.itemsize
    return [raw[i * size:(i + 1) * size] for i in range(len(rows))]
