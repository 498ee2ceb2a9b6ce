"""What the process sandbox (bubblewrap) costs per task, and what skipping input copies saves.

Rows:

- spawn + reap of `true` through ``ProcessRuntime``, unsandboxed (with its parent-death
  ``preexec_fn``) and in the sandbox, in ms per spawn (one at a time);
- what each part of the sandbox's argv costs: `bwrap ... true` with ``--ro-bind / /`` alone,
  then one part added (``--dev /dev``; the alternative of a tmpfs ``/dev`` with only the
  device nodes bound; ``--proc`` with ``--unshare-pid``; the private ``/tmp``; an attempt's
  view), and osmo's whole argv, in ms per run (one at a time, the variants interleaved);
- CPU per start (``perf stat`` task-clock of the starter and every process it starts; as
  root, with ``perf`` installed): osmo's argv, the same without ``--cap-drop ALL``, and the
  issue 16 prototypes of one long-lived sandbox that makes a fresh mount and pid namespace
  per task (``sandbox_supervisor.py``, and its C twin when ``cc`` is installed);
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
import os
import select
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_engine import chain, run_once  # noqa: E402
from bench_inputs import fan_out_reading  # noqa: E402
from benchlib import quick, row, write_rows  # noqa: E402

from osmo.options import ServerOptions  # noqa: E402
from osmo.runtime import ProcessRuntime  # noqa: E402
from osmo.runtime.sandbox import Sandbox, View, choose  # noqa: E402


def spawn_ms(runtime: ProcessRuntime, folder: Path, n: int, sandboxed: bool) -> float:
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


_NODES = ("null", "zero", "full", "random", "urandom", "tty")  # what bwrap's --dev binds


def flag_costs(sandbox: Sandbox, folder: Path, n: int) -> dict[str, list[float]]:
    """ms per `bwrap ... true` for each part of the sandbox's argv (interleaved, one at a time)."""
    work = folder / "work"
    work.mkdir(exist_ok=True)
    view = View(hidden=(folder,), readonly=(folder,), writable=(work,), cwd=work)
    root = [sandbox.bwrap, "--ro-bind", "/", "/"]
    tmpfs_dev = ["--tmpfs", "/dev", "--tmpfs", "/dev/shm"]
    for node in _NODES:
        tmpfs_dev += ["--dev-bind", f"/dev/{node}", f"/dev/{node}"]
    whole = sandbox.argv(["true"], view)[:-2]
    variants = {
        "--ro-bind / / alone": root,
        "+ --dev /dev": [*root, "--dev", "/dev"],
        "+ a tmpfs /dev with its 6 nodes bound (instead of --dev)": [*root, *tmpfs_dev],
        "+ --proc /proc --unshare-pid": [*root, "--proc", "/proc", "--unshare-pid"],
        "+ --tmpfs /tmp": [*root, "--tmpfs", "/tmp"],
        "+ an attempt's view (home hidden, its folders bound)": [*root, *whole[whole.index(
            "--die-with-parent") + 1:]],
        "osmo's whole argv": whole,
    }
    times: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(n):
        for name, argv in variants.items():
            t0 = time.perf_counter()
            subprocess.run([*argv, "--", "true"], check=True, stdin=subprocess.DEVNULL)
            times[name].append((time.perf_counter() - t0) * 1e3)
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
    argv = sandbox.argv(["/bin/true"], view)
    drop = argv.index("--cap-drop")
    loops = {"`/bin/true` alone, from a shell loop": ["/bin/true"], "osmo's argv": argv,
             "osmo's argv without --cap-drop ALL (before s2)": argv[:drop] + argv[drop + 2:]}
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
    sandbox = choose("on")
    rows = []
    spawns: dict[str, list[float]] = {"off": [], "on": []}
    with tempfile.TemporaryDirectory(dir=args.base) as folder:
        for _ in range(args.runs):
            spawns["off"].append(spawn_ms(ProcessRuntime(), Path(folder), args.spawns, False))
            spawns["on"].append(spawn_ms(ProcessRuntime(sandbox), Path(folder), args.spawns,
                                         True))
        flags = flag_costs(sandbox, Path(folder), args.flags)
        cpu: dict[str, list[float]] = {}
        if args.cpu and shutil.which("perf") and os.geteuid() == 0:  # the prototypes mount
            cpu = start_cpu(sandbox, Path(folder), args.cpu, max(args.runs, 3))
    for mode, values in spawns.items():
        rows.append(row(f"spawn+reap `true`, sandbox {mode}", "ms", values,
                        higher_is_better=False, notes=f"median of {args.spawns} spawns per run"))
    for name, values in flags.items():
        rows.append(row(f"bwrap {name}", "ms", [statistics.median(values)],
                        higher_is_better=False, notes=f"median of {args.flags} runs of `true`"))
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
