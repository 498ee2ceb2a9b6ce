"""osmo side by side with Prefect 3 and Ray on the same DAG shapes (``bench/run --peers``).

Runs with osmo's python. The peers live in their own virtualenv, ``.cache/bench-peers-venv``
(created here with osmo's Python, ``python -m venv``; pinned versions; never osmo's
environment; ``bench_sim.py`` adds osmo's site-packages after its own for the plugins' stacks,
:func:`ensure_sim_path`), and run
as ``prefect_dag.py`` / ``ray_dag.py`` under that venv's python, one process per round, each
printing JSON. See those scripts for each peer's local mode and task bodies.

Shapes: a chain of N and a fan-out/join of N (1 → N-2 → 1), N = 1,000. osmo runs them exactly
as bench_engine.py does (fresh server per run, SDK submit → COMPLETED, tasks are ``true``
processes), once sandboxed (the default) and once with ``--sandbox off``. Each round first
measures the bare spawn limit of osmo's isolation (``bench_sandbox.sandbox_spawn_limit``:
osmo's own bwrap argv in the node's namespaces, 2 at a time, no orchestrator), then runs osmo
(both modes, both shapes), then Prefect, then Ray, so osmo's runs alternate with the peers';
each ratio (osmo ÷ peer, sandboxed osmo ÷ the limit) is taken per round from that round's
runs, and reported as the median (min–max) over rounds. The no-op Python body is measured in
the first round only (its rows have 1 run), to keep ``--peers`` under 15 minutes: Prefect
needs 10–70 s per 1,000-task flow here.

Rows: tasks/s for every system × shape (× body for the peers), each peer's start-up (process
start to a finished warm-up flow), and the ratios, with issue 30's targets: sandboxed osmo
≥ 50% of the same isolation's spawn limit (fan-out and chain), osmo ``--sandbox off`` ≥ 1.0×
Ray (fan-out and chain, ``true`` tasks on both sides); and osmo ≥ 5× Prefect on the fan-out.

Usage: python bench/peers/compare.py [--rounds 3] [--tasks 1000] [--spawns 300]
       [--peers prefect,ray] [--no-install] --json OUT
(``OSMO_BENCH_PEER_LIST=ray`` sets ``--peers`` under ``bench/run --peers``.)
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
sys.path.insert(0, str(HERE.parent))

from bench_engine import chain, fan_out, run_once  # noqa: E402
from bench_sandbox import sandbox_spawn_limit  # noqa: E402
from benchlib import Row, quick, row, write_rows  # noqa: E402

from osmo.options import ServerOptions  # noqa: E402

VENV = REPO / ".cache" / "bench-peers-venv"
PINNED = ["prefect==3.9.1", "ray==2.60.0"]
# prefect 3.9.1 declares certifi>=2026.10.19, newer than any certifi the package index here
# has. Then: resolve 3.9.1's other requirements (via 3.8.8 plus 3.9.1's tighter bounds) and
# install prefect 3.9.1 itself without dependencies; `pip check` names only certifi.
FALLBACK = [["ray==2.60.0", "prefect==3.8.8", "fastapi>=0.139,<0.151",
             "whenever>=0.10.5,<0.12", "ruamel-yaml!=0.19.0"],
            ["--no-deps", "prefect==3.9.1"]]
SHAPES = {"chain": ("chain", chain), "fanout": ("fan-out/join", fan_out)}
BODIES = {"shell": "`true` tasks", "noop": "no-op Python tasks"}
# Issue 30: ≥ 1.0× Ray on equal terms (osmo --sandbox off, `true` in both); ≥ 5× Prefect.
TARGETS = {("prefect", "on", "fanout"): 5.0, ("ray", "off", "fanout"): 1.0,
           ("ray", "off", "chain"): 1.0}
SANDBOX_LIMIT = "peers: limit: start the sandbox alone, `true`, 2 at a time"


def pip(*args: str) -> bool:
    """Run the peer venv's pip; True on success."""
    cmd = [str(VENV / "bin" / "python"), "-m", "pip", "install", "--quiet",
           "--disable-pip-version-check", *args]
    return subprocess.run(cmd).returncode == 0


def ensure_venv() -> str:
    """Create/refresh the peer venv; return how the peers were installed."""
    marker = VENV / "osmo-bench-peers.json"
    python = f"{sys.version_info.major}.{sys.version_info.minor}"
    if marker.exists() and json.loads(marker.read_text()).get("pinned") == PINNED and \
            json.loads(marker.read_text()).get("python") == python:
        return json.loads(marker.read_text())["how"]
    if (VENV / "bin" / "python").exists() and not marker.exists():
        pass  # a half-made venv: pip finishes it below
    elif marker.exists():  # another Python (the sim rows import osmo's own packages): remake
        shutil.rmtree(VENV)
    if not (VENV / "bin" / "python").exists():  # osmo's Python: torch & co. load beside Ray
        subprocess.run([sys.executable, "-m", "venv", str(VENV)], check=True)
    print(f"installing {' '.join(PINNED)} into {VENV}", flush=True)
    if pip(*PINNED):
        how = "pip install " + " ".join(PINNED)
    else:
        print("pinned set does not resolve here; installing prefect 3.9.1 without its "
              "certifi pin (see compare.py)", flush=True)
        for step in FALLBACK:
            if not pip(*step):
                raise SystemExit(f"cannot install the peers: pip install {' '.join(step)}")
        how = "prefect 3.9.1 --no-deps over its other requirements (certifi pin unavailable)"
    marker.write_text(json.dumps({"pinned": PINNED, "how": how, "python": python}))
    return how


def leftovers(pgid: int, private: str) -> list[str]:
    """Processes still alive from a peer run: in its process group or naming its folder."""
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmd = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            if os.getpgid(int(proc.name)) == pgid or private in cmd:
                found.append(f"{proc.name} {cmd[:120]}")
        except (OSError, ProcessLookupError):
            continue
    return found


def run_peer(peer: str, tasks: int, log: Path, bodies: str) -> dict[str, object]:
    """One peer process (warm-up + every shape × body); its JSON, plus any leak found."""
    return run_peer_script(f"{peer}_dag.py", ["--tasks", str(tasks), "--bodies", bodies], log,
                           ray=peer == "ray")


def run_peer_script(script: str, args: list[str], log: Path, *, ray: bool,
                    env: dict[str, str] | None = None, out_dir: bool = False,
                    timeout: float = 600) -> dict[str, Any]:
    """Run ``peers/SCRIPT ARGS --json OUT`` under the peer venv in a private folder.

    Returns its JSON plus ``leaked`` (processes of its group, or naming its folder, found
    alive after it exited: killed). ``ray``: also pass ``--temp-dir`` (Ray's session files);
    ``out_dir``: also pass ``--out`` (a folder for the tasks' outputs), both in the private
    folder, removed after.
    """
    private = tempfile.mkdtemp(prefix=f"osmo-peer-{script[:3]}-", dir="/tmp")  # short: sockets
    out_json = Path(private) / "out.json"
    run_env = dict(os.environ, PREFECT_HOME=private, PREFECT_SERVER_ANALYTICS_ENABLED="false",
                   PREFECT_SERVER_ALLOW_EPHEMERAL_MODE="true", RAY_USAGE_STATS_ENABLED="0",
                   **(env or {}))
    run_env.pop("PREFECT_API_URL", None)
    run_env.pop("OSMO_BENCH_QUICK", None)
    cmd = [str(VENV / "bin" / "python"), str(HERE / script), *args, "--json", str(out_json)]
    if ray:
        cmd += ["--temp-dir", str(Path(private) / "ray")]
    if out_dir:
        cmd += ["--out", str(Path(private) / "out")]
    try:
        with open(log, "a") as out:
            proc = subprocess.Popen(cmd, env=run_env, stdout=out, stderr=out,
                                    start_new_session=True)
            try:
                proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                pass
        leaked = leftovers(proc.pid, private)
        if leaked:  # only processes of the group we started, or under our private folder
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        if proc.returncode != 0 or not out_json.exists():
            raise RuntimeError(f"{script} exited {proc.returncode}; see {log}")
        result: dict[str, Any] = json.loads(out_json.read_text())
        result["leaked"] = leaked
        return result
    finally:
        shutil.rmtree(private, ignore_errors=True)


def ensure_sim_path() -> str:
    """Let the peer venv import the plugins' stacks (torch, mujoco, ...) from osmo's venv.

    A ``.pth`` line in the peer venv appends osmo's site-packages *after* its own, so Ray's
    pinned dependencies win and only what the peer venv lacks comes from osmo's; the Python
    versions match (the venv is made with osmo's). Returns the folder added.
    """
    ours = sysconfig.get_paths()["purelib"]
    theirs = subprocess.run([str(VENV / "bin" / "python"), "-c",
                             "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                            capture_output=True, text=True, check=True).stdout.strip()
    (Path(theirs) / "osmo-bench-sim.pth").write_text(ours + "\n")
    return ours


def tps(tasks: int, seconds: float) -> float:
    """Tasks per second."""
    return tasks / seconds


MODES = {"on": "sandboxed", "off": "--sandbox off"}


def main() -> None:
    """Install the peers, run the rounds, write the rows."""
    small = quick()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=1 if small else 3)
    ap.add_argument("--tasks", type=int, default=20 if small else 1000)
    ap.add_argument("--spawns", type=int, default=20 if small else 300,
                    help="sandbox starts per thread for the same-isolation limit")
    ap.add_argument("--peers", default=os.environ.get("OSMO_BENCH_PEER_LIST", "prefect,ray"))
    ap.add_argument("--no-install", action="store_true")
    ap.add_argument("--json")
    args = ap.parse_args()
    how = "as found" if args.no_install else ensure_venv()
    peers = args.peers.split(",")
    n = args.tasks
    specs = {shape: build(n).build() for shape, (_, build) in SHAPES.items()}
    osmo_runs: dict[tuple[str, str], list[float]] = {(m, s): [] for m in MODES for s in SHAPES}
    limits: list[float] = []  # the sandbox alone, 2 at a time, per round
    before: dict[tuple[str, str, str], list[float]] = {}  # (peer, mode, shape) → osmo tasks/s
    results: dict[str, list[dict[str, object]]] = {p: [] for p in peers}
    failures: list[str] = []
    log = Path(tempfile.gettempdir()) / "osmo-bench-peers.log"
    log.write_text("")
    for r in range(args.rounds):
        limits.append(sandbox_spawn_limit(args.spawns))
        this_round = {}
        for mode in MODES:
            for shape, spec in specs.items():
                options = ServerOptions(sandbox=mode)  # type: ignore[arg-type]
                this_round[mode, shape] = tps(n, run_once(spec, None, options))
                osmo_runs[mode, shape].append(this_round[mode, shape])
                print(f"round {r + 1}: osmo {MODES[mode]} {shape} "
                      f"{this_round[mode, shape]:,.0f} tasks/s", flush=True)
        print(f"round {r + 1}: the sandbox alone, 2 at a time: {limits[-1]:,.0f}/s", flush=True)
        for peer in peers:
            try:
                t0 = time.perf_counter()
                res = run_peer(peer, n, log, "shell,noop" if r == 0 else "shell")
                print(f"round {r + 1}: {peer} {res['version']} in {time.perf_counter() - t0:.0f} s:"
                      f" {json.dumps(res['results'])}", flush=True)
                results[peer].append(res)
                for (mode, shape), value in this_round.items():
                    before.setdefault((peer, mode, shape), []).append(value)
            except RuntimeError as exc:
                failures.append(str(exc))
                print(f"round {r + 1}: {exc}", flush=True)
    rows: list[Row] = [row(SANDBOX_LIMIT, "tasks/s", limits, higher_is_better=True,
                           notes=f"osmo's bwrap argv and the node's namespaces, no orchestrator: "
                                 f"2 threads × {args.spawns} starts of `true`, per round")]
    for (mode, shape), values in osmo_runs.items():
        label = SHAPES[shape][0]
        name = f"peers: osmo {label} {n:,}, `true` tasks, {MODES[mode]}"
        rows.append(row(name, "tasks/s", values, higher_is_better=True,
                        limit_of=SANDBOX_LIMIT if mode == "on" else None,
                        notes="fresh server per run; submit → COMPLETED"))
        if mode == "on":
            rows.append(row(f"peers: osmo {label} {n:,}, sandboxed ÷ the sandbox alone", "%",
                            [100 * v / lim for v, lim in zip(values, limits, strict=True)],
                            higher_is_better=True, target=50.0,
                            notes="per round: that round's osmo run ÷ its start limit of the "
                                  "same isolation (2 at a time)"))
    for peer in peers:
        rows += peer_rows(peer, results[peer], before, n, how)
    write_rows(args.json, rows)
    if failures:
        raise SystemExit("peer runs failed: " + "; ".join(failures))


def peer_rows(peer: str, runs: list[dict[str, Any]],
              before: dict[tuple[str, str, str], list[float]], n: int, how: str) -> list[Row]:
    """One peer's rows: start-up, tasks/s per shape and body, osmo ÷ peer per sandbox mode."""
    if not runs:
        return []
    rows: list[Row] = []
    version = runs[0]["version"]
    leaks = sum(len(x["leaked"]) for x in runs)
    rows.append(row(f"peers: {peer} {version} start-up to a finished warm-up flow", "s",
                    [float(x["startup_s"]) for x in runs], higher_is_better=False,
                    notes=f"installed: {how}; leftover processes after exit: {leaks}"))
    for shape, (label, _) in SHAPES.items():
        for body, body_label in BODIES.items():
            values = [tps(n, float(res["seconds"])) for x in runs for res in x["results"]
                      if res["shape"] == shape and res["body"] == body]
            if not values:
                continue
            rows.append(row(f"peers: {peer} {label} {n:,}, {body_label}", "tasks/s", values,
                            higher_is_better=True))
            if body != "shell":
                continue
            for mode in MODES:
                ratios = [o / p for o, p in zip(before[(peer, mode, shape)], values,
                                                strict=True)]
                rows.append(row(f"peers: osmo ÷ {peer}, {label} {n:,} (`true` tasks on both)"
                                + ("" if mode == "on" else ", osmo --sandbox off"), "×",
                                ratios, higher_is_better=True,
                                target=TARGETS.get((peer, mode, shape)),
                                notes="per round: that round's osmo run ÷ the peer's"))
    return rows


if __name__ == "__main__":
    main()
