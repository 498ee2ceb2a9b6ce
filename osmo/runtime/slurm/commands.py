"""The only module that runs Slurm's commands: sbatch, squeue, scancel, sinfo, scontrol, srun.

Every call is an argv (never a shell), run with the node's environment (``SLURM_CONF`` and
``PATH`` as the operator set them), with a time limit; a command that is missing, fails or
hangs raises :class:`SlurmError` (an ``InfrastructureError``: exit 3) naming the command
and what it printed. What the commands print is parsed here, in the fixed formats asked
for (``-o``/``--parsable``), never from the human tables.

It must not know about attempts, launches or the scheduler: it speaks in job ids, states
and nodes.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

from osmo.errors import InfrastructureError

__all__ = ["JobInfo", "Partition", "Slurm", "SlurmError", "gpus_of", "minutes_of"]

_TIMEOUT = 30.0
_SEP = "\x1f"  # a field separator no job name, reason or node list holds


class SlurmError(InfrastructureError):
    """A Slurm command is missing, failed or did not answer (the message says which)."""


@dataclass(frozen=True)
class JobInfo:
    """One job as ``squeue -t all`` shows it.

    Attributes:
        job_id: its id.
        state: ``PENDING``, ``RUNNING``, ``COMPLETED``, ``OUT_OF_MEMORY``... (Slurm's words).
        reason: why it waits or how it ended (``Resources``, ``Priority``, ``None``...).
        nodes: where it runs or ran (empty while it waits).
        name: its name.
        comment: its comment (the owner of a node's jobs: ``osmo.runtime.slurm.runtime``).
    """

    job_id: str
    state: str
    reason: str
    nodes: str
    name: str = ""
    comment: str = ""


@dataclass(frozen=True)
class Partition:
    """Partitions a node may use, as ``sinfo`` counts them.

    Only nodes that take jobs are counted (:func:`takes_jobs`): one that is down, drained
    or draining, failing or not responding adds nothing until Slurm may start jobs on it
    again.

    Attributes:
        name: the partitions (comma-separated).
        cpus: CPUs of its nodes, summed.
        memory: bytes of memory of its nodes, summed.
        gpus: GPUs of its nodes (their ``gpu`` GRES), summed.
        nodes: how many nodes.
        listed: how many nodes ``sinfo`` shows, those that take no job included.
    """

    name: str
    cpus: int
    memory: int
    gpus: int
    nodes: int
    listed: int = 0


class Slurm:
    """Slurm's commands, as one login host runs them.

    Args:
        env: the environment they run with (default: this process's).
        timeout: seconds each command may take.
    """

    def __init__(self, env: Mapping[str, str] | None = None, *,
                 timeout: float = _TIMEOUT) -> None:
        self.env = dict(os.environ if env is None else env)
        self.timeout = timeout

    def which(self, program: str) -> str | None:
        """The path of ``program`` on the environment's ``PATH`` (None: not there)."""
        return shutil.which(program, path=self.env.get("PATH"))

    def version(self) -> str:
        """``slurm 22.05.8``: what ``sbatch --version`` says. Raises SlurmError."""
        return self._run("sbatch", "--version").strip()

    def sbatch(self, script: str, args: Sequence[str], *, cwd: str) -> str:
        """Submit ``script`` (a file path) with ``args``; the new job's id. Raises SlurmError."""
        out = self._run("sbatch", "--parsable", *args, script, cwd=cwd)
        job_id = out.strip().split(";")[0]
        if not job_id.isdigit():
            raise SlurmError(f"sbatch printed {out.strip()!r}, not a job id")
        return job_id

    def jobs(self, job_ids: Iterable[str]) -> dict[str, JobInfo]:
        """The jobs among ``job_ids`` slurmctld still knows (ended ones too, for a while).

        A heterogeneous job's component is ``JOB+N`` (as squeue names it). A job slurmctld
        forgot is missing from the answer (squeue refuses such a list: the user's jobs are
        asked for instead).
        """
        wanted = set(job_ids)
        if not wanted:
            return {}
        bases = sorted({job_id.split("+")[0] for job_id in wanted})
        try:
            found = self._squeue("-j", ",".join(bases))
        except SlurmError as exc:
            if "Invalid job id" not in str(exc):
                raise
            found = self._squeue("--me")  # one of them was forgotten (MinJobAge)
        return {job.job_id: job for job in found if job.job_id in wanted}

    def owned(self, comment: str) -> list[JobInfo]:
        """The jobs (any state) whose comment is ``comment``."""
        return [job for job in self._squeue() if job.comment == comment]

    def cancel(self, job_id: str, *, signal: str | None = None) -> None:
        """``scancel``: the job goes (``signal``: only signal every process of it)."""
        args = [f"--signal={signal}", "--full"] if signal else []
        self._run("scancel", *args, job_id)

    def capacity(self, names: Sequence[str] = ()) -> Partition:
        """The partitions ``names`` together, each node counted once (one may be in several)."""
        rows = self._node_rows(names)
        return _summed(",".join(dict.fromkeys(part for part, _, _ in rows)),
                       {node: counts for _, node, counts in rows})

    def partitions(self, names: Sequence[str]) -> dict[str, Partition]:
        """Each of the partitions ``names`` that ``sinfo`` shows, counted on its own."""
        nodes: dict[str, dict[str, tuple[int, int, int] | None]] = {}
        for part, node, counts in self._node_rows(names):
            nodes.setdefault(part, {})[node] = counts
        return {part: _summed(part, found) for part, found in nodes.items()}

    def max_minutes(self, names: Sequence[str] = ()) -> int | None:
        """The longest ``MaxTime`` of the partitions ``names``, in minutes.

        ``names`` empty: the default partition's (every partition's when none is the
        default). None when one has no limit (``infinite``). Raises SlurmError.
        """
        args = ["-p", ",".join(names)] if names else []
        out = self._run("sinfo", "-h", *args, "-o", f"%P{_SEP}%l")
        rows = [line.split(_SEP) for line in out.splitlines() if _SEP in line]
        if not names and any(part.endswith("*") for part, *_ in rows):
            rows = [row for row in rows if row[0].endswith("*")]
        limits = [minutes_of(row[-1]) for row in rows]
        return None if not limits or None in limits else max(m for m in limits if m is not None)

    def node_address(self, node: str) -> str:
        """Where the login host reaches ``node`` (its ``NodeAddr``). Raises SlurmError."""
        out = self._run("scontrol", "show", "node", "--oneliner", node)
        for word in out.split():
            if word.startswith("NodeAddr="):
                return word.partition("=")[2]
        raise SlurmError(f"scontrol show node {node}: no NodeAddr")

    def srun_argv(self, *args: str) -> list[str]:
        """The argv of ``srun ARGS`` (an exec into a running job). Raises SlurmError."""
        path = self.which("srun")
        if path is None:
            raise SlurmError("srun not found on PATH: install Slurm's client commands")
        return [path, *args]

    def has_pyxis(self) -> bool:
        """Whether ``srun`` takes ``--container-image`` (the pyxis plugin is installed)."""
        try:
            return "--container-image" in self._run("srun", "--help")
        except SlurmError:
            return False

    # -------------------------------------------------------------- internals

    def _node_rows(self, names: Sequence[str]
                   ) -> list[tuple[str, str, tuple[int, int, int] | None]]:
        """``(partition, node, counts)`` of every node ``sinfo`` shows.

        ``names`` empty: Slurm's default partition's nodes (where a job that names no
        partition goes), or every node when no partition is the default.
        ``counts``: ``(cpus, memory bytes, gpus)``, None for a node that takes no jobs
        (:func:`takes_jobs`).
        """
        args = ["-p", ",".join(names)] if names else []
        out = self._run("sinfo", "-h", "-N", *args, "-o",
                        _SEP.join(("%P", "%N", "%c", "%m", "%G", "%T")))
        rows: list[tuple[str, str, tuple[int, int, int] | None]] = []
        defaults: set[str] = set()
        for line in out.splitlines():
            fields = line.split(_SEP)
            if len(fields) == 6:
                part, node, cpus, memory, gres, state = fields
                if part.endswith("*"):  # sinfo's mark of the default partition
                    part = part[:-1]
                    defaults.add(part)
                rows.append((part, node, (_int(cpus), _int(memory.rstrip("+")) << 20,
                                          gpus_of(gres)) if takes_jobs(state) else None))
        if not names and defaults:
            rows = [row for row in rows if row[0] in defaults]
        return rows

    def _squeue(self, *args: str) -> list[JobInfo]:
        fmt = _SEP.join(("%i", "%T", "%r", "%N", "%j", "%k"))
        out = self._run("squeue", "-h", "-t", "all", *args, "-o", fmt)
        found = []
        for line in out.splitlines():
            fields = line.split(_SEP)
            if len(fields) == 6:
                found.append(JobInfo(*fields))
        return found

    def _run(self, program: str, *args: str, cwd: str | None = None) -> str:
        path = self.which(program)
        if path is None:
            raise SlurmError(f"{program} not found on PATH: install Slurm's client commands "
                             "(Debian: slurm-client) on this login host")
        try:
            done = subprocess.run([path, *args], env=self.env, cwd=cwd, capture_output=True,
                                  text=True, timeout=self.timeout, stdin=subprocess.DEVNULL,
                                  check=False)
        except subprocess.TimeoutExpired:
            raise SlurmError(f"{program} did not answer in {self.timeout:g}s: is slurmctld "
                             "up?") from None
        except OSError as exc:
            raise SlurmError(f"cannot run {program}: {exc.strerror or exc}") from None
        if done.returncode != 0:
            said = (done.stderr or done.stdout).strip()
            raise SlurmError(f"{program} {' '.join(args[:1])} failed: {said}"
                             if said else f"{program} exited {done.returncode}")
        return done.stdout


def gpus_of(gres: str) -> int:
    """GPUs in a GRES text (``gpu:2``, ``gpu:a100:4(S:0-1),mps:100``); 0 without any."""
    total = 0
    for item in gres.split(","):
        parts = item.split("(")[0].split(":")
        if parts[0] == "gpu" and len(parts) > 1 and parts[-1].isdigit():
            total += int(parts[-1])
    return total


def minutes_of(limit: str) -> int | None:
    """Minutes in a time limit as ``sinfo`` shows it, seconds rounded up.

    ``1-02:03:04``, ``2:03:04``, ``3:04`` (minutes and seconds), ``5`` (minutes); None
    for ``infinite`` or what it cannot read.
    """
    days, _, clock = limit.strip().rpartition("-")
    parts = clock.split(":")
    if not all(p.isdigit() for p in parts) or not 1 <= len(parts) <= 3 or (
            days and not days.isdigit()):
        return None
    seconds = [0, 0, 0]  # h, m, s; one number alone is minutes
    if len(parts) == 1:
        seconds[1] = int(parts[0])
    else:
        seconds[3 - len(parts):] = map(int, parts)
    total = ((int(days or 0) * 24 + seconds[0]) * 60 + seconds[1]) * 60 + seconds[2]
    return -(-total // 60)


def takes_jobs(state: str) -> bool:
    """Whether Slurm may start jobs on a node in ``state`` (``sinfo``'s ``%T``).

    Idle, mixed, allocated, completing or planned, powered down or powering up included
    (Slurm resumes such a node for a job); not down, drained or draining, failing,
    reserved, in maintenance or rebooting, nor not responding (``*``). A compound state
    (``mixed+drain``) takes jobs only if none of its flags keeps them off.
    """
    if "*" in state:
        return False
    base, *flags = (part.rstrip(_SUFFIXES) for part in state.lower().split("+"))
    return base in _TAKING and not any(flag in _NO_JOBS for flag in flags)


_TAKING = frozenset({"idle", "mixed", "allocated", "completing", "planned"})
_NO_JOBS = frozenset({"down", "drain", "drained", "draining", "fail", "failing", "inval",
                      "maint", "not_responding", "powering_down", "reboot_issued",
                      "reboot_requested", "reserved", "unknown"})
"""Flags of a compound state (``mixed+drain``) that keep new jobs off the node."""
_SUFFIXES = "~#!%$@^-"  # power saving, rebooting, reserved...: sinfo's marks after a state


def _summed(name: str, nodes: dict[str, tuple[int, int, int] | None]) -> Partition:
    counts = [c for c in nodes.values() if c is not None]
    return Partition(name, sum(c for c, _, _ in counts), sum(m for _, m, _ in counts),
                     sum(g for _, _, g in counts), len(counts), len(nodes))


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        return 0
