"""Container start cost: what one container task costs at the least, with no orchestrator.

Rows, each the median of N sequential runs (min/max; the two rows' runs interleaved), after
one warm-up run:

- **limit: bare `podman run --rm` of `true`** — ``podman run --rm --pull=never IMAGE true``
  from this process, until the CLI exits: image already present, default network, no init.
  The floor for any container task here; osmo's container row is compared with it.
- **`podman run` with osmo's options** — the argv ``osmo.runtime.container_run.run_argv``
  makes for a task (``--init``, ``--user``, labels, an input and an output bind, a few
  variables) running ``true``: what osmo's choice of options costs, without the pool.

The image is the busybox ``alpine:3.18`` of the container tests (``tests/containers/images.py``,
built offline in well under a second). On machines that need it (FACTS.md: no
CAP_SYS_RESOURCE, hybrid cgroups) the tests' containers.conf is used when ``CONTAINERS_CONF``
is not set. Without podman the script writes no rows (the harness marks it skipped).

Usage: python bench/bench_container.py [--runs 15] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from benchlib import quick, row, timed, write_rows  # noqa: E402

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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=15)
    parser.add_argument("--json")
    args = parser.parse_args()
    runs = 2 if quick() else args.runs
    if shutil.which("podman") is None:
        print("podman is not installed: no container rows")
        write_rows(args.json, [])
        return
    from tests.containers.images import ensure_images, write_containers_conf

    with tempfile.TemporaryDirectory(prefix="osmo-bench-container-") as tmp:
        folder = Path(tmp)
        env = dict(os.environ)
        env.setdefault("CONTAINERS_CONF", str(write_containers_conf(folder)))
        ensure_images(env)
        (folder / "in").mkdir()
        (folder / "out").mkdir()
        version = subprocess.run(["podman", "--version"], capture_output=True, text=True,
                                 env=env).stdout.strip()
        engine = detect_engine("podman", env=env)
        bare(env)  # warm-up: page cache, storage locks
        limit, osmo = [], []
        for _ in range(runs):  # interleaved, so a busy moment of the machine hits both
            limit += timed(lambda: bare(env), 1)
            osmo += timed(lambda: with_osmo_options(env, folder, engine), 1)
        limit, osmo = [t * 1000 for t in limit], [t * 1000 for t in osmo]
    rows = [row(LIMIT, "ms", limit, higher_is_better=False,
                notes=f"{version}, busybox image, sequential, default network"),
            row("container: `podman run` with osmo's options (run_argv), no pool", "ms", osmo,
                higher_is_better=False, limit_of=LIMIT,
                notes="--init, --user, labels, 2 binds, 3 variables")]
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
