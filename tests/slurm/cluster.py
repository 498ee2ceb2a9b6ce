"""A private Slurm cluster on loopback for the tests: ``munged``, ``slurmctld`` and two nodes.

Everything lives in one folder of its own (``/tmp/osmo-slurm-XXXXXXXX``: short, because the
munge socket and slurmd's step sockets are Unix sockets, and readable by all, because munged
refuses a socket in a folder others cannot enter): the munge key and socket, ``slurm.conf``,
``gres.conf`` and ``cgroup.conf``, the controller's state, each node's spool, every pid file
and log, the job completion file and the jobs' output. Every daemon listens on 127.0.0.1
(``CommunicationParameters=NoInAddrAny,NoCtldInAddrAny``) on a free port; the daemons run as
root (``SlurmUser=root``), and so do the jobs the tests submit.

Each node is one ``slurmd -N NAME`` with its own ``Port=`` in ``slurm.conf``, started in a
pid and mount namespace of its own (``unshare``, with ``node_init.py`` as its process 1).
Killing a node (:meth:`SlurmCluster.kill_slurmd`) kills its slurmd *and* every job step on
it, as a real node failure does; without the namespace ``slurmstepd`` (which forks twice and
leaves slurmd's session) would outlive it.

Memory limits: where the host has cgroup v1 ``memory`` and ``freezer`` controllers (these
machines do), jobs run under ``task/cgroup`` + ``proctrack/cgroup`` and a job over ``--mem``
ends ``OUT_OF_MEMORY``. Each node sees only a folder of its own in those hierarchies (bound
over ``/sys/fs/cgroup/<controller>`` in its mount namespace), so clusters of concurrent test
sessions never share a job's cgroup. Elsewhere the cluster falls back to
``proctrack/linuxproc``, ``task/none`` and ``JobAcctGatherParams=OverMemoryKill``: the job is
killed (signal 9) and ends ``FAILED``. :attr:`SlurmCluster.memory_enforcement` says which.

Accounting: there is no ``slurmdbd`` (it needs MySQL). ``JobCompType=jobcomp/filetxt``
records every finished job, which ``sacct -c`` (:meth:`SlurmCluster.sacct`) reads: state,
exit code, nodes, times. Pending and running jobs are seen with ``squeue``/``scontrol``.

Everything is stopped by PID (:meth:`SlurmCluster.stop`); tests/slurm/README.md has timings.
This module imports nothing from osmo (the benchmark uses it too) and never kills a process
by name: only the daemons it started and the processes that carry its cluster's marks.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

NODE_INIT = Path(__file__).with_name("node_init.py")
CGROUP_ROOT = Path("/sys/fs/cgroup")
CGROUP_CONTROLLERS = ("memory", "freezer")
"""The cgroup v1 hierarchies slurm's cgroup plugins use here (``ConstrainRAMSpace`` and
``proctrack/cgroup``); each node gets a folder of its own in each."""

PROGRAMS = ("slurmctld", "slurmd", "munged", "unshare", "mount", "sbatch", "srun", "squeue",
            "scontrol", "scancel", "sinfo", "sacct")
"""The programs the cluster and its tests need (Debian: slurm-wlm, munge, util-linux)."""

DEFAULT_SCHEDULER_PARAMETERS = "batch_sched_delay=0,sched_interval=2,bf_interval=2"
"""``SchedulerParameters`` of the tests' cluster. ``batch_sched_delay=0``: a batch job is
scheduled at the controller's next background pass (about 1 s) instead of within 3 s;
``sched_interval``/``bf_interval`` 2 s (defaults 60 and 30): a job that becomes eligible
with no event to wake the scheduler (a requeued job after ``cred_expire``) starts soon."""

_FAKE_GPU_FILES = ("/dev/null", "/dev/zero", "/dev/full")
_DAEMON_COMMANDS = ("slurmd -D -N ", ": slurmscriptd", f"{sys.executable} {NODE_INIT} ")
"""How the daemons' own helpers show in ``ps`` (slurmctld's slurmscriptd, each node's
process 1 and slurmd), for :meth:`SlurmCluster.leftovers`."""
_CLIENT_VARIABLES = ("SLURM_", "SBATCH_", "SALLOC_", "SRUN_", "SQUEUE_", "SINFO_", "SACCT_")


def missing_programs() -> list[str]:
    """The programs of :data:`PROGRAMS` that are not on ``PATH`` (root's PATH: sbin too)."""
    path = os.environ.get("PATH", "") + ":/usr/sbin:/sbin"
    return [name for name in PROGRAMS if shutil.which(name, path=path) is None]


def cgroup_v1_ready() -> bool:
    """True if this host has the cgroup v1 controllers slurm's cgroup plugins need here."""
    return (CGROUP_ROOT.joinpath("memory", "memory.oom_control").exists()
            and all(CGROUP_ROOT.joinpath(c, "cgroup.procs").exists()
                    for c in CGROUP_CONTROLLERS))


class SlurmError(AssertionError):
    """A Slurm command failed or the cluster did not reach a state in time (its logs)."""


class SlurmCluster:
    """One private cluster: start it, run Slurm's commands with :attr:`env`, stop it.

    Args:
        nodes: node names; each runs its own ``slurmd``.
        cpus: CPUs per node (all nodes share this host's cores).
        memory_mb: ``RealMemory`` per node; ``DefMemPerCPU`` is a fifth of it.
        gpus: fake GPUs per node (GRES ``gpu``, ``File=/dev/null``...; jobs see
            ``CUDA_VISIBLE_DEVICES``). At most 3.
        slurmd_timeout: ``SlurmdTimeout`` (s).
        message_timeout: ``MessageTimeout`` (s). With ``slurmd_timeout``, how soon a node
            that stopped answering is DOWN: 5 and 5, about 15 s here; 5 and 3, about 11 s.
        scheduler_parameters: ``SchedulerParameters`` (None: Slurm's defaults).
        cgroups: use cgroup v1 memory limits (None: when :func:`cgroup_v1_ready`).
        extra_conf: more ``slurm.conf`` lines.
        base: the folder that holds the cluster's folder (default: the system's temp).
    """

    def __init__(self, nodes: Iterable[str] = ("n1", "n2"), *, cpus: int = 2,
                 memory_mb: int = 500, gpus: int = 1, slurmd_timeout: int = 5,
                 message_timeout: int = 5,
                 scheduler_parameters: str | None = DEFAULT_SCHEDULER_PARAMETERS,
                 cgroups: bool | None = None, extra_conf: Iterable[str] = (),
                 base: Path | None = None) -> None:
        self.nodes = tuple(nodes)
        self.cpus, self.memory_mb, self.gpus = cpus, memory_mb, gpus
        if not 0 <= gpus <= len(_FAKE_GPU_FILES):
            raise ValueError(f"gpus: 0 to {len(_FAKE_GPU_FILES)}")
        self.slurmd_timeout, self.message_timeout = slurmd_timeout, message_timeout
        self.scheduler_parameters = scheduler_parameters
        self.cgroups = cgroup_v1_ready() if cgroups is None else cgroups
        self.extra_conf = tuple(extra_conf)
        self.root = Path(tempfile.mkdtemp(prefix="osmo-slurm-", dir=base))
        self.root.chmod(0o755)
        self.ctld_port, *ports = _free_ports(1 + len(self.nodes))
        self.node_ports = dict(zip(self.nodes, ports, strict=True))
        self.env = _client_env(os.environ, self.conf)
        self._procs: dict[str, subprocess.Popen[bytes]] = {}
        self._cgroup_dirs: dict[str, list[Path]] = {}
        self._inits: dict[str, tuple[int, str]] = {}  # node -> (pid of its process 1,
        #                                                    its pid namespace "pid:[...]")
        self._starts = 0

    # -- the cluster's files ---------------------------------------------------------------

    @property
    def conf(self) -> Path:
        """``slurm.conf`` (``SLURM_CONF`` in :attr:`env`)."""
        return self.root / "etc" / "slurm.conf"

    @property
    def munge_socket(self) -> Path:
        """munged's socket (slurm.conf's ``AuthInfo=socket=``)."""
        return self.root / "munge-socket" / "munge.socket"

    @property
    def jobs(self) -> Path:
        """The folder :meth:`sbatch` runs in and writes job output to (``<jobid>.out``)."""
        return self.root / "jobs"

    @property
    def jobcomp(self) -> Path:
        """The job completion file (``jobcomp/filetxt``) that ``sacct -c`` reads."""
        return self.root / "log" / "jobcomp.txt"

    @property
    def memory_enforcement(self) -> str:
        """``"cgroup"`` (a job over ``--mem`` is OUT_OF_MEMORY) or ``"poll"`` (it is killed
        by jobacct_gather's polling and ends FAILED)."""
        return "cgroup" if self.cgroups else "poll"

    def log(self, daemon: str) -> Path:
        """The log of ``daemon``: ``slurmctld``, ``munged`` or a node's name."""
        name = daemon if daemon in ("slurmctld", "munged") else f"slurmd-{daemon}"
        return self.root / "log" / f"{name}.log"

    def output(self, job_id: str) -> str:
        """What job ``job_id`` wrote (its ``<jobid>.out`` in :attr:`jobs`)."""
        return (self.jobs / f"{job_id}.out").read_text(errors="replace")

    # -- lifecycle -------------------------------------------------------------------------

    def start(self, timeout: float = 60) -> SlurmCluster:
        """Write the configuration, start munged, slurmctld and every node; wait until
        every node is idle. Stops what it started if it fails."""
        try:
            self._write_files()
            self._start_munged(timeout)
            self._spawn("slurmctld", ["slurmctld", "-D"])
            self._wait(lambda: self.run("scontrol", "ping", check=False).returncode == 0,
                       timeout, "slurmctld never answered scontrol ping", "slurmctld")
            for node in self.nodes:
                self.start_slurmd(node, wait=False)
            self.wait_nodes(self.nodes, "idle", timeout)
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self, *, remove: bool = True) -> list[str]:
        """Stop everything by PID (nodes with their jobs, slurmctld and its helper, munged),
        also what a test killed already; then remove the cluster's cgroups and folder.

        Returns:
            The processes found still holding on to the cluster afterwards (then killed by
            PID): a test asserts this is empty.
        """
        left: list[str] = []
        for node in self.nodes:
            try:
                self.kill_slurmd(node)
            except SlurmError as exc:
                left.append(str(exc))
        ctld = self._procs.pop("slurmctld", None)
        if ctld is not None:  # SIGKILL: its state goes with the folder (SIGTERM takes ~3 s)
            _terminate(ctld, signal.SIGKILL)
            _kill_group(ctld.pid)  # slurmscriptd, its helper, shares its process group
        munged = self._procs.pop("munged", None)
        if munged is not None:
            _terminate(munged, signal.SIGTERM)
        for pid, cmd in self.leftovers():
            _kill(pid)
            left.append(f"{pid} {cmd}")
        for node in list(self._cgroup_dirs):
            try:
                self._remove_cgroups(node)
            except SlurmError as exc:
                left.append(str(exc))
        if remove:
            shutil.rmtree(self.root, ignore_errors=True)
        return left

    def kill_slurmd(self, node: str, timeout: float = 30) -> None:
        """Make ``node`` fail: SIGKILL its slurmd and every job step on it (its pid
        namespace ends); return once none of them is left. No-op if it is not running."""
        init = self._inits.pop(node, None)
        proc = self._procs.pop(node, None)
        if init is not None:  # its process 1: the kernel kills the rest of the namespace
            pid, namespace = init
            _kill(pid)
            self._wait(lambda: not _pids_in(namespace), timeout,
                       f"processes of {node} outlived its namespace's process 1", watch=False)
        if proc is not None:  # unshare, which exits when its child does; killed first, it
            _terminate(proc, None)  # would leave the namespace's end to --kill-child: ~1 s

    def start_slurmd(self, node: str, *, wait: bool = True, timeout: float = 60) -> None:
        """Start ``node``'s slurmd (again); with ``wait``, until the controller has it back
        up (``ReturnToService=2``: a node that was DOWN for not responding returns)."""
        if node in self._procs:
            raise SlurmError(f"slurmd of {node} is already running")
        (self.root / "nodes" / node / "spool").mkdir(parents=True, exist_ok=True)
        options = []
        for controller, folder in self._make_cgroups(node):
            options += ["--cgroup", f"{controller}={folder}"]
        self._spawn(node, ["unshare", "--pid", "--fork", "--mount-proc", "--kill-child",
                           sys.executable, str(NODE_INIT), *options, "--",
                           "slurmd", "-D", "-N", node])
        self._inits[node] = self._init_of(node, timeout)
        if wait:
            self.wait_nodes([node], "idle", timeout)

    def reset(self, timeout: float = 60) -> None:
        """Cancel every job, start every node that is not running, and wait until no job
        is left and every node is idle (between tests sharing one cluster)."""
        self.run("scancel", "--user=root")
        for node in self.nodes:
            if not self.alive(node):
                self.kill_slurmd(node)  # forget a node that died on its own
                self.start_slurmd(node, wait=False)
        self._wait(lambda: not self.run("squeue", "-h", "-o", "%i").stdout.strip(), timeout,
                   "jobs still in the queue after scancel", "slurmctld")
        self.wait_nodes(self.nodes, "idle", timeout)

    def cgroups_of(self, node: str) -> list[Path]:
        """The cgroup folders ``node`` runs in now (one per controller; none without
        cgroups)."""
        return list(self._cgroup_dirs.get(node, []))

    def alive(self, daemon: str) -> bool:
        """True while ``daemon`` (``munged``, ``slurmctld`` or a node) runs."""
        proc = self._procs.get(daemon)
        return proc is not None and proc.poll() is None

    def pid(self, daemon: str) -> int:
        """The host PID of ``daemon`` (for a node: of its ``unshare``)."""
        return self._procs[daemon].pid

    def leftovers(self, *, daemons: bool = True) -> list[tuple[int, str]]:
        """Processes that refer to this cluster (its ``SLURM_CONF`` in their environment or
        its folder on their command line) as (pid, command line); with ``daemons=False``
        only those that are not part of a running daemon: jobs, their steps and clients."""
        mine = {p.pid for p in self._procs.values()}
        marks = (str(self.root).encode(), f"SLURM_CONF={self.conf}".encode())
        found = []
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit() or int(entry.name) in mine or \
                    int(entry.name) == os.getpid():
                continue
            try:
                cmdline = (entry / "cmdline").read_bytes()
                environ = (entry / "environ").read_bytes()
            except OSError:
                continue
            if cmdline and (marks[0] in cmdline or marks[1] in environ):
                found.append((int(entry.name), cmdline.replace(b"\0", b" ").decode(
                    errors="replace").strip()))
        if not daemons:
            found = [(pid, cmd) for pid, cmd in found if not cmd.startswith(_DAEMON_COMMANDS)]
        return found

    # -- Slurm's commands ------------------------------------------------------------------

    def run(self, *argv: str, check: bool = True, timeout: float = 60,
            input: str | None = None) -> subprocess.CompletedProcess[str]:
        """Run a Slurm command (``sinfo``, ``sbatch``...) against this cluster."""
        proc = subprocess.run(argv, env=self.env, cwd=self.jobs, capture_output=True,
                              text=True, timeout=timeout, input=input,
                              stdin=None if input is not None else subprocess.DEVNULL)
        if check and proc.returncode != 0:
            raise SlurmError(f"{' '.join(argv)} exited {proc.returncode}:\n"
                             f"{proc.stdout}{proc.stderr}")
        return proc

    def sbatch(self, script: str, *args: str, timeout: float = 60) -> str:
        """Submit ``script`` (its text; a ``#!/bin/sh`` line is added when it has none)
        with ``args``; its output goes to ``jobs/<jobid>.out``. Returns the job id."""
        if not script.startswith("#!"):
            script = "#!/bin/sh\n" + script
        proc = self.run("sbatch", "--parsable", f"--output={self.jobs}/%j.out", *args,
                        input=script, timeout=timeout)
        return proc.stdout.strip().split(";")[0]

    def job(self, job_id: str) -> dict[str, str]:
        """``scontrol show job`` as a dictionary (JobState, Reason, NodeList, ExitCode...)."""
        text = self.run("scontrol", "show", "job", "--oneliner", job_id).stdout
        return _fields(text)

    def wait_job(self, job_id: str, states: Iterable[str], timeout: float = 60
                 ) -> dict[str, str]:
        """Wait until job ``job_id``'s state is one of ``states``; its fields then."""
        wanted = set(states)
        seen: dict[str, str] = {}

        def reached() -> bool:
            seen.update(self.job(job_id))
            return seen.get("JobState") in wanted

        self._wait(reached, timeout,
                   lambda: f"job {job_id} never reached {sorted(wanted)}: {seen}", "slurmctld")
        return seen

    def sacct(self, job_id: str) -> dict[str, str]:
        """The finished job's record from the job completion file (``sacct -c``): JobID,
        State, ExitCode, NodeList, Start, End, Elapsed. Empty while it has not ended."""
        fields = "JobID,JobName,State,ExitCode,NodeList,Start,End,Elapsed"
        out = self.run("sacct", "-c", "-P", "-n", "-j", job_id, "-o", fields).stdout
        lines = out.strip().splitlines()
        return dict(zip(fields.split(","), lines[-1].split("|"), strict=True)) if lines else {}

    def node_states(self) -> dict[str, str]:
        """Each node's state as ``sinfo`` prints it (``idle``, ``mixed``, ``down*``...)."""
        out = self.run("sinfo", "-h", "-N", "-o", "%N %T").stdout
        return dict(line.split(None, 1) for line in out.strip().splitlines())

    def wait_nodes(self, nodes: Iterable[str], state: str | Callable[[str], bool],
                   timeout: float = 60) -> dict[str, str]:
        """Wait until every node of ``nodes`` is in ``state`` (a ``sinfo`` state, or a
        test on it); the states then."""
        names = list(nodes)
        test = state if callable(state) else (lambda s: s == state)
        seen: dict[str, str] = {}

        def reached() -> bool:
            seen.update(self.node_states())
            return all(test(seen.get(node, "")) for node in names)

        self._wait(reached, timeout, lambda: f"nodes {names} never reached {state}: {seen}",
                   *names, "slurmctld")
        return seen

    # -- internals -------------------------------------------------------------------------

    def _write_files(self) -> None:
        for sub in ("etc", "munge", "munge-socket", "ctld/state", "log", "jobs", "tmp"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        (self.root / "munge").chmod(0o700)
        key = self.root / "munge" / "munge.key"
        key.write_bytes(os.urandom(1024))
        key.chmod(0o400)
        self.conf.write_text(slurm_conf(self))
        self.conf.with_name("gres.conf").write_text(
            "".join(f"NodeName={node} Name=gpu File={','.join(_FAKE_GPU_FILES[:self.gpus])}\n"
                    for node in self.nodes) if self.gpus else "")
        self.conf.with_name("cgroup.conf").write_text(
            "CgroupPlugin=cgroup/v1\nConstrainRAMSpace=yes\nConstrainSwapSpace=no\n"
            "ConstrainCores=no\nConstrainDevices=no\n")

    def _start_munged(self, timeout: float) -> None:
        munge = self.root / "munge"
        self._spawn("munged", [
            "munged", "--foreground", f"--socket={self.munge_socket}",
            f"--key-file={munge / 'munge.key'}", f"--pid-file={munge / 'munged.pid'}",
            f"--seed-file={munge / 'munged.seed'}", f"--log-file={self.log('munged')}"])
        self._wait(self.munge_socket.exists, timeout, "munged made no socket", "munged")

    def _spawn(self, name: str, argv: list[str]) -> None:
        with open(self.root / "log" / f"{name}.out", "ab") as out:
            self._procs[name] = subprocess.Popen(
                argv, env=self.env, cwd=self.root, stdin=subprocess.DEVNULL, stdout=out,
                stderr=subprocess.STDOUT, start_new_session=True)

    def _make_cgroups(self, node: str) -> list[tuple[str, Path]]:
        if not self.cgroups:
            return []
        self._remove_cgroups(node)
        self._starts += 1
        made = []
        for controller in CGROUP_CONTROLLERS:
            folder = CGROUP_ROOT / controller / f"{self.root.name}-{node}-{self._starts}"
            folder.mkdir()
            made.append((controller, folder))
        self._cgroup_dirs[node] = [folder for _, folder in made]
        return made

    def _remove_cgroups(self, node: str, timeout: float = 10) -> None:
        """Remove ``node``'s cgroup folders, innermost first (a cgroup is removed with
        rmdir once its processes are gone: wait a little for the killed ones)."""
        deadline = time.monotonic() + timeout
        for top in self._cgroup_dirs.pop(node, []):
            while top.exists():
                for folder in sorted((p for p in top.rglob("*") if p.is_dir()),
                                     key=lambda p: len(p.parts), reverse=True) + [top]:
                    try:
                        folder.rmdir()
                    except OSError:
                        pass
                if top.exists():
                    if time.monotonic() > deadline:
                        raise SlurmError(f"cgroup {top} still busy after {timeout} s")
                    time.sleep(0.05)

    def _init_of(self, node: str, timeout: float) -> tuple[int, str]:
        """The host pid and the pid namespace of ``node``'s process 1 (the child of its
        ``unshare``)."""
        unshare = self._procs[node].pid
        children = Path(f"/proc/{unshare}/task/{unshare}/children")
        found: list[tuple[int, str]] = []

        def known() -> bool:
            for child in children.read_text().split() if children.exists() else ():
                try:
                    found.append((int(child), os.readlink(f"/proc/{child}/ns/pid")))
                except OSError:
                    continue
            return bool(found)

        self._wait(known, timeout, f"{node}: unshare started no process", node)
        return found[0]

    def _wait(self, reached: Callable[[], bool], timeout: float,
              message: str | Callable[[], str], *logs: str, watch: bool = True) -> None:
        """Poll ``reached`` until it holds; fail with the logs of ``logs`` when the time is
        up or, with ``watch``, as soon as a daemon has exited (none should while a test
        waits on the cluster)."""
        deadline = time.monotonic() + timeout
        while not reached():
            dead = [name for name, proc in self._procs.items()
                    if watch and proc.poll() is not None]
            if dead or time.monotonic() > deadline:
                text = message() if callable(message) else message
                raise SlurmError(f"{text}" + (f" (exited: {dead})" if dead else "")
                                 + self._tails(*logs, *dead))
            time.sleep(0.05)

    def _tails(self, *daemons: str) -> str:
        out = []
        for daemon in dict.fromkeys(daemons):
            for path in (self.log(daemon), self.root / "log" / f"{daemon}.out"):
                if path.exists():
                    lines = path.read_text(errors="replace").splitlines()[-15:]
                    out.append(f"\n--- {path.name} ---\n" + "\n".join(lines))
        return "".join(out)


def slurm_conf(cluster: SlurmCluster) -> str:
    """The text of ``cluster``'s ``slurm.conf``."""
    root = cluster.root
    if cluster.cgroups:
        limits = ["ProctrackType=proctrack/cgroup", "TaskPlugin=task/cgroup"]
    else:
        limits = ["ProctrackType=proctrack/linuxproc", "TaskPlugin=task/none",
                  "JobAcctGatherParams=OverMemoryKill"]
    lines = [
        "ClusterName=osmo-test",
        "SlurmctldHost=localhost(127.0.0.1)",
        f"SlurmctldPort={cluster.ctld_port}",
        "SlurmUser=root",
        "SlurmdUser=root",
        "AuthType=auth/munge",
        "CredType=cred/munge",
        # cred_expire also sets how long a requeued job waits before it may start again
        f"AuthInfo=socket={cluster.munge_socket},cred_expire=15",
        "CommunicationParameters=NoInAddrAny,NoCtldInAddrAny",
        f"StateSaveLocation={root}/ctld/state",
        f"SlurmctldPidFile={root}/ctld/slurmctld.pid",
        f"SlurmctldLogFile={root}/log/slurmctld.log",
        f"SlurmdSpoolDir={root}/nodes/%n/spool",
        f"SlurmdPidFile={root}/nodes/%n/slurmd.pid",
        f"SlurmdLogFile={root}/log/slurmd-%n.log",
        f"TmpFS={root}/tmp",
        "SlurmdParameters=config_overrides",  # trust CPUs/RealMemory below, not the host
        "MailProg=/bin/true",
        "MpiDefault=none",
        *limits,
        "JobAcctGatherType=jobacct_gather/linux",
        "JobAcctGatherFrequency=1",
        "AccountingStorageType=accounting_storage/none",
        "JobCompType=jobcomp/filetxt",
        f"JobCompLoc={cluster.jobcomp}",
        "SelectType=select/cons_tres",
        "SelectTypeParameters=CR_Core_Memory",
        f"DefMemPerCPU={max(1, cluster.memory_mb // 5)}",
        "SchedulerType=sched/backfill",
        *([f"SchedulerParameters={cluster.scheduler_parameters}"]
          if cluster.scheduler_parameters else []),
        f"SlurmdTimeout={cluster.slurmd_timeout}",
        f"MessageTimeout={cluster.message_timeout}",
        "ReturnToService=2",
        "KillWait=3",
        *(["GresTypes=gpu"] if cluster.gpus else []),
        *cluster.extra_conf,
    ]
    gres = f" Gres=gpu:{cluster.gpus}" if cluster.gpus else ""
    for node in cluster.nodes:
        lines.append(
            f"NodeName={node} NodeHostname=localhost NodeAddr=127.0.0.1 "
            f"Port={cluster.node_ports[node]} CPUs={cluster.cpus} Boards=1 SocketsPerBoard=1 "
            f"CoresPerSocket={cluster.cpus} ThreadsPerCore=1 RealMemory={cluster.memory_mb} "
            f"TmpDisk=1024{gres}")
    lines.append(f"PartitionName=debug Nodes={','.join(cluster.nodes)} Default=YES "
                 "MaxTime=INFINITE State=UP")
    return "\n".join(lines) + "\n"


def _client_env(base: Mapping[str, str], conf: Path) -> dict[str, str]:
    env = {k: v for k, v in base.items() if not k.startswith(_CLIENT_VARIABLES)}
    env["SLURM_CONF"] = str(conf)
    env["PATH"] = env.get("PATH", "/usr/bin:/bin") + ":/usr/sbin:/sbin"
    return env


def _fields(text: str) -> dict[str, str]:
    """``Key=Value Key=Value...`` (one line of ``scontrol --oneliner``) as a dictionary;
    a value may hold spaces when the next word has no ``=`` (``Reason=Not responding``)."""
    out: dict[str, str] = {}
    key = None
    for word in text.split():
        name, eq, value = word.partition("=")
        if eq and name and name[0].isalpha():
            key = name
            out[key] = value
        elif key is not None:
            out[key] += " " + word
    return out


def _pids_in(namespace: str) -> list[int]:
    """The processes whose pid namespace is ``namespace`` (``pid:[inode]``)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if os.readlink(entry / "ns" / "pid") == namespace:
                    pids.append(int(entry.name))
            except OSError:
                continue
    return pids


def _free_ports(count: int) -> list[int]:
    """``count`` distinct free TCP ports on 127.0.0.1 (held together while chosen)."""
    sockets = [socket.socket(socket.AF_INET, socket.SOCK_STREAM) for _ in range(count)]
    try:
        for sock in sockets:
            sock.bind(("127.0.0.1", 0))
        return [int(sock.getsockname()[1]) for sock in sockets]
    finally:
        for sock in sockets:
            sock.close()


def _terminate(proc: subprocess.Popen[bytes], sig: int | None, grace: float = 10) -> None:
    """Send ``sig`` (None: none) to ``proc``; SIGKILL it if it has not exited ``grace``
    seconds later; reap it."""
    if proc.poll() is None:
        if sig is not None:
            _kill(proc.pid, sig)
        try:
            proc.wait(timeout=grace)
            return
        except subprocess.TimeoutExpired:
            _kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)


def _kill(pid: int, sig: int = signal.SIGKILL) -> None:
    try:
        os.kill(pid, sig)
    except ProcessLookupError:
        pass


def _kill_group(pgid: int) -> None:
    try:
        os.killpg(pgid, signal.SIGKILL)
    except ProcessLookupError:
        pass
