"""What the process sandbox (bubblewrap) costs per task, and what skipping input copies saves.

Rows:

- spawn + reap of `true` through ``ProcessGroups``, unsandboxed (with its parent-death
  ``preexec_fn``) and in the sandbox, in ms per spawn (one at a time);
- what each part of the sandbox's argv costs: `bwrap ... true` showing the system folders
  alone, then one part added (``--dev /dev``; ``--proc`` with ``--unshare-pid``; the
  private ``/tmp``; the IPC and UTS namespaces; an attempt's view), and osmo's whole argv
  without entering the node's namespaces, in ms per run (one at a time, interleaved);
- the node's namespaces (``osmo.runtime.process.netns``): what making them costs a server or worker
  once (the keeper and slirp4netns; also what a network per task would cost each task), and
  what a start costs, two at a time on 2 cores (so CPU shows), with and without entering
  them, against the sandbox before them (``--ro-bind / /`` on the host's network, as root);
- CPU per start (``perf stat`` task-clock of the starter and every process it starts; as
  root, with ``perf`` installed): osmo's argv (the node's namespaces not entered: a shell
  loop cannot), the same without ``--cap-drop ALL``, and the issue 16 prototypes of one
  long-lived sandbox that makes a fresh mount and pid namespace per task
  (``sandbox_supervisor.py``, and its C twin when ``cc`` is installed);
- a chain of ``--tasks`` `true` tasks (one task at a time: per-task latency) with
  ``--sandbox off`` and ``on``;
- bench_inputs.py's fan-out whose tasks read their inputs, ``off`` (each attempt gets its own
  copy) and ``on`` (inputs bound read-only, no copies).

Same method as bench_engine.py (fresh server per run, ``no_cache``, submit → COMPLETED).

Usage: python bench/bench_sandbox.py [--runs 3] [--tasks 300] [--fanout 1000] [--spawns 200]
       [--flags 100] [--cpu 300] [--base DIR] [--json out.json]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import select
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_engine import chain, run_once  # noqa: E402
from bench_inputs import fan_out_reading  # noqa: E402
from benchlib import quick, row, write_rows  # noqa: E402

from osmo.options import ServerOptions  # noqa: E402
from osmo.runtime import ProcessGroups  # noqa: E402
from osmo.runtime.process.netns import Entry  # noqa: E402
from osmo.runtime.process.sandbox import Sandbox, View, choose, node_network  # noqa: E402


def _work(folder: Path, sandbox: Sandbox) -> Path:
    """``folder/work``, the sandboxed task's own (a pool gives it to the task's uid)."""
    work = folder / "work"
    work.mkdir(exist_ok=True)
    if sandbox.owner is not None:
        os.chown(work, *sandbox.owner)
    return work


def spawn_ms(runtime: ProcessGroups, folder: Path, n: int, sandboxed: bool) -> float:
    """Median ms to start `true` and collect its exit."""
    work = folder / "work"
    work.mkdir(exist_ok=True)
    view = View(hidden=(folder,), readonly=(), writable=(work,), cwd=work) if sandboxed else None
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        handle = runtime.start(["true"], cwd=work, env={"PATH": os.environ["PATH"]}, view=view)
        select.select([handle.exit_fd], [], [])
        runtime.reap(handle)
        runtime.release(handle)
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def flag_costs(sandbox: Sandbox, folder: Path, n: int) -> dict[str, list[float]]:
    """ms per `bwrap ... true` for each part of the sandbox's argv (interleaved, one at a time).

    Without the node's namespaces (``Entry()``): bwrap's own work, as root.
    """
    work = _work(folder, sandbox)
    view = View(hidden=(folder,), readonly=(folder,), writable=(work,), cwd=work)
    bare = dataclasses.replace(sandbox, entry=Entry())
    root = [sandbox.bwrap, *sandbox.system]
    whole = bare.argv(["true"], view)[:-2]
    variants = {
        "system folders alone": root,
        "+ --dev /dev": [*root, "--dev", "/dev"],
        "+ --proc /proc --unshare-pid": [*root, "--proc", "/proc", "--unshare-pid"],
        "+ --tmpfs /tmp": [*root, "--tmpfs", "/tmp"],
        "+ --unshare-ipc --unshare-uts": [*root, "--unshare-ipc", "--unshare-uts"],
        "+ an attempt's view (home hidden, its folders bound)": [*root, *whole[whole.index(
            str(folder)) - 1:]],
        "osmo's whole argv, the node's namespaces not entered": whole,
    }
    times: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(n):
        for name, argv in variants.items():
            t0 = time.perf_counter()
            subprocess.run([*argv, "--", "true"], check=True, stdin=subprocess.DEVNULL)
            times[name].append((time.perf_counter() - t0) * 1e3)
    return times


_BEFORE = ["--cap-drop", "ALL", "--ro-bind", "/", "/", "--dev", "/dev", "--proc", "/proc",
           "--tmpfs", "/tmp", "--unshare-pid", "--die-with-parent"]  # the sandbox before them


def namespace_costs(sandbox: Sandbox, folder: Path, n: int, rounds: int
                    ) -> dict[str, list[float]]:
    """ms per start of `true` (spawn, wait), two at a time, for each way (rounds interleaved).

    Two threads start ``n`` each: on 2 cores the time per start is then what a start costs
    a fan-out, CPU included.
    """
    work = _work(folder, sandbox)
    view = View(hidden=(folder,), readonly=(folder,), writable=(work,), cwd=work)
    bare = dataclasses.replace(sandbox, entry=Entry())
    old = [*_BEFORE, "--tmpfs", str(folder), "--ro-bind", str(folder), str(folder), "--bind",
           str(work), str(work), "--chdir", str(work), "--", "true"]
    ways: dict[str, tuple[list[str], Sandbox | None]] = {
        "before: --ro-bind / /, host network, as root": ([sandbox.bwrap, *old], None),
        "the system view, host network (no node namespaces)": (bare.argv(["true"], view), None),
        "the system view in the node's namespaces (tasks now)": (
            sandbox.argv(["true"], view), sandbox),
    }
    out: dict[str, list[float]] = {name: [] for name in ways}
    for _ in range(rounds):
        for name, (argv, joined) in ways.items():
            out[name].append(two_at_a_time(argv, joined, n))
    return out


def two_at_a_time(argv: list[str], joined: Sandbox | None, n: int) -> float:
    """ms per start of ``argv`` (spawn, wait) when two threads start ``n`` each.

    ``joined``: a sandbox whose node namespaces each start enters (its fds passed).
    """
    def start() -> None:
        for _ in range(n):
            with joined.entered() if joined else contextlib.nullcontext():
                proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, start_new_session=True,
                                        pass_fds=joined.fds if joined else ())
            proc.wait()

    t0 = time.perf_counter()
    pair = [threading.Thread(target=start) for _ in range(2)]
    for thread in pair:
        thread.start()
    for thread in pair:
        thread.join()
    return (time.perf_counter() - t0) * 1e3 / (2 * n)


def sandbox_spawn_limit(n: int, base: str | None = None) -> float:
    """Starts/s of `true` in osmo's own sandbox (an attempt's view, the node's namespaces).

    Two at a time on a fresh node network, no orchestrator: the bare spawn limit of the same
    isolation a sandboxed task gets (bench/peers/compare.py's limit row).
    """
    found = choose("on")
    if found is None:
        raise SystemExit("no working sandbox here (bubblewrap)")
    network = node_network()
    try:
        sandbox = found.joined(network)
        with tempfile.TemporaryDirectory(dir=base) as folder:
            os.chmod(folder, 0o755)
            work = _work(Path(folder), sandbox)
            view = View(hidden=(Path(folder),), readonly=(Path(folder),), writable=(work,),
                        cwd=work)
            return 1000 / two_at_a_time(sandbox.argv(["true"], view), sandbox, n)
    finally:
        network.close()


def network_start_ms(n: int) -> list[float]:
    """ms to make a node's namespaces with outbound connectivity (keeper + slirp4netns)."""
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        network = node_network()
        times.append((time.perf_counter() - t0) * 1e3)
        network.close()
    return times


_HERE = Path(__file__).resolve().parent
_SHARED = ["--ro-bind", "/", "/", "--dev", "/dev", "--proc", "/proc", "--unshare-pid",
           "--die-with-parent", "--"]  # what the prototypes' long-lived sandbox shares


def cpu_ms(argv: Sequence[str], stdin: bytes = b"") -> float:
    """CPU ms (``perf stat`` task-clock) of ``argv`` and every process it starts."""
    done = subprocess.run(["perf", "stat", "-x,", "-e", "task-clock", "--", *argv],
                          input=stdin, capture_output=True, check=True)
    line = next(x for x in done.stderr.decode().splitlines() if "task-clock" in x)
    return float(line.split(",")[0])


def start_cpu(sandbox: Sandbox, folder: Path, n: int, rounds: int) -> dict[str, list[float]]:
    """CPU ms per start of `/bin/true` in each way of sandboxing it (the rounds interleaved).

    bwrap: a shell loop of ``n`` starts (the loop's own fork is in every row: see the first).
    The prototypes: one supervisor serving ``n`` starts, less one serving none.
    """
    home = folder / "cpu-home"
    attempt = home / "a"
    for name in ("work", "output.partial", "files"):
        (attempt / name).mkdir(parents=True, exist_ok=True)
    view = View(hidden=(home,), readonly=(attempt,), cwd=attempt / "work",
                writable=tuple(attempt / name for name in ("work", "output.partial", "files")))
    argv = dataclasses.replace(sandbox, entry=Entry()).argv(["/bin/true"], view)
    drop = argv.index("--cap-drop")
    loops = {"`/bin/true` alone, from a shell loop": ["/bin/true"],
             "osmo's argv, the node's namespaces not entered": argv,
             "the same without --cap-drop ALL": argv[:drop] + argv[drop + 2:]}
    supervisors = {"prototype: long-lived sandbox, Python supervisor": [
        sys.executable, str(_HERE / "sandbox_supervisor.py"), "--home", str(home),
        "--attempt", str(attempt)]}
    compiler = shutil.which("cc")
    if compiler:
        binary = folder / "sandbox_supervisor"
        subprocess.run([compiler, "-O2", "-o", str(binary), str(_HERE / "sandbox_supervisor.c")],
                       check=True)
        supervisors["prototype: long-lived sandbox, C supervisor"] = [
            str(binary), str(home), str(attempt)]
    lines = f"{attempt / 'work'}\t/bin/true\n".encode() * n
    times: dict[str, list[float]] = {name: [] for name in [*loops, *supervisors]}
    for _ in range(rounds):
        for name, command in loops.items():
            loop = f"for i in $(seq {n}); do {shlex.join(command)}; done"
            times[name].append(cpu_ms(["sh", "-c", loop]) / n)
        for name, command in supervisors.items():
            wrapped = [sandbox.bwrap, *_SHARED, *command]
            times[name].append((cpu_ms(wrapped, lines) - cpu_ms(wrapped)) / n)
    return times


def main() -> None:
    """Run every shape ``--runs`` times, alternating off/on, and write the rows."""
    small = quick()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1 if small else 3)
    parser.add_argument("--tasks", type=int, default=20 if small else 300)
    parser.add_argument("--fanout", type=int, default=20 if small else 1000)
    parser.add_argument("--spawns", type=int, default=10 if small else 200)
    parser.add_argument("--flags", type=int, default=5 if small else 100,
                        help="runs of each bwrap variant (the per-flag rows)")
    parser.add_argument("--cpu", type=int, default=20 if small else 300,
                        help="starts per CPU measurement (the CPU rows; 0: skip them)")
    parser.add_argument("--json")
    parser.add_argument("--base", help="folder for the OSMO_HOMEs (default: system temp)")
    args = parser.parse_args()
    found = choose("on")
    assert found is not None
    network = node_network()
    sandbox = found.joined(network)
    rows = []
    spawns: dict[str, list[float]] = {"off": [], "on": []}
    with tempfile.TemporaryDirectory(dir=args.base) as folder:
        os.chmod(folder, 0o755)
        for _ in range(args.runs):
            spawns["off"].append(spawn_ms(ProcessGroups(), Path(folder), args.spawns, False))
            _work(Path(folder), sandbox)
            spawns["on"].append(spawn_ms(ProcessGroups(sandbox), Path(folder), args.spawns,
                                         True))
        flags = flag_costs(sandbox, Path(folder), args.flags)
        namespaces = namespace_costs(sandbox, Path(folder), args.spawns, max(args.runs, 3))
        cpu: dict[str, list[float]] = {}
        if args.cpu and shutil.which("perf") and os.geteuid() == 0:  # the prototypes mount
            cpu = start_cpu(sandbox, Path(folder), args.cpu, max(args.runs, 3))
    network.close()
    starts = network_start_ms(5 if small else 20)
    for mode, values in spawns.items():
        rows.append(row(f"spawn+reap `true`, sandbox {mode}", "ms", values,
                        higher_is_better=False, notes=f"median of {args.spawns} spawns per run"))
    for name, values in flags.items():
        rows.append(row(f"bwrap {name}", "ms", [statistics.median(values)],
                        higher_is_better=False, notes=f"median of {args.flags} runs of `true`"))
    rows.append(row("the node's namespaces: made once per server or worker", "ms", starts,
                    higher_is_better=False,
                    notes="keeper + slirp4netns ready; a network per task would cost each "
                          "task this"))
    for name, values in namespaces.items():
        rows.append(row(f"start of `true`, 2 at a time: {name}", "ms", values,
                        higher_is_better=False,
                        notes=f"spawn + wait, 2 x {args.spawns} per round"))
    for name, values in cpu.items():
        rows.append(row(f"CPU per start: {name}", "ms", values, higher_is_better=False,
                        notes=f"perf stat task-clock, {args.cpu} starts per round"))
    shapes = {f"osmo chain {args.tasks:,} `true` tasks": (chain(args.tasks).build(), args.tasks)}
    if not small:  # the smoke run (bench/run --quick) skips the slowest shape
        shapes[f"osmo fan-out/join {args.fanout:,} tasks reading 3 x 1024 B inputs"] = (
            fan_out_reading(args.fanout, 3, 1024).build(), args.fanout)
    for name, (spec, n) in shapes.items():
        times: dict[str, list[float]] = {"off": [], "on": []}
        for _ in range(args.runs):
            for mode in times:
                options = ServerOptions(sandbox=mode)  # type: ignore[arg-type]
                times[mode].append(run_once(spec, args.base, options))
        for mode, runs in times.items():
            rows.append(row(f"{name}, sandbox {mode}", "tasks/s", [n / t for t in runs],
                            higher_is_better=True,
                            notes=f"submit→COMPLETED median {statistics.median(runs):.2f} s, "
                                  f"{1000 * statistics.median(runs) / n:.2f} ms/task"))
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
