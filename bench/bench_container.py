"""Container start cost: what one container task costs at the least, with no orchestrator.

Rows, each the median of N sequential runs (min/max), after one warm-up run. The first four
rows' runs are interleaved round by round (bare, osmo's options, osmo submit, process), so a
busy moment of a shared machine hits all of them alike:

- **limit: bare `podman run --rm` of `true`** — ``podman run --rm --pull=never IMAGE true``
  from this process, until the CLI exits: image already present, default network, no init.
  The floor for any container task here; osmo's container row is compared with it.
- **`podman run` with osmo's options** — the argv ``osmo.runtime.container.run.run_argv``
  makes for a task (``--init``, ``--user``, labels, an input and an output bind, a few
  variables) running ``true``: what osmo's choice of options costs, without the pool.
- **`osmo submit` of a 1-task container workflow** — SDK submit of one task with
  ``image: alpine:3.18`` and ``command: [true]`` to a server with ``--runtime container``,
  until the workflow is COMPLETED (``no_cache``): the whole per-task cost through osmo
  (placement, preparation, image id, the container, output promotion and ingest). Its limit
  is the bare ``podman run`` row (target: ≤ 20 % over it).
- **the same as a process** — the same task without ``image:`` on the same server.
- **200-task container fan-out** — one workflow of 200 such tasks (``--cpus 2``: two at a
  time), wall time per task from submit to COMPLETED.
- **typed tasks in their image, warm and cold** — a 40-task fan-out of a custom type (a
  few milliseconds of Python) with ``image:`` the Python test image: per task, from submit
  to COMPLETED, its attempts forked from a runner container (warm) and each in a container
  of its own (``warm: false``), the two workflows alternated; the runner's start is in the
  first warm round only (one warm-up workflow of each before).

The image is the busybox ``alpine:3.18`` of the container tests (``tests/containers/images.py``,
built offline in well under a second). On machines that need it (FACTS.md: no
CAP_SYS_RESOURCE, hybrid cgroups) the tests' containers.conf is used when ``CONTAINERS_CONF``
is not set. Without podman the script writes no rows (the harness marks it skipped).

Usage: python bench/bench_container.py [--runs 15] [--fanout 200] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from benchlib import quick, row, timed, write_rows  # noqa: E402

import osmo  # noqa: E402
from osmo.options import ServerOptions  # noqa: E402
from osmo.runtime.container import (  # noqa: E402
    DATA_OUTPUT,
    ContainerRun,
    EngineInfo,
    Mount,
    data_input,
    detect_engine,
    run_argv,
    safe_name,
)
from osmo.sdk.connect import start_server, stop_server  # noqa: E402

IMAGE = "alpine:3.18"
LIMIT = "limit: bare `podman run --rm` of `true`"


def bare(env: dict[str, str]) -> None:
    """One bare ``podman run --rm`` of ``true``."""
    subprocess.run(["podman", "run", "--rm", "--pull=never", IMAGE, "true"], check=True,
                   env=env, stdin=subprocess.DEVNULL)


def with_osmo_options(env: dict[str, str], folder: Path, engine: EngineInfo) -> None:
    """``true`` through the argv osmo builds for a task (fresh name each time)."""
    run = ContainerRun(
        image=IMAGE, name=safe_name("bench", str(time.monotonic_ns())), argv=("true",),
        env={"OSMO_TASK": "bench", "OSMO_RETRY": "0"}, user=f"{os.getuid()}:{os.getgid()}",
        labels={"osmo.bench": "container", "osmo.attempt": "bench:true:0"},
        mounts=(Mount(folder / "in", data_input(0)),
                Mount(folder / "out", DATA_OUTPUT, read_only=False)))
    subprocess.run(run_argv(engine, run), check=True, env=env, stdin=subprocess.DEVNULL)


TYPED = """
import json, os
from osmo import task_type

@task_type(version="1")
def small(ctx):
    total = sum(i * i for i in range(20000))
    (ctx.output / "v.json").write_text(json.dumps({"total": total, "pid": os.getpid()}))
"""


def typed_in_image(home: str, rounds: int, tasks: int, image: str, folder: Path
                   ) -> tuple[list[float], list[float]]:
    """Per task ms of a ``tasks``-task fan-out of a typed task in ``image``: warm, cold."""
    (folder / "typedbench.py").write_text(TYPED)

    def spec(warm: bool, index: int) -> Path:
        lines = ["workflow:", f"  name: typed-{'warm' if warm else 'cold'}-{index}", "  tasks:"]
        for i in range(tasks):
            lines += [f"  - name: t{i}", "    type: typedbench:small", f"    image: {image}"]
            lines += [] if warm else ["    warm: false"]
        path = folder / f"typed-{warm}-{index}.yaml"
        path.write_text("\n".join(lines) + "\n")
        return path

    start_server(home, ServerOptions(runtime="container", cpus=2))
    warm_ms: list[float] = []
    cold_ms: list[float] = []
    try:
        with osmo.Client(home=home) as client:
            for index in range(-1, rounds):
                for warm, out in ((True, warm_ms), (False, cold_ms)):
                    t0 = time.perf_counter()
                    info = client.wait(client.submit(spec(warm, index), no_cache=True),
                                       min_interval=0.05)
                    if not info.ok:
                        raise SystemExit(f"typed fan-out ended {info.status.name}")
                    if index >= 0:  # the first of each: images, page cache, the runner
                        out.append((time.perf_counter() - t0) * 1000 / tasks)
    finally:
        stop_server(home)
    return warm_ms, cold_ms


def through_osmo(home: str, runs: int, fanout: int, env: dict[str, str], folder: Path,
                 engine: EngineInfo) -> tuple[list[float], ...]:
    """Per round: bare ms, osmo's options ms, 1-task workflow ms, as a process ms; fan-out."""
    def one(client: osmo.Client, i: int, image: str | None) -> float:
        wf = osmo.Workflow(f"bench-{'box' if image else 'proc'}-{i}")
        wf.task("t", ["true"], image=image)
        t0 = time.perf_counter()
        info = client.wait(client.submit(wf, no_cache=True), min_interval=0.005)
        if not info.ok:
            raise SystemExit(f"bench workflow ended {info.status.name}: {info.task('t').message}")
        return (time.perf_counter() - t0) * 1000

    def ms(fn: Callable[[], object]) -> float:
        return timed(fn, 1)[0] * 1000

    start_server(home, ServerOptions(runtime="container", cpus=2))
    try:
        with osmo.Client(home=home) as client:
            bare(env)  # warm-up: page cache, storage locks
            one(client, -1, IMAGE)
            one(client, -2, None)
            limit: list[float] = []
            options: list[float] = []
            boxed: list[float] = []
            plain: list[float] = []
            for i in range(runs):  # interleaved, as above
                limit.append(ms(lambda: bare(env)))
                options.append(ms(lambda: with_osmo_options(env, folder, engine)))
                boxed.append(one(client, i, IMAGE))
                plain.append(one(client, i, None))
            wf = osmo.Workflow("bench-fanout")
            for i in range(fanout):
                wf.task(f"t{i}", ["true"], image=IMAGE)
            t0 = time.perf_counter()
            info = client.wait(client.submit(wf, no_cache=True), min_interval=0.05)
            per_task = (time.perf_counter() - t0) * 1000 / fanout
            if not info.ok:
                raise SystemExit(f"fan-out ended {info.status.name}")
    finally:
        stop_server(home)
    return limit, options, boxed, plain, [per_task]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=15)
    parser.add_argument("--fanout", type=int, default=200)
    parser.add_argument("--json")
    args = parser.parse_args()
    runs = 2 if quick() else args.runs
    fanout = 4 if quick() else args.fanout
    if shutil.which("podman") is None:
        print("podman is not installed: no container rows")
        write_rows(args.json, [])
        return
    from tests.containers.images import KINDS_PYTHON, ensure_images, write_containers_conf

    with tempfile.TemporaryDirectory(prefix="osmo-bench-container-") as tmp:
        folder = Path(tmp)
        env = dict(os.environ)
        env.setdefault("CONTAINERS_CONF", str(write_containers_conf(folder)))
        ensure_images(env)
        python_image = next(name for name in ensure_images(env, KINDS_PYTHON)
                            if not name.startswith("localhost/"))
        (folder / "in").mkdir()
        (folder / "out").mkdir()
        version = subprocess.run(["podman", "--version"], capture_output=True, text=True,
                                 env=env).stdout.strip()
        engine = detect_engine("podman", env=env)
        os.environ["CONTAINERS_CONF"] = env["CONTAINERS_CONF"]  # the server inherits it
        limit, options, boxed, plain, per_task = through_osmo(
            str(folder / "home"), runs, fanout, env, folder, engine)
        added = [b - bare_ms for b, bare_ms in zip(boxed, limit, strict=True)]
        typed_tasks = 4 if quick() else 40
        warm_ms, cold_ms = typed_in_image(str(folder / "home-typed"), 1 if quick() else 3,
                                          typed_tasks, python_image, folder)
    rows = [row(LIMIT, "ms", limit, higher_is_better=False,
                notes=f"{version}, busybox image, sequential, default network"),
            row("container: `podman run` with osmo's options (run_argv), no pool", "ms", options,
                higher_is_better=False, limit_of=LIMIT,
                notes="--init, --user, labels, 2 binds, 3 variables"),
            row("container: `osmo submit` of a 1-task container workflow (SDK, to COMPLETED)",
                "ms", boxed, higher_is_better=False, limit_of=LIMIT,
                target=1.2 * statistics.median(limit),
                notes="image: alpine:3.18, command: [true], --runtime container, no_cache"),
            row("container: osmo's addition per task (submit minus bare, same round)", "ms",
                added, higher_is_better=False, target=0.2 * statistics.median(limit),
                notes="paired by round; target: 20% of the bare median"),
            row("container: the same task as a process (no image)", "ms", plain,
                higher_is_better=False, notes="same server, interleaved runs"),
            row(f"container: {fanout}-task container fan-out, per task (2 at a time)", "ms",
                per_task, higher_is_better=False,
                notes="one workflow, --cpus 2, wall time submit → COMPLETED / tasks"),
            row(f"container: typed task in its image, {typed_tasks}-task fan-out, per task, "
                "warm (runner container)", "ms", warm_ms, higher_is_better=False,
                notes="custom type, Python test image, --cpus 2; alternated with cold"),
            row(f"container: typed task in its image, {typed_tasks}-task fan-out, per task, "
                "cold (warm: false)", "ms", cold_ms, higher_is_better=False,
                notes="a container (podman run) and a fresh interpreter per attempt")]
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
