"""The Slurm runtime: each attempt is one batch job, submitted from the login host.

A node started with ``--runtime slurm`` (``osmo.runtime.choose``) runs every attempt so.
What it owns, one concern per method of the runtime contract:

- what the task sees: the host's own paths (``HOST_PATHS``): the attempt's folder is on a
  filesystem the login host and the compute nodes share (an HPC home or scratch), so the
  pool's inputs, files and output folder are where the job finds them. Credentials are kept
  out of the argv and environment (``Paths.hidden_secrets``).
- the launch (:meth:`SlurmRuntime.prepare`): the attempt's job folder (``<attempt>/slurm``,
  0700) with ``launch.json`` for the agent, the fixed batch script ``job.sh`` and sbatch's
  options (``osmo.runtime.slurm.script``: resources → ``--cpus-per-task``, ``--mem``,
  ``--gres=gpu:N``, ``--tmp``; the pool's partitions, account, QOS; name and owner comment).
- start: credentials to ``secret.json`` (0600), ``sbatch``, then the attempt's watcher
  (``osmo.runtime.slurm.watch``, the local process the pool watches: the job's output as
  it comes, its exit code at the end).
- status: one poller thread per node asks ``squeue`` about every live job of the node at
  once, a few times a second, and reads the state through the one table
  (``osmo.runtime.slurm.states``): a PENDING reason and the node a job runs on go to the
  attempt's log; an end the agent could not report (killed, OUT_OF_MEMORY, TIMEOUT) is
  written for the watcher (``ended.json``) with its code and reason; a lost job
  (NODE_FAIL, PREEMPTED, BOOT_FAIL) is submitted again as the same attempt, not counted
  against its retries. A job Slurm requeues by itself (a failed node, by default) is the
  same job: the agent empties the lost run's output when it runs again.
- kill: ``scancel --signal=TERM --full`` (the agent passes it on to the task); the forced
  kill: ``scancel --signal=KILL --full`` then ``scancel``; in the background.
- exec: ``srun --jobid=ID --overlap`` of the command in the attempt's working folder, with
  the task's environment (its credentials excepted).
- port-forward: to the task's port on the address of the node its job runs on.
- clean-up: the job is cancelled if it still runs, the secret file goes.

Orphans: :meth:`SlurmRuntime.cancel_orphans` cancels every job carrying the node's owner
comment; a node's runtime is made with it (``osmo.runtime.choose``), before anything new
runs: no job outlives the node that submitted it (a restarted node's attempts are
rescheduled by the server).
"""

from __future__ import annotations

import json
import logging
import os
import sys
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from osmo.runtime.api import (
    HOST_PATHS,
    Attempt,
    ConnectError,
    Connector,
    ExecCommand,
    Launch,
    Paths,
    PrepareError,
    ProcessHandle,
    Runtime,
    StartError,
    dial,
)
from osmo.runtime.process.groups import ProcessGroups
from osmo.runtime.slurm.commands import JobInfo, Slurm, SlurmError
from osmo.runtime.slurm.script import JobOptions, batch_script, job_name, sbatch_args
from osmo.runtime.slurm.states import Phase, verdict
from osmo.scheduler.types import PrepareAttempt

__all__ = ["SlurmJob", "SlurmRuntime"]

_log = logging.getLogger(__name__)

_HERE = Path(__file__).parent
AGENT, WATCHER = _HERE / "agent.py", _HERE / "watch.py"
_PATHS = replace(HOST_PATHS, hidden_secrets=True)


@dataclass(frozen=True)
class SlurmJob:
    """An attempt's batch job, as prepared (``Launch.run`` of the Slurm runtime).

    Attributes:
        folder: its job folder (``launch.json``, ``job.sh``, the job's output files).
        name: its Slurm job name.
        args: sbatch's options.
    """

    folder: Path
    name: str
    args: tuple[str, ...]

    @property
    def script(self) -> Path:
        """The batch script."""
        return self.folder / "job.sh"


@dataclass(eq=False)
class _Live:
    job: SlurmJob
    job_id: str
    handle: ProcessHandle | None = None
    killed: bool = False
    ended: bool = False
    state: str = ""
    reason: str = ""
    nodes: str = ""
    lost: int = 0
    said: set[str] = field(default_factory=set)


class SlurmRuntime:
    """Attempts as Slurm batch jobs (see the module docstring).

    Args:
        slurm: Slurm's commands on this login host.
        owner: the comment every job of this node carries (``owner_id`` of its home).
        options: partitions, account, QOS... for every job.
        python: the Python the jobs run their agent with, on the compute nodes.
        poll: seconds between two looks at the node's live jobs.
    """

    def __init__(self, slurm: Slurm, *, owner: str, options: JobOptions | None = None,
                 python: str = sys.executable, poll: float = 0.25) -> None:
        self.slurm, self.owner = slurm, owner
        self.options = options or JobOptions()
        self.options.check()
        self._python, self._poll = python, poll
        self._processes = ProcessGroups()
        self._jobs: dict[Path, _Live] = {}  # by job folder
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._closing = threading.Event()
        self._poller: threading.Thread | None = None
        self._threads: set[threading.Thread] = set()
        self._version: str | None = None

    def describe(self) -> str:
        """``slurm (slurm 22.05.8)``."""
        if self._version is None:
            try:
                self._version = self.slurm.version()
            except SlurmError:
                self._version = "version unknown"
        return f"slurm ({self._version})"

    def cancel_orphans(self) -> list[str]:
        """Cancel every job of this owner still queued or running (a previous life's)."""
        cancelled = []
        for job in self.slurm.owned(self.owner):
            if verdict(job.state).phase in (Phase.WAITING, Phase.RUNNING):
                self._quietly(self.slurm.cancel, job.job_id)
                cancelled.append(job.job_id)
        return cancelled

    def paths(self, cmd: PrepareAttempt) -> Paths:
        """The host's own paths (a shared filesystem), credentials kept apart."""
        return _PATHS

    def prepare(self, launch: Launch, attempt: Attempt, *,
                progress: Callable[[str], None]) -> Launch:
        """The launch with its job folder, batch script and sbatch options.

        Raises:
            PrepareError: the task names an image (no container runtime on the compute
                nodes yet), or its job folder cannot be written.
        """
        task, dirs = attempt.task, attempt.dirs
        if task.image is not None and task.type is None:
            raise PrepareError(
                f"task {task.name!r} names image '{task.image}', and this Slurm pool cannot "
                "run images: it needs pyxis (srun --container-image) or podman on its compute "
                "nodes; the task is not run as a bare process instead")
        folder = dirs.root / "slurm"
        name = job_name(task.name, attempt.cmd.attempt_id)
        try:
            folder.mkdir(mode=0o700, exist_ok=True)
            _write_private(folder / "launch.json", json.dumps({
                "argv": list(launch.argv), "cwd": str(launch.cwd), "env": launch.env,
                "output": str(dirs.output_partial)}))
            job = SlurmJob(folder, name, tuple(sbatch_args(
                name=name, owner=self.owner, folder=folder, resources=attempt.resources,
                options=self.options)))
            _write_private(job.script, batch_script(self._python, AGENT, folder))
        except OSError as exc:
            raise PrepareError(f"cannot write the job folder {folder}: "
                               f"{exc.strerror or exc}") from exc
        note = f"runs as a Slurm batch job ({self.describe()}): {name}"
        return replace(launch, run=job, notes=(*launch.notes, note))

    def start(self, launch: Launch) -> ProcessHandle:
        """Submit the job and start its watcher.

        Raises:
            StartError: sbatch refused the job (its message: no node can ever fit it, an
                unknown partition...) or the watcher cannot start.
        """
        job = _job(launch)
        secret = job.folder / "secret.json"
        try:
            if launch.secret_env:
                _write_private(secret, json.dumps(launch.secret_env))
            job_id = self.slurm.sbatch(str(job.script), job.args, cwd=str(job.folder))
        except (OSError, SlurmError) as exc:
            _unlink(secret)
            raise StartError(f"Slurm did not take the job: {exc}") from exc
        live = _Live(job, job_id)
        self._note(live, f"Slurm job {job_id} submitted")
        try:
            handle = self._processes.start(
                [self._python, "-I", str(WATCHER), str(job.folder)], cwd=launch.cwd,
                env={"PATH": os.environ.get("PATH", "/usr/bin:/bin")})
        except StartError:
            self._quietly(self.slurm.cancel, job_id)
            _unlink(secret)
            raise
        live.handle = handle
        with self._lock:
            self._jobs[job.folder] = live
            if self._poller is None:
                self._poller = threading.Thread(target=self._watch, name="osmo-slurm-poll",
                                                daemon=True)
                self._poller.start()
        self._wake.set()
        return handle

    def kill(self, handle: ProcessHandle, *, force: bool = False) -> None:
        """``scancel`` with SIGTERM (SIGKILL, then the job cancelled, when ``force``)."""
        live = self._live(handle)
        if live is None:
            self._processes.kill(handle, force=force)
            return
        live.killed = True
        self._later(self._cancel, live, force)

    def reap(self, handle: ProcessHandle) -> int:
        """The job's exit code, once its watcher ended (a job still running is cancelled)."""
        live = self._live(handle)
        if live is not None and handle.popen.poll() is None:
            live.killed = True
            self._quietly(self.slurm.cancel, live.job_id)  # the pool closes under it
        return self._processes.reap(handle)

    def release(self, handle: ProcessHandle) -> None:
        """Close the watcher's descriptors; the secret file goes."""
        self._processes.release(handle)
        live = self._live(handle)
        if live is not None:
            _unlink(live.job.folder / "secret.json")

    def exec(self, launch: Launch, command: Sequence[str], *, tty: bool,
             term: str | None) -> ExecCommand:
        """``srun --jobid=ID --overlap`` of ``command`` beside the task, in its folder.

        Raises:
            SlurmError: srun is missing.
        """
        live = self._jobs.get(_job(launch).folder)
        job_id = live.job_id if live is not None else "0"
        argv = self.slurm.srun_argv(f"--jobid={job_id}", "--overlap", "--nodes=1",
                                    "--ntasks=1", "--quiet", f"--chdir={launch.cwd}",
                                    "--export=ALL", *(["--pty"] if tty else []), *command)
        env = {**launch.env, **{k: v for k, v in self.slurm.env.items()
                                if k.startswith("SLURM_CONF")}}
        if tty and term is not None:
            env["TERM"] = term
        return ExecCommand(argv, launch.cwd, env)

    def connector(self, launch: Launch, handle: ProcessHandle) -> Connector:
        """To the task's ports on the address of its job's node.

        Raises:
            ConnectError: the job runs on no node yet.
            SlurmError: scontrol cannot say where that node is.
        """
        live = self._jobs.get(_job(launch).folder)
        if live is None or not live.nodes:
            raise ConnectError("the task's Slurm job is not running on a node yet")
        address = self.slurm.node_address(live.nodes.split(",")[0])
        return lambda port, udp: dial(address, port, udp=udp)

    def cleanup(self, launch: Launch) -> None:
        """Its job is cancelled if it still runs; the secret file goes."""
        job = launch.run
        if not isinstance(job, SlurmJob):
            return
        _unlink(job.folder / "secret.json")
        with self._lock:
            live = self._jobs.pop(job.folder, None)
        if live is not None and not live.ended:
            self._later(self._quietly, self.slurm.cancel, live.job_id)

    def close(self) -> None:
        """Stop the poller; cancel the jobs still running; wait for Slurm calls under way."""
        self._closing.set()
        self._wake.set()
        if self._poller is not None:
            self._poller.join()
        with self._lock:
            left = [live for live in self._jobs.values() if not live.ended]
        for live in left:
            self._quietly(self.slurm.cancel, live.job_id)
        while True:
            with self._lock:
                threads = list(self._threads)
            if not threads:
                return
            for thread in threads:
                thread.join()

    # -------------------------------------------------------------- the poller

    def _watch(self) -> None:
        while not self._closing.is_set():
            self._wake.wait(self._poll)
            self._wake.clear()
            with self._lock:
                live = [job for job in self._jobs.values() if not job.ended]
            if not live:
                continue
            try:
                known = self.slurm.jobs(job.job_id for job in live)
            except SlurmError as exc:
                _log.warning("cannot read the Slurm jobs' states: %s", exc)
                continue
            for job in live:
                try:
                    self._update(job, known.get(job.job_id))
                except (OSError, SlurmError) as exc:
                    _log.warning("Slurm job %s: %s", job.job_id, exc)

    def _update(self, live: _Live, info: JobInfo | None) -> None:
        if info is None:  # slurmctld forgot it (MinJobAge): the agent's word, or none
            seen = verdict("", listed=False)
        else:
            seen = verdict(info.state)
            live.state, live.nodes = info.state, info.nodes or live.nodes
        if seen.phase is Phase.WAITING and info is not None:
            self._say(live, f"Slurm job {live.job_id} {info.state} ({info.reason})")
        elif seen.phase is Phase.RUNNING and info is not None and info.nodes:
            self._say(live, f"Slurm job {live.job_id} RUNNING on {info.nodes}")
        elif seen.phase is Phase.LOST:
            self._resubmit(live, seen.reason or "lost")
        elif seen.phase is Phase.ENDED:
            killed = live.killed and not seen.override
            ended = {"state": live.state, "code": 137 if killed else seen.code,
                     "override": seen.override,
                     "reason": None if killed else seen.reason}
            _write_private(live.job.folder / "ended.json", json.dumps(ended))
            live.ended = True

    def _resubmit(self, live: _Live, reason: str) -> None:
        live.lost += 1
        old = live.job_id
        live.job_id = self.slurm.sbatch(str(live.job.script), live.job.args,
                                        cwd=str(live.job.folder))
        live.said.clear()
        self._note(live, f"job {old}: {reason}; submitted again as job {live.job_id}")

    def _say(self, live: _Live, line: str) -> None:
        if line not in live.said:
            live.said.add(line)
            self._note(live, line)

    @staticmethod
    def _note(live: _Live, line: str) -> None:
        with (live.job.folder / "notes").open("a") as f:
            f.write(f"osmo: {line}\n")

    # -------------------------------------------------------------- internals

    def _live(self, handle: ProcessHandle) -> _Live | None:
        with self._lock:
            return next((j for j in self._jobs.values() if j.handle is handle), None)

    def _cancel(self, live: _Live, force: bool) -> None:
        try:
            if force:
                self._quietly(self.slurm.cancel, live.job_id, signal="KILL")
                self.slurm.cancel(live.job_id)
            else:
                self.slurm.cancel(live.job_id, signal="TERM")
        except SlurmError:
            self._quietly(self.slurm.cancel, live.job_id)  # pending: it cannot be signalled
        self._wake.set()

    def _later(self, fn: Callable[..., object], *args: object) -> None:
        """Call ``fn(*args)`` on a thread of its own (a Slurm call); ``close`` waits for it."""
        def run() -> None:
            try:
                fn(*args)
            finally:
                with self._lock:
                    self._threads.discard(thread)

        thread = threading.Thread(target=run, name="osmo-slurm-call", daemon=True)
        with self._lock:
            self._threads.add(thread)
        thread.start()

    @staticmethod
    def _quietly(fn: Callable[..., object], *args: object, **kwargs: object) -> None:
        try:
            fn(*args, **kwargs)
        except SlurmError as exc:
            _log.debug("Slurm call failed (clean-up goes on): %s", exc)


def _job(launch: Launch) -> SlurmJob:
    job = launch.run
    if not isinstance(job, SlurmJob):
        raise TypeError(f"{launch!r} was not prepared by the Slurm runtime")
    return job


def _write_private(path: Path, text: str) -> None:
    """Write ``text`` to a 0600 file at ``path``, never through a symlink."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW | os.O_CLOEXEC
    fd = os.open(path, flags, 0o600)
    try:
        os.fchmod(fd, 0o600)
        os.write(fd, text.encode())
    finally:
        os.close(fd)


def _unlink(path: Path) -> None:
    try:
        path.unlink()
    except FileNotFoundError:
        pass


def _conforms(runtime: SlurmRuntime) -> Runtime:
    """Never called: mypy checks here that SlurmRuntime keeps the runtime contract."""
    return runtime
