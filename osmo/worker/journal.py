"""A node's journal of the attempts whose launches outlive it, so that its next life adopts them.

A node whose runtime's launches are not its children (a Slurm job, a pod: the runtime's
``outlives``) writes one entry per such attempt once it is prepared, in ``<home>/journal``
(0700, the node's private home), and removes it when the attempt's final report is made.
An entry holds what the pool needs to watch the attempt again and hand its outputs on:
its id, workflow, task and retry (its folder is ``Home.attempt`` of them: never a path read
from the file), its storage limit, its command (lineage), its image id, and the values its
log masks (its credentials' values: the file is 0600 in a 0700 folder, like the job's own
secret file). The workflow's spec is kept once per workflow beside the entries. How far the
attempt's output was shipped to the server (bytes of its stdout and stderr) is kept in a
third file per attempt, rewritten as the log is read, so that a restarted node resumes the
log where it stopped (no line twice).

Read back (:meth:`Journal.read`), every entry is checked: fields of their types, names that
make one path component each, an attempt folder that exists inside the home's ``runs/``
and is no symlink, a spec that loads and names the task. An entry that fails is dropped
with a warning (its launch, unknown to the node, is then cancelled as an orphan) and never
trusted as a path.

This module owns the journal's files; it runs nothing and decides nothing about the
attempts (``osmo.worker.remote`` and ``osmo.worker.pool`` do).
"""

from __future__ import annotations

import hashlib
import logging
import os
import stat
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from osmo.config import read_json_private, write_json_atomic
from osmo.errors import OsmoError
from osmo.layout import AttemptDirs, Home
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import TaskSpec
from osmo.spec.stored import StoredSpec

__all__ = ["Entry", "Journal"]

_log = logging.getLogger("osmo.worker")

_MAX_FILE = 4 << 20  # bytes of one journal file read back at most
_STREAMS = ("stdout", "stderr")


@dataclass(frozen=True)
class Entry:
    """One journaled attempt, as read back and checked.

    Attributes:
        attempt_id: its id.
        workflow_id, task, retry: where its folder is (``Home.attempt``).
        dirs: its folder (checked: it exists, inside the home's ``runs/``).
        spec: its task.
        argv: its command as reported for lineage.
        image_id: the image it runs in (None: none).
        secrets: the values its log masks.
        max_output_bytes: its storage limit (None: none).
        shipped: bytes of its stdout and stderr already logged and sent.
    """

    attempt_id: str
    workflow_id: str
    task: str
    retry: int
    dirs: AttemptDirs
    spec: TaskSpec
    argv: tuple[str, ...]
    image_id: str | None
    secrets: tuple[str, ...]
    max_output_bytes: int | None
    shipped: Mapping[str, int]


class Journal:
    """The journal in ``folder`` (see the module docstring); made 0700 if missing.

    Args:
        folder: the journal's folder, in the node's private home.
        spec_of: a workflow id → its stored spec (None: unknown: nothing is journaled).

    Raises:
        OsmoError: ``folder`` is a symlink or not a folder.
    """

    def __init__(self, folder: Path, spec_of: Callable[[str], StoredSpec | None]) -> None:
        self.folder = folder
        self._spec_of = spec_of
        self._specs = threading.Lock()  # a workflow's attempts are journaled from several threads
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        found = os.lstat(folder)
        if not stat.S_ISDIR(found.st_mode):
            raise OsmoError(f"the journal {folder} is not a folder (a symlink?)")
        os.chmod(folder, 0o700)

    def add(self, cmd: PrepareAttempt, *, argv: tuple[str, ...], image_id: str | None,
            secrets: tuple[str, ...], max_output_bytes: int | None) -> None:
        """Journal attempt ``cmd`` (its spec too, once per workflow). Raises OSError."""
        stored = self._spec_of(cmd.workflow_id)
        if stored is None:
            _log.warning("attempt %s is not journaled: its workflow's spec is unknown here",
                         cmd.attempt_id)
            return
        spec_file = self._file("spec", cmd.workflow_id)
        with self._specs:
            if not spec_file.exists():
                write_json_atomic(spec_file, {"workflow_id": cmd.workflow_id,
                                              "spec": stored.to_dict()})
        write_json_atomic(self._file("attempt", cmd.attempt_id), {
            "attempt_id": cmd.attempt_id, "workflow_id": cmd.workflow_id, "task": cmd.task,
            "retry": cmd.retry, "argv": list(argv), "image_id": image_id,
            "secrets": list(secrets), "max_output_bytes": max_output_bytes})

    def shipped(self, attempt_id: str, offsets: Mapping[str, int]) -> None:
        """Bytes of the attempt's stdout and stderr logged and sent so far."""
        try:
            write_json_atomic(self._file("shipped", attempt_id), dict(offsets))
        except OSError as exc:
            _log.warning("cannot journal how far %s's log was sent: %s", attempt_id, exc)

    def remove(self, attempt_id: str) -> None:
        """The attempt ended here: its entry goes (its workflow's spec stays until read)."""
        for kind in ("attempt", "shipped"):
            self._file(kind, attempt_id).unlink(missing_ok=True)

    def clear(self) -> None:
        """Remove every entry (a node whose launches do not outlive it adopts nothing)."""
        for path in self.folder.iterdir():
            path.unlink(missing_ok=True)

    def read(self, home: Home) -> list[Entry]:
        """Every valid entry; invalid ones are removed with a warning, unused specs too."""
        specs: dict[str, StoredSpec] = {}
        for path in sorted(self.folder.glob("spec-*.json")):
            try:
                data = _load(path)
                wf = _text(data, "workflow_id")
                if path != self._file("spec", wf):
                    raise ValueError("it is not under its workflow's name")
                specs[wf] = StoredSpec.from_dict(data["spec"])
            except (ValueError, KeyError, TypeError, OSError, OsmoError) as exc:
                _drop(path, exc)
        entries, used = [], set()
        for path in sorted(self.folder.glob("attempt-*.json")):
            try:
                entry = self._entry(path, home, specs)
            except (ValueError, KeyError, TypeError, OSError, OsmoError) as exc:
                _drop(path, exc)
                continue
            entries.append(entry)
            used.add(entry.workflow_id)
        for wf in set(specs) - used:
            self._file("spec", wf).unlink(missing_ok=True)
        for path in self.folder.iterdir():  # shipped offsets of no entry, temp files
            if path.name.startswith(("shipped-", ".")) and not any(
                    path == self._file("shipped", e.attempt_id) for e in entries):
                path.unlink(missing_ok=True)
        return entries

    def _entry(self, path: Path, home: Home, specs: Mapping[str, StoredSpec]) -> Entry:
        data = _load(path)
        aid, wf, task = _text(data, "attempt_id"), _text(data, "workflow_id"), _text(data, "task")
        retry = data["retry"]
        if type(retry) is not int or retry < 0:
            raise ValueError(f"retry {retry!r} is not a count")
        if path != self._file("attempt", aid):
            raise ValueError("it is not under its attempt's name")
        dirs = home.attempt(wf, task, retry)  # UsageError (an OsmoError) for a bad name
        runs = home.runs.absolute()
        if not _real_folder(dirs.root) or not dirs.root.resolve().is_relative_to(
                runs.resolve()):
            raise ValueError(f"its folder {dirs.root} is gone or not inside {runs}")
        if wf not in specs:
            raise ValueError(f"the spec of workflow {wf} is not journaled")
        spec = specs[wf].load().task(task)
        argv = data["argv"]
        secrets = data["secrets"]
        if not _strings(argv) or not _strings(secrets):
            raise ValueError("'argv' and 'secrets' must be lists of strings")
        image_id, limit = data.get("image_id"), data.get("max_output_bytes")
        if image_id is not None and not isinstance(image_id, str):
            raise ValueError("'image_id' must be a string")
        if limit is not None and (type(limit) is not int or limit < 0):
            raise ValueError("'max_output_bytes' must be a count of bytes")
        return Entry(aid, wf, task, retry, dirs, spec, tuple(argv), image_id, tuple(secrets),
                     limit, self._shipped(aid))

    def _shipped(self, attempt_id: str) -> dict[str, int]:
        """The attempt's shipped offsets (0 for a stream whose offset is missing or bad)."""
        path = self._file("shipped", attempt_id)
        try:
            data = _load(path)
        except (OSError, ValueError):
            return dict.fromkeys(_STREAMS, 0)
        return {s: v if type(v := data.get(s)) is int and v >= 0 else 0 for s in _STREAMS}

    def _file(self, kind: str, name: str) -> Path:
        """The file of ``kind`` for ``name``, named by a digest (never by the name itself)."""
        digest = hashlib.sha256(name.encode()).hexdigest()[:40]
        return self.folder / f"{kind}-{digest}.json"


def _load(path: Path) -> dict[str, Any]:
    """A journal file's object; never through a symlink, never a huge one."""
    return read_json_private(path, _MAX_FILE)


def _text(data: Mapping[str, Any], key: str) -> str:
    value = data[key]
    if not isinstance(value, str) or not value or len(value) > 4096:
        raise ValueError(f"{key!r} must be a non-empty string")
    return value


def _strings(value: object) -> bool:
    return isinstance(value, list) and all(isinstance(v, str) for v in value)


def _real_folder(path: Path) -> bool:
    """``path`` and every folder above it up to ``runs/`` is a real folder (no symlink)."""
    try:
        return all(stat.S_ISDIR(os.lstat(p).st_mode)
                   for p in (path, path.parent, path.parent.parent))
    except OSError:
        return False


def _drop(path: Path, why: BaseException) -> None:
    _log.warning("dropped the journal entry %s: %s (its launch is cancelled, not adopted)",
                 path.name, why)
    path.unlink(missing_ok=True)
