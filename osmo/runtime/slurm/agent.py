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
- ``gang.json`` (a group's member, one component of a heterogeneous job): ``hosts``, the
  placeholder ``__OSMO_SLURM_HOST_<i>__`` of each member, replaced in the task's argv,
  environment and files by the address of the node Slurm gave component ``i``
  (``SLURM_JOB_NODELIST_HET_GROUP_<i>``, its ``NodeAddr`` from ``scontrol``); ``after``, an
  argv that prints ``true`` once the group's lead runs (a peer starts after its lead, at
  most 30 s later, as in OSMO).

With ``--own-output`` (a gang's members, started by one ``srun``) the task's stdout and
stderr go to the folder's ``out`` and ``err`` (appended); otherwise Slurm's ``--output``
and ``--error`` already point there.

What Slurm gives the job (``SLURM_*``, ``SLURMD_NODENAME``, ``CUDA_VISIBLE_DEVICES``: the
GPUs it allocated) is added to the task's environment. SIGTERM, SIGINT, SIGHUP, SIGUSR1 and
SIGUSR2 (``scancel --signal``, Slurm's time limit) are passed on to the task's process group.

It must not import osmo: the compute node may not have it.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

_FROM_SLURM = ("SLURM_", "SLURMD_", "CUDA_VISIBLE_DEVICES", "GPU_DEVICE_ORDINAL",
               "ROCR_VISIBLE_DEVICES")
_FORWARDED = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2)


PLACEHOLDER = "__OSMO_SLURM_HOST_{}__"
_LEAD_WAIT = 30.0


def main(folder: Path, *, own_output: bool = False) -> int:
    """Run the attempt described in ``folder``; its exit code (also in ``exit.json``)."""
    if own_output:
        for fd, name in ((1, "out"), (2, "err")):
            target = os.open(folder / name, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
            os.dup2(target, fd)
            os.close(target)
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
    argv = launch["argv"]
    gang_file = folder / "gang.json"
    if gang_file.exists():
        gang = json.loads(gang_file.read_text())
        hosts = {PLACEHOLDER.format(i): address(i) for i in range(int(gang["size"]))}
        argv = [replace_all(word, hosts) for word in argv]
        env = {k: replace_all(v, hosts) for k, v in env.items()}
        if launch.get("files"):
            rewrite(Path(launch["files"]), hosts)
        if gang.get("after"):
            wait_for(gang["after"], gang.get("after_env") or env)
    code = run(argv, launch["cwd"], env)
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


def address(index: int) -> str:
    """Where the node of heterogeneous component ``index`` is reached (its NodeAddr)."""
    node = os.environ.get(f"SLURM_JOB_NODELIST_HET_GROUP_{index}", "").split(",")[0]
    try:
        shown = subprocess.run(["scontrol", "show", "node", "--oneliner", node],
                               capture_output=True, text=True, timeout=30, check=False).stdout
    except (OSError, subprocess.TimeoutExpired):
        return node
    for word in shown.split():
        if word.startswith("NodeAddr="):
            return word.partition("=")[2]
    return node


def replace_all(text: str, values: dict[str, str]) -> str:
    """``text`` with every key of ``values`` replaced by its value."""
    for key, value in values.items():
        text = text.replace(key, value)
    return text


def rewrite(folder: Path, values: dict[str, str]) -> None:
    """Replace the placeholders in every file under ``folder`` (the task's ``files:``)."""
    for path in folder.rglob("*"):
        if path.is_file() and not path.is_symlink():
            data = path.read_bytes()
            if b"__OSMO_SLURM_HOST_" in data:
                text = replace_all(data.decode("utf-8", "surrogateescape"), values)
                path.write_bytes(text.encode("utf-8", "surrogateescape"))


def wait_for(argv: list[str], env: dict[str, str]) -> None:
    """Until ``argv`` prints ``true`` (the lead runs), at most 30 s."""
    deadline = time.monotonic() + _LEAD_WAIT
    while time.monotonic() < deadline:
        try:
            said = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=10,
                                  check=False).stdout
        except (OSError, subprocess.TimeoutExpired):
            said = ""
        if said.strip() == "true":
            return
        time.sleep(0.1)


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
    own = "--own-output" in sys.argv[1:-1]
    sys.exit(main(Path(sys.argv[-1]), own_output=own))
