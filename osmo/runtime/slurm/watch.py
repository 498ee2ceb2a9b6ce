"""The attempt's watcher: the local process that stands for a Slurm job on the login host.

The worker pool watches every launch through a local process (``osmo.runtime.api``): for a
Slurm job it is this one, spawned by ``osmo.runtime.slurm.runtime`` right after ``sbatch``.
It copies what the job writes to its ``out`` and ``err`` files (on the shared filesystem)
to its own stdout and stderr as it comes, so they stream into ``osmo logs``; it exits with
the job's exit code:

- ``exit.json`` (the job's agent, ``osmo.runtime.slurm.agent``): the task's exit code;
  when that says it was killed (128+N), the node's verdict is awaited a little: it may
  override the code (OUT_OF_MEMORY is 137), and the node logs the reason before it;
- ``ended.json`` (the node, from Slurm's state: ``osmo.runtime.slurm.states``): the job
  ended without its agent's word (killed, out of memory, failed to start): its code.

A node that restarted starts a new watcher for a job it adopts, from what its previous life
shipped: ``python3 -I watch.py FOLDER OUT_OFFSET ERR_OFFSET``.

Standard library only, run as a file (``python3 -I watch.py FOLDER``). It polls the folder
a few times a second; it must not call Slurm (one poller per node does, for every job).
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

_TICK = 0.05
_VERDICT_WAIT = 10.0  # s a killed task's exit waits for the node's word on why


class Tail:
    """A file read from where it was last read to, into a descriptor."""

    def __init__(self, path: Path, fd: int, offset: int = 0) -> None:
        self.path, self.fd, self.offset = path, fd, offset

    def pump(self) -> None:
        """Copy what was added to the file since the last pump."""
        try:
            with self.path.open("rb") as f:
                f.seek(self.offset)
                while chunk := f.read(65536):
                    self.offset += len(chunk)
                    os.write(self.fd, chunk)
        except FileNotFoundError:
            pass


def read(path: Path) -> dict[str, object] | None:
    """A JSON file's object (None: not there yet)."""
    try:
        found = json.loads(path.read_text())
    except (FileNotFoundError, ValueError):
        return None
    return found if isinstance(found, dict) else None


def main(folder: Path, out_from: int = 0, err_from: int = 0) -> int:
    """Stream the job's output (from these offsets) until it ended; its exit code."""
    tails = [Tail(folder / "out", 1, out_from), Tail(folder / "err", 2, err_from)]
    while True:
        for tail in tails:
            tail.pump()
        own, verdict = read(folder / "exit.json"), read(folder / "ended.json")
        if own is not None or verdict is not None:
            break
        time.sleep(_TICK)
    code = int(own["code"]) if own is not None else 1  # type: ignore[call-overload]
    if own is not None and code >= 128 and verdict is None:
        deadline = time.monotonic() + _VERDICT_WAIT
        while verdict is None and time.monotonic() < deadline:
            time.sleep(_TICK)
            verdict = read(folder / "ended.json")
    for tail in tails:
        tail.pump()
    if verdict is not None:
        if own is None or verdict.get("override"):
            code = int(verdict.get("code", 1))  # type: ignore[call-overload]
    return code


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1]), *(int(arg) for arg in sys.argv[2:4])))
