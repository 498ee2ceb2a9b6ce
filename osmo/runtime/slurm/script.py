"""An attempt's batch job as text: the script and sbatch's options (pure: runs nothing).

The decisions that keep user text out of Slurm's languages:

- The batch script is fixed text: ``exec PYTHON -I AGENT FOLDER``, its three paths quoted
  with :func:`shlex.quote`. The task's command, arguments and environment are in the
  folder's ``launch.json`` (read by the agent, run as an argv): the script never runs user
  text as shell, and ``scontrol write batch_script`` shows nothing of the task.
- Every option is one ``--opt=value`` word of sbatch's own argv, none a ``#SBATCH`` line:
  nothing a value holds can start another directive. Values osmo computes (numbers) or
  takes from the node's configuration (partition, account, QOS: plain words,
  ``osmo.options.SlurmOptions.check``) only.
- The workflow's ``exec_timeout`` is the job's ``--time``, rounded up to whole minutes
  (Slurm's unit; osmo's own timeout, the server's, ends the task first); its priority is
  ``--nice`` (HIGH none, NORMAL the pool's step, LOW twice it: a user may only lower a
  job's priority) and, where the pool configures one, its priority's QOS.
- The job's name (``osmo-<task>-<hash>``) keeps ``[A-Za-z0-9_.-]`` of the task's name, so
  ``squeue`` shows which task it is; its comment is the node's owner id, how a restarted
  node finds its jobs.
- ``--export=NONE``: the job's environment as Slurm records it is only Slurm's own; the
  agent gives the task its environment from ``launch.json``.
"""

from __future__ import annotations

import hashlib
import math
import re
import shlex
from collections.abc import Sequence
from pathlib import Path

from osmo.options import SlurmOptions
from osmo.runtime.api import PrepareError, Terms
from osmo.runtime.container.run import Mount
from osmo.spec.model import ResourceSpec

__all__ = ["batch_script", "gang_args", "gang_script", "job_args", "job_name", "pyxis_argv",
           "resource_args", "sbatch_args"]

_NAME_CHARS = re.compile(r"[^A-Za-z0-9_.-]")


def job_name(task: str, attempt_id: str) -> str:
    """``osmo-<task>-<hash of the attempt id>``: readable, unique, safe in any Slurm field."""
    digest = hashlib.sha256(attempt_id.encode()).hexdigest()[:10]
    return f"osmo-{_NAME_CHARS.sub('_', task)[:40]}-{digest}"


def sbatch_args(*, name: str, owner: str, folder: Path, resources: ResourceSpec,
                options: SlurmOptions, terms: Terms | None = None) -> list[str]:
    """Sbatch's options for one attempt (one ``--opt=value`` word each)."""
    return [*job_args(name=name, owner=owner, folder=folder),
            *resource_args(resources, options, terms)]


def job_args(*, name: str, owner: str, folder: Path, log: str | None = None) -> list[str]:
    """The job's own options: name, owner comment, folder, output files, environment.

    The batch script's stdout and stderr go to ``folder``'s ``out`` and ``err``, or both to
    ``log`` there.
    """
    out, err = (folder / log, folder / log) if log else (folder / "out", folder / "err")
    return [f"--job-name={name}", f"--comment={owner}", f"--chdir={folder}",
            f"--output={out}", f"--error={err}", "--open-mode=append", "--export=NONE"]


def gang_args(*, name: str, owner: str, folder: Path,
              components: Sequence[Sequence[str]]) -> list[str]:
    """A heterogeneous job's options: one component per member (``resource_args``).

    Slurm places all of them or none. The batch script's own output (srun's messages
    about every member) goes to ``folder``'s ``gang.log``; each member's agent writes its
    task's output to its own folder.
    """
    args = job_args(name=name, owner=owner, folder=folder, log="gang.log")
    for index, component in enumerate(components):
        args.extend([":"] if index else [])
        args.extend(component)
    return args


def resource_args(resources: ResourceSpec, options: SlurmOptions,
                  terms: Terms | None = None) -> list[str]:
    """What one task asks for: node, task, CPUs, memory, GPUs, disk, where, time, priority.

    ``terms``: the workflow's ``exec_timeout`` (``--time``) and priority (``--nice``, or its
    QOS where the pool configures one).
    """
    terms = terms or Terms()
    args = ["--nodes=1", "--ntasks=1", f"--cpus-per-task={max(1, int(resources.cpu or 1))}"]
    if resources.memory:
        args.append(f"--mem={_mebibytes(resources.memory)}M")
    if resources.gpu:
        args.append(f"--gres=gpu:{int(resources.gpu)}")
    if resources.storage:
        args.append(f"--tmp={_mebibytes(resources.storage)}M")
    partitions = options.partitions
    if resources.platform and resources.platform in partitions:
        partitions = (resources.platform,)  # a platform that names one of them picks it
    if partitions:
        args.append(f"--partition={','.join(partitions)}")
    qos = dict(options.priority_qos).get(terms.priority or "NORMAL", options.qos)
    for flag, value in (("--account", options.account), ("--qos", qos),
                        ("--constraint", options.constraint)):
        if value:
            args.append(f"{flag}={value}")
    if terms.exec_timeout is not None:
        args.append(f"--time={max(1, math.ceil(terms.exec_timeout / 60))}")
    nice = {"NORMAL": options.nice, "LOW": 2 * options.nice}.get(terms.priority or "", 0)
    if nice:
        args.append(f"--nice={nice}")
    args.extend(options.extra)
    return args


def batch_script(python: str, agent: Path, folder: Path) -> str:
    """The batch script: the agent, on the attempt's folder, and nothing else.

    Raises:
        PrepareError: a path holds a control character (a line break would start a line
            of its own, which sbatch might read as a directive).
    """
    _check_words(python, str(agent), str(folder))
    words = " ".join(shlex.quote(str(w)) for w in (python, "-I", agent, folder))
    return f"#!/bin/sh\nexec {words}\n"


def gang_script(python: str, agent: Path, folders: Sequence[Path]) -> str:
    """A gang's batch script: one ``srun`` starting every member's agent in its component.

    Raises:
        PrepareError: a path holds a control character.
    """
    _check_words(python, str(agent), *map(str, folders))
    steps = " : ".join(
        " ".join(shlex.quote(str(w)) for w in (f"--het-group={index}", python, "-I", agent,
                                               "--own-output", folder))
        for index, folder in enumerate(folders))
    return f"#!/bin/sh\nexec srun --kill-on-bad-exit=0 {steps}\n"


def pyxis_argv(srun: str, image: str, mounts: Sequence[Mount], workdir: str | None,
               argv: Sequence[str]) -> list[str]:
    """``srun`` running ``argv`` in ``image`` through pyxis, OSMO's layout bound in.

    One step of the job's own allocation (``--ntasks=1``); the binds are pyxis's
    ``--container-mounts`` list (``SRC:DST[:ro]``, comma-separated), the working folder
    ``--container-workdir``; the task's environment is srun's (the agent's), as pyxis
    passes it.

    Raises:
        PrepareError: a path that list cannot hold (a comma, a colon, a control character).
    """
    binds = []
    for mount in mounts:
        for path in (str(mount.source), mount.target):
            if any(c in path for c in ",:") or any(ord(c) < 32 for c in path):
                raise PrepareError(f"{path!r}: pyxis cannot bind a path holding ',' or ':'")
        binds.append(f"{mount.source}:{mount.target}" + (":ro" if mount.read_only else ""))
    args = [srun, "--ntasks=1", "--nodes=1", f"--container-image={image}",
            "--no-container-mount-home"]
    args += [f"--container-mounts={','.join(binds)}"] if binds else []
    args += [f"--container-workdir={workdir}"] if workdir else []
    return [*args, "--", *argv]


def _check_words(*words: str) -> None:
    for word in words:
        if any(ord(c) < 32 or c == "\x7f" for c in word):
            raise PrepareError(f"{word!r}: a path with a control character cannot go into "
                               "a Slurm batch script")


def _mebibytes(size: int) -> int:
    return max(1, math.ceil(size / (1 << 20)))


