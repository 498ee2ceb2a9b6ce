"""Process 1 of one test node's pid namespace: its cgroups, its ``slurmd``, and reaping.

``SlurmCluster`` starts each node as ``unshare --pid --fork --mount-proc --kill-child python
node_init.py [--cgroup CONTROLLER=DIR ...] -- slurmd -D -N NAME``. This script then:

- bind-mounts each ``DIR`` (a folder the cluster made inside the host's cgroup v1 hierarchy
  of ``CONTROLLER``) over ``/sys/fs/cgroup/CONTROLLER`` in the node's own mount namespace, so
  this node's ``slurm_<node>/job_<id>`` cgroups cannot meet those of another test cluster on
  the same machine (job ids start at 1 in each of them);
- runs ``slurmd`` and reaps every process that ends in the namespace (``slurmstepd`` forks
  twice, so its parent becomes this process, not ``slurmd``);
- passes SIGTERM and SIGINT on to ``slurmd`` and exits when it does, with its status.

When this process dies, the kernel kills every other process of the namespace: that is how
the cluster makes a node fail (SIGKILL to ``unshare``, whose ``--kill-child`` kills this).
It only uses the standard library and must not import osmo or the tests.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys


def _bind_cgroups(pairs: list[str]) -> None:
    for pair in pairs:
        controller, _, folder = pair.partition("=")
        target = f"/sys/fs/cgroup/{controller}"
        subprocess.run(["mount", "--bind", folder, target], check=True)


def _run(argv: list[str]) -> int:
    child = os.posix_spawnp(argv[0], argv, os.environ)

    def forward(signum: int, _frame: object) -> None:
        try:
            os.kill(child, signum)
        except ProcessLookupError:
            pass

    signal.signal(signal.SIGTERM, forward)
    signal.signal(signal.SIGINT, forward)
    while True:
        try:
            pid, status = os.wait()
        except ChildProcessError:  # cannot happen while the child lives; be safe
            return 1
        if pid == child:
            return os.waitstatus_to_exitcode(status) & 0xFF


def main(args: list[str]) -> int:
    """Bind the cgroups named before ``--``, run the command after it; its exit status."""
    split = args.index("--")
    options, argv = args[:split], args[split + 1:]
    cgroups = [options[i + 1] for i, opt in enumerate(options) if opt == "--cgroup"]
    _bind_cgroups(cgroups)
    return _run(argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
