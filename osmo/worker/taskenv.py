"""The environment a task starts from: a small documented base, never the worker's own.

A task's environment is built from its spec (``osmo.worker.workdir.prepare`` adds the spec's
``environment``, its credentials' variables and osmo's ``OSMO_*`` variables on top of this
base). The server's or worker's environment is not inherited: it may hold the server's
secrets, ``OSMO_HOME``, cloud credentials or a zenoh config, none of which is the task's.
Like a container, which gets only its image's variables and the spec's.

The base (:data:`BASE_VARIABLES`), copied from the worker's environment when set there:

- ``PATH``, so commands are found as on the worker (``/usr/local/bin:/usr/bin:/bin`` if unset);
- ``HOME``, ``USER``, ``LOGNAME``, ``SHELL``: who runs it (read-only in the sandbox);
- ``LANG``, ``LANGUAGE``, ``LC_ALL``, ``LC_CTYPE``, ``TZ``: how text and time read.

One variable is osmo's own default, unless the worker sets it: ``OMP_WAIT_POLICY=PASSIVE``
(:data:`DEFAULTS`). An OpenMP library (libgomp, under torch and many BLAS builds) otherwise
spins its idle threads for up to a few milliseconds at every barrier; when the machine is
busier than its cores (another task, another program), the spinning threads take the CPU from
the ones doing the work. Measured on 2 cores at load 5, a ResNet-18 training step of 2
threads took 2.2–3.5 s spinning against 0.45–0.61 s passive, and 5–9% longer passive on an
idle machine (``bench/README.md``). A spec that wants spinning sets ``OMP_WAIT_POLICY:
ACTIVE`` in its ``environment`` (a cold start; a warm runner's libraries read it once, at
its import, from this base).

A task that requests cpus (its resource's ``cpu``, or its type's) gets
``OMP_NUM_THREADS`` set to that count (:func:`with_threads`), unless its spec's
``environment`` or the worker sets it: OpenMP and the BLAS libraries under numpy and torch
otherwise start a thread per core of the machine in every task, and two tasks of one cpu
each on a busy node fight over the cores. Ray does the same for its tasks' ``num_cpus``.
A container task's environment is its image's (``Paths.own_env``): the container runtime
sets it there, unless the image does.

``TMPDIR`` is left out on purpose: the default ``/tmp`` is the task's own in the sandbox,
while the worker's ``TMPDIR`` may be shared or read-only there.

In the sandbox, where the host (``HOME`` included) is read-only, ``XDG_CACHE_HOME`` is the
attempt's ``work/.cache`` unless the spec sets it (``osmo.runtime.process.sandboxed``):
libraries that cache under ``~/.cache`` (Hugging Face datasets, torch, matplotlib) then write
there.

Typed tasks get one more variable (``osmo.worker.launch.runner_env``): ``PYTHONPATH`` with the
task type's folders and the folders osmo and its plugins were imported from, so the runner
imports the same osmo as the worker.
"""

from __future__ import annotations

from collections.abc import Mapping

__all__ = ["BASE_VARIABLES", "DEFAULTS", "DEFAULT_PATH", "THREADS", "base_env", "with_threads"]

THREADS = "OMP_NUM_THREADS"
"""Set to a task's cpu request (:func:`with_threads`)."""

BASE_VARIABLES = ("PATH", "HOME", "USER", "LOGNAME", "SHELL",
                  "LANG", "LANGUAGE", "LC_ALL", "LC_CTYPE", "TZ", THREADS)
"""The worker's variables every task gets (when set)."""

DEFAULT_PATH = "/usr/local/bin:/usr/bin:/bin"
"""``PATH`` when the worker has none."""


DEFAULTS = {"OMP_WAIT_POLICY": "PASSIVE"}
"""osmo's own defaults, each replaced by the worker's value when it sets one (see above)."""


def base_env(environ: Mapping[str, str]) -> dict[str, str]:
    """The base of every task's environment, taken from ``environ`` (the worker's)."""
    env = {name: environ[name] for name in BASE_VARIABLES if name in environ}
    env.setdefault("PATH", DEFAULT_PATH)
    for name, value in DEFAULTS.items():
        env[name] = environ.get(name, value)
    return env


def with_threads(env: Mapping[str, str], cpu: int | None) -> dict[str, str]:
    """``env`` with ``OMP_NUM_THREADS`` = ``cpu`` (at least 1) when the task requests cpus.

    A value already in ``env`` (the spec's ``environment``, or the worker's own) is kept.
    """
    out = dict(env)
    if cpu is not None and THREADS not in out:
        out[THREADS] = str(max(1, int(cpu)))
    return out
