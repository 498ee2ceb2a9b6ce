"""Chaos: many seeded trials of SIGKILLs of the server and workers mid-run (``tests/e2e/chaos.py``).

Each trial runs a 12-task DAG (source → 6 → join → 3 → sink; every task checks its inputs byte
for byte) and SIGKILLs, at random moments, the server (``local``: its local pool runs the
tasks) or the server or one of two remote workers (``remote``). It then checks that the
workflow COMPLETED, each task was committed once, each output has its expected digest, no
task saw a partial input, and no process of the trial is left. Trial ``i`` uses seed
``--seed + i``; a failing seed is printed and replays with ``OSMO_CHAOS_SEED``/``--seed``.

Rows: trials, kills, reruns (task starts beyond one per task), lost / duplicated / wrong /
partial / leftover counts (target 0), and recovery times: from a server's SIGKILL until the
next CLI call is answered by a new server (auto-started with the saved options), and from a
worker's SIGKILL until it is back online. Leftover *task* processes of a SIGKILLed remote
worker are counted in their own row: a task dying with its worker is issue 15 item 1, which
was not merged when this was written.

With ``--warm`` (issue 30), every other task of the fan-outs is a typed task and the pool
(remotely, worker w2) runs unsandboxed, so those attempts are forks of warm runners; the
rows then also count the runners found under the killed processes and those that outlived
them (target 0), and the modes are named ``local-warm`` and ``remote-warm``.

Usage: python bench/bench_chaos.py [--trials 50] [--mode local|remote|both] [--kills 3]
       [--seed 1000] [--warm] [--json out.json]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchlib import quick, row, write_rows  # noqa: E402

from tests.e2e.chaos import Trial, TrialResult  # noqa: E402


def run_mode(mode: str, trials: int, kills: int, seed: int, base: Path,
             warm: bool = False) -> list[TrialResult]:
    """Run ``trials`` trials of ``mode`` (with warm runners: ``warm``); print one line each."""
    results = []
    for i in range(trials):
        root = base / f"{mode}{'-warm' * warm}-{seed + i}"
        result = Trial(root, seed + i, mode=mode, kills=kills, warm=warm).run()
        results.append(result)
        problems = result.problems(task_leftovers=mode == "local")
        print(f"  {mode} seed {result.seed}: {result.status}, {len(result.kills)} kill(s) "
              f"{[k for k, _ in result.kills]}, {result.reruns} rerun(s), "
              f"{result.seconds:.1f} s{'; ' + '; '.join(problems) if problems else ''}",
              flush=True)
        if not problems and not result.leftover_tasks:
            shutil.rmtree(root, ignore_errors=True)
    return results


def rows_of(mode: str, results: list[TrialResult], warm: bool = False) -> list[dict]:
    """The protocol rows of one mode's trials."""
    label = f"{mode}-warm" if warm else mode

    def count(attr: str) -> list[float]:
        return [float(len(getattr(r, attr))) for r in results]

    kills = [k for r in results for k in r.kills]
    server = [t for what, t in kills if what == "server"] or [0.0]
    worker = [t for what, t in kills if what != "server"]
    failed = [r.seed for r in results if r.problems(task_leftovers=mode == "local")]
    out = [
        row(f"chaos {label}: trials", "trials", [float(len(results))], higher_is_better=True,
            notes=f"failed seeds: {failed or 'none'}; seeds {results[0].seed}-"
                  f"{results[-1].seed}"),
        row(f"chaos {label}: SIGKILLs per trial", "kills", [float(len(r.kills)) for r in results],
            higher_is_better=True, notes=f"{len(kills)} in all "
                                         f"({len(kills) - len(worker)} server, "
                                         f"{len(worker)} worker)"),
        row(f"chaos {label}: task reruns per trial", "reruns", [float(r.reruns) for r in results],
            higher_is_better=False, notes="starts beyond one per task (killed attempts)"),
        row(f"chaos {label}: attempts lost before they ran, not counted", "attempts",
            [float(r.uncounted) for r in results], higher_is_better=False,
            notes="placed or preparing when the server died: outside the lost-attempt cap"),
        row(f"chaos {label}: tasks lost", "tasks", count("lost"), higher_is_better=False,
            target=0, notes="not COMPLETED, for any reason (the quarantine rule included)"),
        row(f"chaos {label}: attempts failed as quarantined", "attempts", count("quarantined"),
            higher_is_better=False, target=0,
            notes="a SIGKILL landed while the server applied its report (documented rule)"),
        row(f"chaos {label}: tasks committed twice", "tasks", count("duplicated"),
            higher_is_better=False, target=0),
        row(f"chaos {label}: outputs with a wrong digest", "outputs", count("bad_digests"),
            higher_is_better=False, target=0),
        row(f"chaos {label}: partial inputs seen", "tasks", count("partial"),
            higher_is_better=False, target=0),
        row(f"chaos {label}: server/worker processes left", "processes",
            count("leftover_other"), higher_is_better=False, target=0),
        row(f"chaos {label}: task processes left", "processes", count("leftover_tasks"),
            higher_is_better=False, target=0,
            notes=None if mode == "local" else "remote workers: needs issue 15 item 1"),
        row(f"chaos {label}: server back after SIGKILL", "s", server, higher_is_better=False,
            notes="SIGKILL → the next CLI call answered by an auto-started server"),
        row(f"chaos {label}: trial duration", "s", [r.seconds for r in results],
            higher_is_better=False),
    ]
    if warm:
        out += [row(f"chaos {label}: typed attempts forked from warm runners", "attempts",
                    [float(r.warm_starts) for r in results], higher_is_better=True),
                row(f"chaos {label}: warm runners and forks under a killed process", "processes",
                    [float(r.warm_at_kills) for r in results], higher_is_better=True),
                row(f"chaos {label}: warm runners or attempts that outlived their pool",
                    "processes", count("warm_survivors"), higher_is_better=False, target=0)]
    if worker:
        out.append(row(f"chaos {label}: worker back after SIGKILL", "s", worker,
                       higher_is_better=False,
                       notes="SIGKILL → its new process registered (worker.json); includes "
                             "a random 0-0.5 s pause before the restart"))
    return out


def main() -> None:
    """Run the trials and write the rows."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=1 if quick() else 50)
    parser.add_argument("--mode", choices=("local", "remote", "both"), default="both")
    parser.add_argument("--kills", type=int, default=3)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--warm", action="store_true",
                        help="typed tasks on warm runners (unsandboxed pools; see above)")
    parser.add_argument("--base", help="folder for the trials (default: system temp)")
    parser.add_argument("--json")
    args = parser.parse_args()
    base = Path(tempfile.mkdtemp(prefix="osmo-chaos-", dir=args.base))
    print(f"chaos: {args.trials} trial(s) per mode, seeds from {args.seed}, under {base}",
          flush=True)
    started = time.monotonic()
    rows = []
    for mode in (("local", "remote") if args.mode == "both" else (args.mode,)):
        results = run_mode(mode, args.trials, args.kills, args.seed, base, args.warm)
        rows += rows_of(mode, results, args.warm)
    print(f"chaos: {time.monotonic() - started:.0f} s in all; median trial "
          f"{statistics.median(r['median'] for r in rows if r['name'].endswith('duration')):.1f}"
          f" s", flush=True)
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
