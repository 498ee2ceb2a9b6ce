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
  ``--gres=gpu:N``, ``--tmp``; the pool's partitions, account, QOS; the workflow's
  ``exec_timeout`` → ``--time`` and priority → ``--nice`` or QOS (``Attempt.terms``); name
  and owner comment).
- start: credentials to ``secret.json`` (0600), ``sbatch``, then the attempt's watcher
  (``osmo.runtime.slurm.watch``, the local process the pool watches: the job's output as
  it comes, its exit code at the end).
- groups are gangs: a group's members (``PrepareAttempt.hosts``) go to Slurm as one
  heterogeneous job, one component each, submitted when the last member starts (the
  group barrier), so Slurm places all of them or none (PENDING with its reason until it
  can). One ``srun`` starts every member's agent in its component (its own messages
  go to the first member's job folder, ``gang.log``). ``{{host:NAME}}`` is a
  placeholder the agent replaces with the address of NAME's node; containers use their
  node's network; a peer starts once its lead's task (container) runs. A lost gang
  (NODE_FAIL...) ends every member as lost (``ProcessHandle.lost``): each runs again as a
  new attempt that uses none of the workflow's retries, and the members' new attempts
  (the same retry) form the group's job again.
- status: one poller thread per node asks ``squeue`` about every live job of the node at
  once, a few times a second, and reads the state through the one table
  (``osmo.runtime.slurm.states``): a PENDING reason goes to the server once per new
  reason (``Attempt.waiting``: ``osmo query`` and ``osmo events`` show it; cleared when the
  job runs) and to the attempt's log, the node a job runs on to the log as a progress
  line (``osmo query`` shows the latest); an end the agent
  could not report (killed, OUT_OF_MEMORY, TIMEOUT) is written for the watcher
  (``ended.json``) with its code, and its reason logged; a lost job
  (NODE_FAIL, PREEMPTED, BOOT_FAIL) is submitted again as the same attempt, not counted
  against its retries. A job Slurm requeues by itself (a failed node, by default) is the
  same job: the agent empties the lost run's output when it runs again.
- kill: ``scancel --signal=TERM --full`` (the agent passes it on to the task); the forced
  kill: ``scancel --signal=KILL --full`` then ``scancel``; in the background.
- exec: ``srun --jobid=ID --overlap`` of the command in the attempt's working folder, with
  the task's environment (its credentials excepted).
- port-forward: to the task's port on the address of the node its job runs on.
- clean-up: the job is cancelled if it still runs, the secret file goes.

Images: a runtime made with ``containers`` (the node's container engine, found on the login
host and expected on the compute nodes: rootless podman) runs tasks in their image: the
container runtime prepares the run (image id, OSMO's data layout, binds, user, labels,
secret file) and the job's agent runs the engine's ``run`` argv
(``osmo.runtime.container.run.run_argv``) on the compute node. The image is resolved on the
login host: its storage must be the compute nodes' (a shared one), or the run fails at
once with podman's message. Without an engine an image task fails at start, saying what is
missing; it never runs as a bare process. Where the cluster has pyxis and the login host no
engine, a runtime made with ``pyxis`` runs them through ``srun --container-image``
(``osmo.runtime.slurm.script.pyxis_argv``: OSMO's data layout as ``--container-mounts``).

Adoption: a job outlives the node that submitted it (``osmo.runtime.api.Adopting``). Each
job's id, name and options are kept in its job folder (``job.json``, rewritten when it is
submitted again); a restarted node re-attaches to a journaled attempt's job
(:meth:`SlurmRuntime.adopt`: a new watcher resumes its output after what was shipped, the
poller watches it again), then :meth:`SlurmRuntime.cancel_orphans` cancels every other job
carrying the node's owner comment, and a whole group's job when one of its members was not
adopted (a gang comes back whole or not at all). A job whose task runs in a container is
not adopted yet (its attempt is lost and rescheduled, its job cancelled). No job outlives
its workflow: what the server no longer places on the node is killed when it registers.
"""

from __future__ import annotations

import json
import logging
import os
import re
import socket
import stat
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from osmo.config import read_json_private
from osmo.errors import OsmoError
from osmo.layout import AttemptDirs
from osmo.options import SlurmOptions
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
    Terms,
    dial,
)
from osmo.runtime.background import Background
from osmo.runtime.container.layout import DATA_LAYOUT, mounts
from osmo.runtime.container.run import ContainerError, ContainerRun, run_argv, secret_env_text
from osmo.runtime.container.runtime import ContainerRuntime
from osmo.runtime.process.groups import ProcessGroups
from osmo.runtime.slurm.agent import PLACEHOLDER
from osmo.runtime.slurm.commands import JobInfo, Partition, Slurm, SlurmError
from osmo.runtime.slurm.script import (
    batch_script,
    gang_args,
    gang_script,
    job_name,
    pyxis_argv,
    resource_args,
    sbatch_args,
)
from osmo.runtime.slurm.states import Phase, verdict, waiting_reason
from osmo.scheduler.types import PrepareAttempt
from osmo.status import ExitCode
from osmo.tasktypes.api import PROGRESS_PREFIX

__all__ = ["Gang", "SlurmJob", "SlurmRuntime"]

_JOB_ID = re.compile(r"[0-9]{1,20}(\+[0-9]{1,6})?")

_log = logging.getLogger(__name__)

_HERE = Path(__file__).parent
AGENT, WATCHER = _HERE / "agent.py", _HERE / "watch.py"
_PATHS = replace(HOST_PATHS, hidden_secrets=True)
LIMIT_TTL = 10.0  # s the partitions' time limit is known for
LOST = 3
"""The exit code of a gang member whose job was lost (with ``ProcessHandle.lost``)."""


@dataclass(frozen=True)
class SlurmJob:
    """An attempt's batch job, as prepared (``Launch.run`` of the Slurm runtime).

    Attributes:
        folder: its job folder (``launch.json``, ``job.sh``, the job's output files).
        name: its Slurm job name.
        args: sbatch's options.
        container: the container its task runs in, on the compute node (None: none).
        resources: the options of what it asks for (a gang's component).
        gang: a group member's gang: its key, its members in component order, its index
            among them (None: a job of its own).
    """

    folder: Path
    name: str
    args: tuple[str, ...]
    container: ContainerRun | None = None
    resources: tuple[str, ...] = ()
    gang: Gang | None = None
    waiting: Callable[[str], None] = field(default=lambda _reason: None, repr=False,
                                           compare=False)

    @property
    def script(self) -> Path:
        """The batch script."""
        return self.folder / "job.sh"


@dataclass(frozen=True)
class Gang:
    """A group member's place in its gang (one heterogeneous job for the whole group).

    Attributes:
        key: the group's attempt (workflow, retry, members).
        members: the members' task names, in component order.
        index: this member's component.
        lead: this member is the group's lead (its peers start once it runs).
    """

    key: str
    members: tuple[str, ...]
    index: int
    lead: bool


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
    lost_as: str = ""  # a gang's job was lost: why (its attempt is lost, not failed)
    said: set[str] = field(default_factory=set)
    notes: int = -1  # write end of the handle's notes pipe


class SlurmRuntime:
    """Attempts as Slurm batch jobs (see the module docstring).

    Args:
        slurm: Slurm's commands on this login host.
        owner: the comment every job of this node carries (``owner_id`` of its home).
        options: partitions, account, QOS... for every job.
        python: the Python the jobs run their agent with, on the compute nodes.
        poll: seconds between two looks at the node's live jobs.
        containers: runs the tasks in their images, through this engine on the compute
            nodes (the container runtime prepares each run: image, binds, user, labels); its
            paths are then OSMO's data layout. None: image tasks are refused.
        pyxis: runs the tasks in their images through ``srun --container-image`` (the
            cluster's pyxis plugin; ``containers`` is then None); OSMO's data layout.
    """

    def __init__(self, slurm: Slurm, *, owner: str, options: SlurmOptions | None = None,
                 python: str = sys.executable, poll: float = 0.25,
                 containers: ContainerRuntime | None = None, pyxis: bool = False) -> None:
        self.slurm, self.owner = slurm, owner
        self._containers, self._pyxis = containers, pyxis
        self.options = options or SlurmOptions()
        self.options.check()
        self._python, self._poll = python, poll
        self._processes = ProcessGroups()
        self._jobs: dict[Path, _Live] = {}  # by job folder
        self._gangs: dict[str, dict[int, _Live]] = {}  # members started, until submitted
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._closing = threading.Event()
        self._poller: threading.Thread | None = None
        self._calls = Background("osmo-slurm-call")  # Slurm calls off the reactor
        self._version: str | None = None
        self._max_minutes: int | None = None
        self._max_minutes_until = 0.0

    def describe(self) -> str:
        """``slurm (slurm 22.05.8)``; ``slurm (slurm 22.05.8, podman 4.3.1)`` with images."""
        if self._version is None:
            try:
                self._version = self.slurm.version()
            except SlurmError:
                self._version = "version unknown"
        if self._pyxis:
            return f"slurm ({self._version}, pyxis)"
        if self._containers is None:
            return f"slurm ({self._version})"
        engine = self._containers.engine.engine
        return f"slurm ({self._version}, {engine.name} {engine.version})"

    def capacity(self) -> Partition:
        """What its pool may use: its partitions' nodes that take jobs.

        A pool that names none: Slurm's default partition's (where its jobs go). None while
        each of them is down or drained.

        Raises:
            SlurmError: sinfo fails, or knows none of the partitions.
        """
        found = self.slurm.capacity(self.options.partitions)
        if not found.listed:
            raise SlurmError(f"sinfo shows no partition {','.join(self.options.partitions)}"
                             if self.options.partitions else "sinfo shows no partition")
        return found

    def platforms(self) -> dict[str, Partition]:
        """Each partition the pool names, a platform of its own with its nodes' capacity.

        A task with ``platform: P`` goes to partition P (``script.resource_args``); a pool
        that names no partition (Slurm's default one) has no platforms. Raises SlurmError.
        """
        if not self.options.partitions:
            return {}
        return self.slurm.partitions(self.options.partitions)

    def cancel_orphans(self, keep: Sequence[str] = ()) -> list[str]:
        """Cancel every job of this owner still queued or running but those in ``keep``.

        A group's job with a member not kept is cancelled whole (its members end with it).
        """
        live = [job for job in self.slurm.owned(self.owner)
                if verdict(job.state).phase in (Phase.WAITING, Phase.RUNNING)]
        whole = {job.job_id.split("+")[0] for job in live if job.job_id not in keep}
        cancelled = []
        for base in sorted(whole):
            self._quietly(self.slurm.cancel, base)
            cancelled.append(base)
        self._wake.set()
        return cancelled

    def adopted(self) -> set[str]:
        """The jobs it watches (adopted ones among them)."""
        with self._lock:
            return {live.job_id for live in self._jobs.values() if live.job_id}

    def adopt(self, dirs: AttemptDirs, shipped: Mapping[str, int]
              ) -> tuple[Launch, ProcessHandle]:
        """Re-attach to the job a previous life of the node submitted for ``dirs``.

        Its folder's ``job.json`` names the job; a new watcher resumes its output files after
        ``shipped`` bytes; the poller watches it again.

        Raises:
            OsmoError: no job was submitted there, its record is not valid, Slurm no longer
                knows it (and its agent left no exit), or its task runs in a container.
        """
        folder = dirs.root / "slurm"
        try:
            if not stat.S_ISDIR(os.lstat(folder).st_mode):
                raise OsmoError(f"{folder} is not a folder")
            meta = read_json_private(folder / "job.json")
            env = read_json_private(folder / "launch.json").get("env")
        except (OSError, ValueError) as exc:
            raise OsmoError(f"no Slurm job to adopt in {folder}: {exc}") from exc
        job = _job_of(folder, meta)
        job_id = str(meta["job_id"])
        if not isinstance(env, dict) or not all(isinstance(k, str) and isinstance(v, str)
                                                for k, v in env.items()):
            raise OsmoError(f"the launch in {folder} is not valid")
        info = self.slurm.jobs([job_id]).get(job_id)
        if info is None and not (folder / "exit.json").exists():
            raise OsmoError(f"Slurm job {job_id} is gone")
        offsets = [str(max(0, int(shipped.get(s, 0)))) for s in ("stdout", "stderr")]
        handle = self._processes.start(
            [self._python, "-I", str(WATCHER), str(folder), *offsets], cwd=dirs.work,
            env={"PATH": os.environ.get("PATH", "/usr/bin:/bin")})
        live = _Live(job, job_id, handle=handle)
        if info is not None and info.nodes:  # said by its previous life: not said again
            live.said.add(f"{PROGRESS_PREFIX} Slurm job {job_id} RUNNING on {info.nodes}")
        handle.notes_fd, live.notes = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        self._track(live)
        self._note(live, f"Slurm job {job_id} adopted: watched again")
        launch = Launch((), dirs.work, dict(env), run=job)
        return launch, handle

    def paths(self, cmd: PrepareAttempt) -> Paths:
        """The host's paths (shared), credentials apart; in a container, OSMO's layout.

        A group member's ``{{host:NAME}}`` is a placeholder the job's agent replaces with
        the address of the node Slurm gives NAME (``osmo.runtime.slurm.agent``).
        """
        hosts = _placeholders(cmd)
        if self._pyxis:
            return DATA_LAYOUT if not hosts else replace(DATA_LAYOUT, hosts=hosts)
        if self._containers is not None:
            seen = self._containers.paths(replace(cmd, hosts=hosts))
            return seen if not hosts else replace(seen, hosts=hosts)
        return _PATHS if not hosts else replace(_PATHS, hosts=hosts)

    def prepare(self, launch: Launch, attempt: Attempt, *,
                progress: Callable[[str], None]) -> Launch:
        """The launch with its job folder, batch script and sbatch options.

        Raises:
            PrepareError: the task names an image (no container runtime on the compute
                nodes yet), or its job folder cannot be written.
        """
        task, dirs, cmd = attempt.task, attempt.dirs, attempt.cmd
        argv, env, container = list(launch.argv), dict(launch.env), None
        if self._pyxis:
            assert task.image is not None, "the chooser gives this runtime image tasks only"
            binds, workdir = mounts(dirs, launch.files, launch.inputs)
            argv = pyxis_argv(self.slurm.srun_argv()[0], task.image, binds, workdir,
                              launch.argv)
        elif self._containers is None and task.image is not None and task.type is None:
            # the chooser gives image tasks to this runtime when the node has no engine
            raise PrepareError(
                f"task {task.name!r} names image '{task.image}', and this Slurm pool cannot "
                "run images: it needs pyxis (srun --container-image) or podman on its compute "
                "nodes; the task is not run as a bare process instead")
        if self._containers is not None:
            # a group's containers use their nodes' networks (``_placeholders``)
            spread = replace(attempt, cmd=replace(attempt.cmd, hosts=_placeholders(cmd)))
            launch = replace(self._containers.prepare(launch, spread, progress=progress),
                             waits=False)
            container = replace(_container(launch), argv=launch.argv, env=dict(launch.env))
            try:
                argv = run_argv(self._containers.engine.engine, container)
            except ContainerError as exc:
                raise PrepareError(str(exc)) from exc
            # its own cgroup namespace: it is made inside the job's cgroup, whose path the
            # compute node may show otherwise than the host does (a node in a container)
            argv.insert(2, "--cgroupns=private")
            env = self._containers.engine.env
        folder = dirs.root / "slurm"
        name = job_name(task.name, cmd.attempt_id)
        gang = None
        if len(cmd.hosts) > 1:
            members = tuple(cmd.hosts)
            gang = Gang(f"{cmd.workflow_id}\0{cmd.retry}\0{chr(0).join(members)}", members,
                        members.index(task.name), task.lead)
        try:
            folder.mkdir(mode=0o700, exist_ok=True)
            _write_private(folder / "launch.json", json.dumps({
                "argv": argv, "cwd": str(launch.cwd), "env": env,
                "output": str(dirs.output_partial), "files": str(dirs.files)}))
            terms = self._within_partitions(attempt.terms, launch)
            job = SlurmJob(folder, name, tuple(sbatch_args(
                name=name, owner=self.owner, folder=folder, resources=attempt.resources,
                options=self.options, terms=terms)), container,
                tuple(resource_args(attempt.resources, self.options, terms)), gang,
                attempt.waiting)
            _write_private(job.script, batch_script(self._python, AGENT, folder))
        except OSError as exc:
            raise PrepareError(f"cannot write the job folder {folder}: "
                               f"{exc.strerror or exc}") from exc
        note = f"runs as a Slurm batch job ({self.describe()}): {name}"
        notes = (*launch.notes, *self._capped_note(attempt.terms, terms), note)
        return replace(launch, run=job, notes=notes)

    def _within_partitions(self, terms: Terms, launch: Launch) -> Terms:
        """``terms`` with its time no longer than the partitions allow.

        A job asking for more than its partition's ``MaxTime`` would stay PENDING
        (PartitionTimeLimit) for ever: it asks for that limit instead, and Slurm ends it
        there (FAILED_EXEC_TIMEOUT). A limit is known for ``LIMIT_TTL`` seconds; one that
        would shorten the job is read again first.
        """
        if terms.exec_timeout is None:
            return terms
        now = time.monotonic()
        with self._lock:
            known = self._max_minutes if now < self._max_minutes_until else False
        if known is False or (known is not None and terms.exec_timeout > known * 60):
            try:
                known = self.slurm.max_minutes(self.options.partitions)
            except SlurmError as exc:
                _log.warning("cannot read the partitions' time limits: %s", exc)
                known = None
            with self._lock:
                self._max_minutes, self._max_minutes_until = known, now + LIMIT_TTL
        if known is None or terms.exec_timeout <= known * 60:
            return terms
        return replace(terms, exec_timeout=float(known * 60))

    @staticmethod
    def _capped_note(asked: Terms, given: Terms) -> tuple[str, ...]:
        if asked.exec_timeout == given.exec_timeout or given.exec_timeout is None:
            return ()
        return (f"exec_timeout {asked.exec_timeout:g}s is over the partitions' time limit: "
                f"the job asks for {given.exec_timeout / 60:g} min (--time), Slurm ends it "
                "there",)

    def start(self, launch: Launch) -> ProcessHandle:
        """Submit the job (a gang's, once its last member starts) and start its watcher.

        Raises:
            StartError: sbatch refused the job (its message: no node can ever fit it, an
                unknown partition...) or the watcher cannot start.
        """
        job = _job(launch)
        secret = job.folder / "secret.json"
        box = job.container
        try:
            if box is not None and box.secret_env and box.secret_env_file is not None:
                secret = box.secret_env_file  # the container sources it
                _write_private(secret, secret_env_text(box.secret_env))
            elif launch.secret_env:
                _write_private(secret, json.dumps(launch.secret_env))
            job_id = "" if job.gang else self.slurm.sbatch(str(job.script), job.args,
                                                           cwd=str(job.folder))
        except (OSError, SlurmError) as exc:
            _unlink(secret)
            raise StartError(f"Slurm did not take the job: {exc}") from exc
        live = _Live(job, job_id)
        try:
            handle = self._processes.start(
                [self._python, "-I", str(WATCHER), str(job.folder)], cwd=launch.cwd,
                env={"PATH": os.environ.get("PATH", "/usr/bin:/bin")})
        except StartError:
            if job_id:
                self._quietly(self.slurm.cancel, job_id)
            _unlink(secret)
            raise
        handle.notes_fd, live.notes = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        live.handle = handle
        self._track(live)
        if job.gang is None:
            _record(live)
            self._note(live, f"Slurm job {job_id} submitted")
        else:
            self._join(live, job.gang)
        self._wake.set()
        return handle

    def _track(self, live: _Live) -> None:
        """Watch ``live`` (its poller started with the first job)."""
        with self._lock:
            self._jobs[live.job.folder] = live
            if self._poller is None:
                self._poller = threading.Thread(target=self._watch, name="osmo-slurm-poll",
                                                daemon=True)
                self._poller.start()
        self._wake.set()

    def _join(self, live: _Live, gang: Gang) -> None:
        """One more member of ``gang`` started: the last one submits the gang's job."""
        with self._lock:
            started = self._gangs.setdefault(gang.key, {})
            started[gang.index] = live
            complete = len(started) == len(gang.members)
            if complete:
                del self._gangs[gang.key]
        if not complete:
            self._note(live, f"waits for its group ({len(started)} of {len(gang.members)} "
                             "members ready) to go to Slurm as one job")
            return
        members = [started[i] for i in range(len(gang.members))]
        if any(member.killed for member in members):
            for member in members:
                self._end(member, 137)
            return
        try:
            job_id = self._submit_gang(members)
        except (OSError, SlurmError, PrepareError) as exc:
            for member in members:
                self._note(member, f"Slurm did not take the group's job: {exc}")
                self._end(member, 1)
            return
        for index, member in enumerate(members):
            member.job_id = f"{job_id}+{index}"
            _record(member)
            self._note(member, f"Slurm job {member.job_id} submitted (one job for the group "
                               f"of {len(members)}: all placed, or none)")

    def _submit_gang(self, members: list[_Live]) -> str:
        """Write each member's ``gang.json`` and the gang's script; sbatch; the job id.

        Slurm gives each component of a heterogeneous job a node of its own: a group with
        more members than the pool's partitions have nodes could never start, and is
        refused here rather than left PENDING for ever.
        """
        nodes = self.capacity().listed
        if len(members) > nodes:
            raise SlurmError(f"Slurm runs each member of a group on a node of its own (one "
                             f"heterogeneous job), and the pool's partitions have {nodes} "
                             f"node{'s' if nodes != 1 else ''} for its {len(members)} "
                             "members: it could never start")
        lead = next((m for m in members if m.job.gang and m.job.gang.lead), members[0])
        # its peers start once it runs, as in OSMO (a container's, as its engine says)
        box = lead.job.container
        after = None
        if box is not None and self._containers is not None:
            after = [self._containers.engine.engine.path, "container", "inspect",
                     "--format", "{{.State.Running}}", box.name]
        for member in members:
            _write_private(member.job.folder / "gang.json", json.dumps({
                "size": len(members),
                "after": after if member is not lead else None,
                "after_env": self._containers.engine.env if after and self._containers
                else None}))
        first = members[0].job.folder
        script = first / "gang.sh"
        _write_private(script, gang_script(self._python, AGENT,
                                           [m.job.folder for m in members]))
        name = members[0].job.name.replace("osmo-", "osmo-group-", 1)
        args = gang_args(name=name, owner=self.owner, folder=first,
                         components=[m.job.resources for m in members])
        return self.slurm.sbatch(str(script), args, cwd=str(first))

    def _end(self, live: _Live, code: int) -> None:
        """``live`` ended without a job's word: its watcher exits with ``code``."""
        _write_private(live.job.folder / "ended.json", json.dumps({"code": code}))
        live.ended = True

    def kill(self, handle: ProcessHandle, *, force: bool = False) -> None:
        """``scancel`` with SIGTERM (SIGKILL, then the job cancelled, when ``force``)."""
        live = self._live(handle)
        if live is None:
            self._processes.kill(handle, force=force)
            return
        live.killed = True
        if not live.job_id:  # a gang member whose group's job is not submitted yet
            self._end(live, 137 if force else 143)
            return
        self._calls.later(self._cancel, live, force)

    def reap(self, handle: ProcessHandle) -> int:
        """The job's exit code, once its watcher ended (a job still running is cancelled).

        A job Slurm ended at its time limit (TIMEOUT) and osmo did not kill is
        ``ExitCode.EXEC_TIMEOUT``: the task is FAILED_EXEC_TIMEOUT. A gang member whose job
        was lost says so on the handle (``lost``).
        """
        live = self._live(handle)
        if live is not None and handle.popen.poll() is None:
            live.killed = True
            self._quietly(self.slurm.cancel, live.job_id)  # the pool closes under it
        code = self._processes.reap(handle)
        if live is not None and not live.killed and live.lost_as:
            handle.lost = live.lost_as
        if live is not None and not live.killed and _timed_out(live.job.folder):
            return ExitCode.EXEC_TIMEOUT
        return code

    def release(self, handle: ProcessHandle) -> None:
        """Close the watcher's descriptors and the notes pipe; the secret file goes."""
        self._processes.release(handle)
        live = self._live(handle)
        if live is not None:
            _unlink_secrets(live.job)
            with self._lock:
                live.notes = _close(live.notes)
        handle.notes_fd = _close(handle.notes_fd)

    def exec(self, launch: Launch, command: Sequence[str], *, tty: bool,
             term: str | None) -> ExecCommand:
        """``srun --jobid=ID --overlap`` of ``command`` beside the task, in its folder.

        Raises:
            SlurmError: srun is missing.
        """
        job = _job(launch)
        live = self._jobs.get(job.folder)
        job_id = live.job_id if live is not None else "0"
        env = dict(launch.env)
        if job.container is not None and self._containers is not None:
            inner = self._containers.exec(replace(launch, run=job.container), command,
                                          tty=tty, term=term)
            command, env = inner.argv, inner.env
        elif tty and term is not None:
            env["TERM"] = term
        argv = self.slurm.srun_argv(f"--jobid={job_id}", "--overlap", "--nodes=1",
                                    "--ntasks=1", "--quiet", f"--chdir={launch.cwd}",
                                    "--export=ALL", *(["--pty"] if tty else []), *command)
        env.update((k, v) for k, v in self.slurm.env.items() if k.startswith("SLURM_CONF"))
        return ExecCommand(argv, launch.cwd, env)

    def connector(self, launch: Launch, handle: ProcessHandle) -> Connector:
        """To the task's ports on the address of its job's node.

        The node is looked up at each connection: the task may run (and listen) before the
        poller has heard from Slurm where, and a connection then gets a ConnectError to retry.

        Raises:
            ConnectError: the job is no longer followed here.
        """
        folder = _job(launch).folder
        if folder not in self._jobs:
            raise ConnectError("the task's Slurm job is not running")

        def connect(port: int, udp: bool) -> socket.socket:
            live = self._jobs.get(folder)
            if live is None or not live.nodes:
                raise ConnectError("the task's Slurm job is not running on a node yet")
            try:
                address = self.slurm.node_address(live.nodes.split(",")[0])
            except SlurmError as exc:
                raise ConnectError(str(exc)) from None
            return dial(address, port, udp=udp)
        return connect

    def cleanup(self, launch: Launch) -> None:
        """Its job is cancelled if its task may still run; the secret file goes."""
        job = launch.run
        if not isinstance(job, SlurmJob):
            return
        _unlink_secrets(job)
        with self._lock:
            live = self._jobs.pop(job.folder, None)
        agent_done = (job.folder / "exit.json").exists()  # the job ends by itself
        if live is not None and live.job_id and not live.ended and not agent_done:
            # (a gang member's cancel would end its whole group: only one still running)
            self._calls.later(self._quietly, self.slurm.cancel, live.job_id)
        if job.container is not None and self._containers is not None:
            self._containers.cleanup(replace(launch, run=job.container))
            if live is not None and live.killed:  # its engine CLI may have died mid-create
                self._calls.later(self._remove_container, job.container.name)

    def close(self) -> None:
        """Stop the poller; cancel the jobs still running; wait for Slurm calls under way."""
        self._closing.set()
        self._wake.set()
        if self._poller is not None:
            self._poller.join()
        with self._lock:
            left = [live for live in self._jobs.values() if live.job_id and not live.ended]
        for live in left:
            self._quietly(self.slurm.cancel, live.job_id)
        self._calls.close()

    # -------------------------------------------------------------- the poller

    def _watch(self) -> None:
        while not self._closing.is_set():
            self._wake.wait(self._poll)
            self._wake.clear()
            with self._lock:
                live = [job for job in self._jobs.values() if job.job_id and not job.ended]
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
        if seen.phase is Phase.WAITING:
            if info is not None:  # osmo query and osmo events show it
                self._waits(live, waiting_reason(live.job_id, info.state, info.reason))
            return
        self._waits(live, "")
        if seen.phase in (Phase.RUNNING, Phase.ENDED) and info is not None and info.nodes:
            # (once; a job that ran between two reads is first seen ended: where it ran)
            self._say(live, f"{PROGRESS_PREFIX} Slurm job {live.job_id} RUNNING on "
                            f"{info.nodes}")
        if seen.phase is Phase.LOST and live.job.gang is None:
            self._resubmit(live, seen.reason or "lost")
        elif seen.phase is Phase.LOST:  # a gang's: every member is lost, and runs again
            live.lost_as = f"job {live.job_id}: {seen.reason or 'lost'}"
            self._note(live, live.lost_as)
            self._end(live, LOST)
        elif seen.phase is Phase.ENDED:
            killed = live.killed and not seen.override
            if seen.reason and not killed:
                self._note(live, seen.reason)
            ended = {"state": live.state, "code": 137 if killed else seen.code,
                     "override": seen.override}
            _write_private(live.job.folder / "ended.json", json.dumps(ended))
            live.ended = True

    def _resubmit(self, live: _Live, reason: str) -> None:
        live.lost += 1
        old = live.job_id
        live.job_id = self.slurm.sbatch(str(live.job.script), live.job.args,
                                        cwd=str(live.job.folder))
        _record(live)
        live.said.clear()
        self._note(live, f"job {old}: {reason}; submitted again as job {live.job_id}")

    def _waits(self, live: _Live, reason: str) -> None:
        """Tell the server why the job waits (``""``: no more), once per new reason."""
        if reason != live.reason:
            live.reason = reason
            live.job.waiting(reason)
            if reason:
                self._note(live, reason)

    def _say(self, live: _Live, line: str) -> None:
        if line not in live.said:
            live.said.add(line)
            self._note(live, line)

    def _note(self, live: _Live, line: str) -> None:
        """A line for the attempt's log, as osmo's (dropped once the attempt let go)."""
        with self._lock:  # release closes the pipe under it: never a write to a reused fd
            if live.notes >= 0:
                try:
                    os.write(live.notes, f"{line}\n".encode())
                except OSError:  # full: a note is not worth a stall
                    pass

    # -------------------------------------------------------------- internals

    def _live(self, handle: ProcessHandle) -> _Live | None:
        with self._lock:
            return next((j for j in self._jobs.values() if j.handle is handle), None)

    def _cancel(self, live: _Live, force: bool) -> None:
        try:
            if force:
                self._quietly(self.slurm.cancel, live.job_id, signal="KILL")
                self.slurm.cancel(live.job_id)
                box = live.job.container
                if box is not None and self._containers is not None:
                    # the engine's CLI died with the job; its container may not have
                    self._containers.engine.remove(box.name)
            else:
                self.slurm.cancel(live.job_id, signal="TERM")
        except (SlurmError, ContainerError):
            self._quietly(self.slurm.cancel, live.job_id)  # pending: it cannot be signalled
        self._wake.set()

    def _remove_container(self, name: str, tries: int = 10, pause: float = 0.5) -> None:
        """Remove a killed task's container, which may appear a moment after its job ended."""
        assert self._containers is not None
        for _ in range(tries):
            try:
                if self._containers.engine.remove(name):
                    return
            except ContainerError:
                pass
            if self._closing.wait(pause):
                return

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


def _placeholders(cmd: PrepareAttempt) -> dict[str, str]:
    """A group member's ``{{host:NAME}}`` placeholders, by member (none alone).

    Each names a component of the group's job; the agent replaces it with the address of
    the node Slurm gives that component. Distinct, they also tell the container runtime
    that the members are spread over hosts: its containers use their node's network.
    """
    if len(cmd.hosts) < 2:
        return {}
    return {name: PLACEHOLDER.format(index) for index, name in enumerate(cmd.hosts)}


def _container(launch: Launch) -> ContainerRun:
    run = launch.run
    if not isinstance(run, ContainerRun):
        raise TypeError(f"{launch!r} was not prepared by a container runtime")
    return run


def _record(live: _Live) -> None:
    """Keep what adopting ``live``'s job takes in its folder (``job.json``)."""
    job, gang = live.job, live.job.gang
    _write_private(job.folder / "job.json", json.dumps({
        "job_id": live.job_id, "name": job.name, "args": list(job.args),
        "container": job.container.name if job.container is not None else None,
        "gang": None if gang is None else {"key": gang.key, "members": list(gang.members),
                                           "index": gang.index, "lead": gang.lead}}))


def _job_of(folder: Path, meta: Mapping[str, object]) -> SlurmJob:
    """The job ``job.json`` describes (``_record``), every field checked.

    Raises:
        OsmoError: a field is missing or of the wrong type, or its task runs in a container.
    """
    job_id, name, args, gang = (meta.get("job_id"), meta.get("name"), meta.get("args"),
                                meta.get("gang"))
    if not isinstance(job_id, str) or not _JOB_ID.fullmatch(job_id):
        raise OsmoError(f"{folder}/job.json names no Slurm job id")
    if not isinstance(name, str) or not isinstance(args, list) or not all(
            isinstance(a, str) for a in args):
        raise OsmoError(f"{folder}/job.json is not valid")
    if meta.get("container") is not None:
        raise OsmoError(f"job {job_id} runs its task in a container: not adopted yet")
    found = None
    if gang is not None:
        if not isinstance(gang, dict):
            raise OsmoError(f"{folder}/job.json names no valid group")
        key, members, index = gang.get("key"), gang.get("members"), gang.get("index")
        if not (isinstance(key, str) and isinstance(members, list) and type(index) is int
                and all(isinstance(m, str) for m in members) and 0 <= index < len(members)):
            raise OsmoError(f"{folder}/job.json names no valid group")
        found = Gang(key, tuple(members), index, gang.get("lead") is True)
    return SlurmJob(folder, name, tuple(args), gang=found)


def _timed_out(folder: Path) -> bool:
    """Whether the poller saw the job end in Slurm's TIMEOUT (``ended.json``)."""
    try:
        ended = json.loads((folder / "ended.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(ended, dict) and str(ended.get("state") or "").split()[:1] == ["TIMEOUT"]


def _unlink_secrets(job: SlurmJob) -> None:
    _unlink(job.folder / "secret.json")
    if job.container is not None and job.container.secret_env_file is not None:
        _unlink(job.container.secret_env_file)


def _write_private(path: Path, text: str) -> None:
    """Write ``text`` to a 0600 file at ``path``, never through a symlink."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW | os.O_CLOEXEC
    fd = os.open(path, flags, 0o600)
    try:
        os.fchmod(fd, 0o600)
        os.write(fd, text.encode())
    finally:
        os.close(fd)


def _close(fd: int) -> int:
    """Close ``fd`` if open; -1."""
    if fd >= 0:
        try:
            os.close(fd)
        except OSError:
            pass
    return -1


def _unlink(path: Path) -> None:
    try:
        path.unlink()
    except FileNotFoundError:
        pass


def _conforms(runtime: SlurmRuntime) -> Runtime:
    """Never called: mypy checks here that SlurmRuntime keeps the runtime contract."""
    return runtime
