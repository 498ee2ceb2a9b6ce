"""The job's agent: what a Slurm batch job of an attempt runs on its compute node.

Standard library only, run as a file (``python3 -I agent.py FOLDER``), so any Python 3 on
the compute node runs it, whatever is installed there. ``FOLDER`` is the attempt's job
folder on the filesystem the login host and the compute nodes share
(``osmo.runtime.slurm.runtime``); it holds:

- ``launch.json`` (0600, written by the node): the task's argv, working folder, environment
  and output folder. The argv is run as it is (no shell): user text never reaches a shell
  unless the spec's own command is one.
- ``secret.json`` (0600, written just before the submit, deleted when the attempt ends):
  its credential variables. They never appear in the batch script, in the job's
  environment as Slurm records it (``--export=NONE``), nor in ``scontrol show job``.
- ``exit.json``: written here, atomically (temporary file, then rename), when the task has
  ended: ``{"code": N}``; 128+N when it was killed by signal N; 127 when it cannot run.
- ``started``: written here when the task starts; found at a start, it means Slurm runs the
  job again (requeued after a node failure or a preemption): the output folder is emptied
  first, so nothing of the lost run is kept or duplicated.

What Slurm gives the job (``SLURM_*``, ``CUDA_VISIBLE_DEVICES``: the GPUs it allocated) is
added to the task's environment. SIGTERM, SIGINT, SIGHUP, SIGUSR1 and SIGUSR2 (``scancel
--signal``, Slurm's time limit) are passed on to the task's process group.

It must not import osmo: the compute node may not have it.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

_FROM_SLURM = ("SLURM_", "CUDA_VISIBLE_DEVICES", "GPU_DEVICE_ORDINAL", "ROCR_VISIBLE_DEVICES")
_FORWARDED = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2)


def main(folder: Path) -> int:
    """Run the attempt described in ``folder``; its exit code (also in ``exit.json``)."""
    launch = json.loads((folder / "launch.json").read_text())
    secret_file = folder / "secret.json"
    secrets = json.loads(secret_file.read_text()) if secret_file.exists() else {}
    env = {**launch["env"], **secrets}
    env.update({k: v for k, v in os.environ.items() if k.startswith(_FROM_SLURM)})
    marker = folder / "started"
    if marker.exists():
        note(f"Slurm runs this job again (job {os.environ.get('SLURM_JOB_ID', '?')} on "
             f"{os.environ.get('SLURMD_NODENAME', '?')}): the lost run's output is removed")
        empty(Path(launch["output"]))
    marker.write_text(os.environ.get("SLURM_JOB_ID", ""))
    code = run(launch["argv"], launch["cwd"], env)
    write_exit(folder, code)
    return code


def run(argv: list[str], cwd: str, env: dict[str, str]) -> int:
    """Run ``argv`` in its own process group, passing signals on; its exit code."""
    try:
        child = subprocess.Popen(argv, cwd=cwd, env=env, stdin=subprocess.DEVNULL,
                                 start_new_session=True)
    except OSError as exc:
        note(f"cannot run {argv[0]!r}: {exc.strerror or exc}")
        return 127 if isinstance(exc, FileNotFoundError) else 126

    def forward(signum: int, _frame: object) -> None:
        try:
            os.killpg(child.pid, signum)
        except ProcessLookupError:
            pass

    for signum in _FORWARDED:
        signal.signal(signum, forward)
    code = child.wait()
    return 128 - code if code < 0 else code


def empty(folder: Path) -> None:
    """Remove everything inside ``folder`` (not the folder itself)."""
    for entry in folder.iterdir() if folder.is_dir() else ():
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)


def write_exit(folder: Path, code: int) -> None:
    """``exit.json``, atomically."""
    part = folder / "exit.json.part"
    part.write_text(json.dumps({"code": code}))
    os.replace(part, folder / "exit.json")


def note(text: str) -> None:
    """An osmo line in the task's stderr."""
    sys.stderr.write(f"osmo: {text}\n")
    sys.stderr.flush()


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1])))
