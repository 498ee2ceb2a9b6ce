"""One chaos trial: a workflow run while its server (and, remotely, its workers) are SIGKILLed.

Used by ``tests/e2e/test_chaos.py`` (a few trials) and ``bench/bench_chaos.py`` (many). Every
process is real: the server started by the CLI, remote workers (``osmo worker``), the tasks.

A trial, from a seed (everything random comes from ``random.Random(seed)``):

1. A DAG: a source, a fan-out of ``width`` tasks, a join, a second fan-out, a sink. Each task
   checks every input byte for byte against what its upstream must have written (computed
   from the seed and the upstream's name) and, on any difference, notes it in
   ``shared/partial`` and exits 99; then it sleeps 0.1-0.6 s and writes its own 64 KiB.
2. ``kills`` SIGKILLs at random moments (0-1.5 s after the previous recovery), of the server
   (``mode="local"``: its local pool runs the tasks) or of the server or one of two workers
   (``mode="remote"``). After a server kill, the next CLI call starts a new server (with the
   saved options); a killed worker starts again under the same name and home, and counts
   as back once its new process says it registered (``worker.json``).
   With ``warm``, every other task of the fan-outs is a *typed* task (``chaostype:step``, a
   custom type written beside the spec, doing the same as the command) and the pool runs
   unsandboxed (``--sandbox off``; remotely, only worker ``w2``): those attempts are forks
   of warm runners (``osmo.runtime.process.warm``), and each notes in ``shared/warm`` that it
   was one; one that finds, after its sleep, that the pool it was forked for died notes it
   in ``shared/orphans`` (two seconds later, if it is still alive then).
3. Checks, after the workflow ended and everything was stopped: the workflow COMPLETED
   (or, where the caller allows it, failed only by the documented quarantine rule: a kill
   that lands while the server applies an attempt's report fails that attempt);
   every task has exactly one committed attempt (one lineage record for its output, one
   COMPLETED transition); every output's digest is the expected one; no task saw a partial
   input; no process of the trial is left (found by the trial's folder in a process's
   command line or environment, and killed by pid). With ``warm``: at each kill, the warm
   runners under the killed process (and their forked attempts) are gone a few seconds
   after it, no forked attempt outlives its pool (``shared/orphans``; both:
   :attr:`TrialResult.warm_survivors`), and none is left at the end.

Leftover task processes of a SIGKILLed *remote worker* are counted apart
(:attr:`TrialResult.leftover_tasks`): a task dying with its worker is issue 15 item 1, not
merged yet when this was written, so the suite checks them only for the local pool.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import random
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path

from osmo.layout import Home
from osmo.runtime.process import warm_runner
from osmo.store.sqlite import Store
from tests.conftest import Osmo, process_alive, wait_gone
from tests.e2e.cluster import Cluster

TASK = """
import hashlib, os, sys, time
name, seed, out, shared, delay, *inputs = sys.argv[1:]
with open(os.path.join(shared, "starts"), "a") as f:
    f.write(name + "\\n")
def content(task):
    return hashlib.sha256(f"{seed}:{task}".encode()).digest() * 2048
for item in inputs:
    upstream, path = item.split("=", 1)
    with open(os.path.join(path, "data.bin"), "rb") as f:
        data = f.read()
    if data != content(upstream):
        with open(os.path.join(shared, "partial"), "a") as f:
            f.write(f"{name} read {len(data)} wrong bytes from {upstream}\\n")
        sys.exit(99)
time.sleep(float(delay))
with open(os.path.join(out, "data.bin"), "wb") as f:
    f.write(content(name))
"""


TYPE = """
import hashlib, os, time
from osmo import Param, task_type


def stat(pid):
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[1].split()


def alive(pid, start):
    try:
        fields = stat(pid)
    except OSError:
        return False
    return fields[19] == start and fields[0] != "Z"


@task_type(version="1", params={"seed": Param(int), "shared": Param(str), "delay": Param(float)})
def step(ctx):
    \"\"\"The chaos task, typed: it checks its inputs, sleeps, writes its 64 KiB.\"\"\"
    name, seed, shared = ctx.task, ctx.params["seed"], ctx.params["shared"]
    with open(os.path.join(shared, "starts"), "a") as f:
        f.write(name + "\\n")
    pool = None
    with open(f"/proc/{os.getppid()}/cmdline", "rb") as f:
        if b"warm_runner" in f.read():  # forked from a runner: note it, and whose it is
            with open(os.path.join(shared, "warm"), "a") as w:
                w.write(name + "\\n")
            pool = stat(os.getppid())[1]
            try:
                pool = (pool, stat(pool)[19])
            except OSError:  # already gone
                pool = (pool, None)
    def content(task):
        return hashlib.sha256(f"{seed}:{task}".encode()).digest() * 2048
    for upstream, path in ctx.input_named.items():
        data = (path / "data.bin").read_bytes()
        if data != content(upstream):
            with open(os.path.join(shared, "partial"), "a") as f:
                f.write(f"{name} read {len(data)} wrong bytes from {upstream}\\n")
            raise SystemExit(99)
    time.sleep(ctx.params["delay"])
    if pool is not None and alive(*pool) is False:  # its pool died: it must die too
        time.sleep(2)  # (its death is on its way, by signal: give it time)
        with open(os.path.join(shared, "orphans"), "a") as f:
            f.write(f"{name} (pid {os.getpid()}) outlived its pool (pid {pool[0]})\\n")
    (ctx.output / "data.bin").write_bytes(content(name))
"""


def expected(seed: int, task: str) -> bytes:
    """What ``task`` writes (and its consumers expect) in a trial of ``seed``."""
    return hashlib.sha256(f"{seed}:{task}".encode()).digest() * 2048


@dataclass
class TrialResult:
    """What one trial did and found."""

    seed: int
    mode: str
    tasks: int
    status: str = "?"
    kills: list[tuple[str, float]] = field(default_factory=list)  # (target, recovery s)
    reruns: int = 0  # task starts beyond one per task
    uncounted: int = 0  # attempts lost to a server restart before they ran (not capped)
    lost: list[str] = field(default_factory=list)  # tasks not COMPLETED
    quarantined: list[str] = field(default_factory=list)  # failed by the quarantine rule
    duplicated: list[str] = field(default_factory=list)  # tasks committed more than once
    bad_digests: list[str] = field(default_factory=list)
    partial: list[str] = field(default_factory=list)  # a task saw a wrong input
    leftover_tasks: list[int] = field(default_factory=list)
    leftover_other: list[int] = field(default_factory=list)  # servers, workers
    leftover_detail: list[str] = field(default_factory=list)  # what each leftover was
    warm_starts: int = 0  # attempts forked from a warm runner
    warm_at_kills: int = 0  # warm runner processes (and forks) under the killed processes
    warm_survivors: list[str] = field(default_factory=list)  # alive after their pool died
    seconds: float = 0.0

    def problems(self, *, task_leftovers: bool = True, quarantine: bool = False) -> list[str]:
        """Every broken promise, as sentences (empty: the trial is clean).

        With ``quarantine``, a workflow failed only by the documented quarantine rule (a
        SIGKILL landed while the server applied that attempt's report: docs/concepts/durability.md,
        "When the server itself fails") and the failures that follow from it (downstream, stopped) pass.
        """
        out = []
        excused = quarantine and bool(self.quarantined)
        if self.status != "COMPLETED" and not excused:
            out.append(f"workflow ended {self.status}")
        for what, items in (("lost", [] if excused else self.lost),
                            ("committed twice", self.duplicated),
                            ("wrong digest", self.bad_digests), ("saw a partial input",
                                                                  self.partial),
                            ("processes left (server/worker)", self.leftover_other),
                            ("warm runners outlived their pool", self.warm_survivors)):
            if items:
                out.append(f"{what}: {items}")
        if task_leftovers and self.leftover_tasks:
            out.append(f"task processes left: {self.leftover_tasks}")
        return out


def spec_text(seed: int, width: int, shared: Path,
              warm: bool = False) -> tuple[str, list[str]]:
    """The trial's workflow (YAML) and its task names; with ``warm``, every other task of
    the fan-outs is of the type ``chaostype:step`` (:data:`TYPE`, beside the spec)."""
    rng = random.Random(seed)
    layers = [["source"], [f"a{i}" for i in range(width)], ["join"],
              [f"b{i}" for i in range(max(1, width // 2))], ["sink"]]
    lines = ["workflow:", f"  name: chaos-{seed}", "  tasks:"]
    for depth, layer in enumerate(layers):
        ups = layers[depth - 1] if depth else []
        for name in layer:
            delay = f"{rng.uniform(0.1, 0.6):.2f}"
            inputs = ["    inputs: [" + ", ".join(f"{{task: {u}}}" for u in ups) + "]"] * bool(ups)
            if warm and len(layer) > 1 and int(name[1:]) % 2:
                lines += [f"  - name: {name}", "    type: chaostype:step",
                          f"    params: {{seed: {seed}, shared: {json.dumps(str(shared))}, "
                          f"delay: {delay}}}", *inputs]
                continue
            args = [name, str(seed), "{{output}}", str(shared), delay]
            args += [f"{u}={{{{input:{u}}}}}" for u in ups]
            lines += [f"  - name: {name}", "    command: [python3, /opt/chaos_task.py]",
                      f"    args: {json.dumps(args)}", *inputs]
            lines += ["    files:", "    - path: /opt/chaos_task.py", "      contents: |"]
            lines += [f"        {line}" if line else "" for line in TASK.strip().splitlines()]
    return "\n".join(lines) + "\n", [n for layer in layers for n in layer]


class Trial:
    """Runs one trial under ``root`` (see the module docstring)."""

    def __init__(self, root: Path, seed: int, *, mode: str = "local", kills: int = 3,
                 width: int = 6, warm: bool = False) -> None:
        assert mode in ("local", "remote"), mode
        self.root, self.seed, self.mode, self.kills = root, seed, mode, kills
        self.warm = warm
        self.rng = random.Random(seed ^ 0x5EED)
        self.shared = root / "shared"
        self.shared.mkdir(parents=True, exist_ok=True)
        self.shared.chmod(0o1777)  # a root server's sandboxed tasks write here as nobody
        self.spec, self.names = spec_text(seed, width, self.shared, warm)
        if warm:
            _write(root / "chaostype.py", TYPE)
        self.cluster = Cluster(root, env={"OSMO_HOST_ID": f"chaos-{seed}"})
        self.osmo: Osmo = self.cluster.osmo
        self.result = TrialResult(seed, mode, len(self.names))
        self.server_pids: set[int] = set()

    def run(self) -> TrialResult:
        """Run the trial; always stops and reaps everything it started."""
        started = time.monotonic()
        try:
            self._start()
            wf = self.osmo.submit(_write(self.root / "wf.yaml", self.spec))
            self._note_server()
            for _ in range(self.kills):
                time.sleep(self.rng.uniform(0.0, 1.5))
                if self._ended(wf):
                    break
                self._kill_one()
            info = self._wait_end(wf)
            self.result.status = info["status"]
            self._check_outputs(wf, info)
        finally:
            self._stop()
        self._check_store(wf)
        self._check_files()
        self._check_leftovers()
        self.result.seconds = time.monotonic() - started
        return self.result

    # ------------------------------------------------------------------ life

    def _start(self) -> None:
        if self.mode == "local":
            self.osmo("server", "start", *self._pool_args("local"), check=True)
        else:
            self.cluster.start_server()
            for name in ("w1", "w2"):
                self.cluster.start_worker(name, *self._pool_args(name), wait=False)
            for name in ("w1", "w2"):
                self.cluster.wait_online(name)

    def _pool_args(self, pool: str) -> tuple[str, ...]:
        """A pool's options: warm trials run the local pool and worker w2 unsandboxed."""
        cpus = () if pool == "local" else ("--cpus", "1")
        return (*cpus, "--sandbox", "off") if self.warm and pool in ("local", "w2") else cpus

    def _note_server(self) -> None:
        pid = self.osmo.server_pid()
        if pid is not None:
            self.server_pids.add(pid)

    def _kill_one(self) -> None:
        targets = ["server"] if self.mode == "local" else ["server", "w1", "w2"]
        target = self.rng.choice(targets)
        if target == "server":
            pid = self.osmo.server_pid()
            if pid is None:
                return
            runners = _warm_runners_under(pid)
            killed = time.monotonic()
            os.kill(pid, signal.SIGKILL)
            wait_gone(pid)
            self._check_runners_die(target, runners)
            self.osmo("list", "--count", "1", check=True)  # the next call starts a server
            self._note_server()
        else:
            proc = self.cluster.workers[target]
            runners = _warm_runners_under(proc.pid)
            killed = time.monotonic()
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=30)
            self._check_runners_die(target, runners)
            time.sleep(self.rng.uniform(0.0, 0.5))
            new = self.cluster.start_worker(target, *self._pool_args(target), wait=False)
            self._wait_registered(target, new.pid)
        self.result.kills.append((target, time.monotonic() - killed))

    def _check_runners_die(self, target: str, runners: dict[int, int],
                           timeout: float = 15) -> None:
        """The warm runners (and forked attempts) that were under killed ``target``: each
        must be gone within ``timeout`` s (they die with their pool; not a timing promise)."""
        self.result.warm_at_kills += len(runners)
        deadline = time.monotonic() + timeout
        alive = dict(runners)
        while alive and time.monotonic() < deadline:
            alive = {pid: start for pid, start in alive.items() if _same_process(pid, start)}
            time.sleep(0.05)
        self.result.warm_survivors += [f"{target}: {_describe(pid, b'')}" for pid in alive]

    def _wait_registered(self, name: str, pid: int, timeout: float = 60) -> None:
        """Until worker ``name``'s new process ``pid`` says it registered with the server."""
        health = Home(self.root / name / "worker").worker_health  # `osmo worker`: OSMO_HOME/worker
        deadline = time.monotonic() + timeout
        while True:
            with contextlib.suppress(OSError, ValueError):
                state = json.loads(health.read_text())
                if state.get("pid") == pid and state.get("connected"):
                    return
            assert time.monotonic() < deadline, f"worker {name} never registered again"
            time.sleep(0.05)

    def _ended(self, wf: str) -> bool:
        return self.osmo.query(wf)["status"] not in ("PENDING", "RUNNING", "WAITING")

    def _wait_end(self, wf: str, timeout: float = 180) -> dict:
        return self.osmo.wait_for(wf, lambda i: i["status"] not in (
            "PENDING", "RUNNING", "WAITING"), timeout=timeout)

    def _stop(self) -> None:
        self._note_server()
        for proc in self.cluster.workers.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in self.cluster.workers.values():
            try:
                proc.wait(timeout=20)
            except Exception:  # noqa: BLE001 - a worker that does not drain is killed
                proc.kill()
                proc.wait(timeout=10)
        self.osmo.stop_server()
        for pid in self.server_pids:
            wait_gone(pid, timeout=30)

    # ------------------------------------------------------------------ checks

    def _check_outputs(self, wf: str, info: dict) -> None:
        r = self.osmo("artifacts", "list", wf, "--format", "json", check=True)
        outputs = {o["task"]: o for o in json.loads(r.out)}
        self.result.lost = [t["name"] for t in info["tasks"] if t["status"] != "COMPLETED"]
        self.result.quarantined = [t["name"] for t in info["tasks"]
                                   if t["message"].startswith("quarantined:")]
        for name in set(self.names) - set(self.result.lost):  # what completed: its bytes
            want = hashlib.sha256(expected(self.seed, name)).hexdigest()
            files = {f["path"]: f["digest"] for f in outputs.get(name, {}).get("files", [])}
            if not str(files.get("data.bin", "")).endswith(want):
                self.result.bad_digests.append(name)

    def _check_store(self, wf: str) -> None:
        store = Store(self.osmo.home / "state.db")
        try:
            completed: dict[str, int] = {}
            for event in store.transitions(wf):
                if event["task"] is not None and event["status"] == "COMPLETED":
                    completed[event["task"]] = completed.get(event["task"], 0) + 1
                if event["status"] == "RESCHEDULED" and "not counted" in event["message"]:
                    self.result.uncounted += 1
            for output in store.outputs(wf):
                commits = len(store.lineage_of_manifest(output["manifest"]))
                if commits != 1 or completed.get(output["task"], 0) != 1:
                    self.result.duplicated.append(output["task"])
        finally:
            store.close()

    def _check_files(self) -> None:
        starts = (self.shared / "starts").read_text().split()
        self.result.reruns = len(starts) - len(set(starts))
        partial = self.shared / "partial"
        self.result.partial = partial.read_text().splitlines() if partial.exists() else []
        warm = self.shared / "warm"
        self.result.warm_starts = len(warm.read_text().split()) if warm.exists() else 0
        orphans = self.shared / "orphans"
        if orphans.exists():
            self.result.warm_survivors += orphans.read_text().splitlines()

    def _check_leftovers(self) -> None:
        """Find (and kill, by pid) every process still naming the trial's folder."""
        marker = str(self.root).encode()
        for pid in _pids():
            if pid == os.getpid():
                continue
            try:
                cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
                environ = Path(f"/proc/{pid}/environ").read_bytes()
            except OSError:
                continue
            if marker not in cmdline and marker not in environ:
                continue
            if not process_alive(pid):
                continue
            is_task = str(self.shared).encode() in cmdline
            (self.result.leftover_tasks if is_task else self.result.leftover_other).append(pid)
            self.result.leftover_detail.append(_describe(pid, cmdline))
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


def _describe(pid: int, cmdline: bytes) -> str:
    """A leftover process, for the failure message: its state, parent, age and command."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        state, ppid, start = fields[0], fields[1], int(fields[19]) / os.sysconf("SC_CLK_TCK")
        age = float(Path("/proc/uptime").read_text().split()[0]) - start
    except (OSError, IndexError, ValueError):
        return f"{pid}: gone"
    words = [w.decode(errors="replace")[-60:] for w in cmdline.split(b"\0") if w]
    return f"{pid}: state {state}, parent {ppid}, age {age:.2f} s: {' '.join(words)[:600]}"


def _warm_runners_under(root: int) -> dict[int, int]:
    """The warm runner processes (and their forked attempts, which share their command line)
    descending from ``root``: pid -> start time (so a reused pid is not mistaken for one)."""
    children: dict[int, list[int]] = {}
    for pid in _pids():
        stat = _stat(pid)
        if stat is not None:
            children.setdefault(int(stat[1]), []).append(pid)
    found, todo = {}, [root]
    while todo:
        for pid in children.get(todo.pop(), []):
            todo.append(pid)
            with contextlib.suppress(OSError):
                if warm_runner.__name__.encode() in Path(f"/proc/{pid}/cmdline").read_bytes():
                    stat = _stat(pid)
                    if stat is not None:
                        found[pid] = int(stat[19])
    return found


def _same_process(pid: int, start: int) -> bool:
    """``pid`` is still the process that started at ``start`` and is not a zombie."""
    stat = _stat(pid)
    return stat is not None and int(stat[19]) == start and stat[0] != "Z"


def _stat(pid: int) -> list[str] | None:
    """The fields of ``/proc/PID/stat`` after the command (state first), or None if gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def _pids() -> list[int]:
    return [int(p) for p in os.listdir("/proc") if p.isdigit()]


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path
