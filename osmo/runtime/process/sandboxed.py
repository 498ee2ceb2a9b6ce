"""The sandboxed process runtime: an attempt's command runs as host processes in bubblewrap.

A node runs its tasks so when a sandbox works there (``--sandbox auto`` or ``on``;
``osmo.runtime.choose``); what the sandbox shows and hides is ``osmo.runtime.process.sandbox``,
the node's shared namespaces ``osmo.runtime.process.netns``. What it owns:

- the view (:func:`attempt_view`): what of osmo's homes an attempt sees: its own folder
  read-only, its ``work/``, ``output.partial/`` and ``files/`` writable, its inputs
  read-only (at the same absolute paths as outside, so the host's paths work unchanged:
  ``HOST_PATHS``, its artifact inputs hard links of the checked blobs); the rest of the homes
  is hidden, and so are the files :meth:`SandboxRuntime.hide` names. A typed task's own code
  folders are shown read-only.
- the hand-over (:func:`hand_over`): a root pool's sandboxed task is ``nobody`` on the host,
  so its writable folders become nobody's.
- its environment's ``XDG_CACHE_HOME`` (:func:`sandbox_env`): the host, ``HOME`` included, is
  read-only there, so libraries that cache under ``~/.cache`` write to ``work/.cache``.
- start, kill, reap, release: bubblewrap spawned in the node's namespaces through
  :class:`~osmo.runtime.process.groups.ProcessGroups` (a setup that failed before the command
  ran marks the handle ``setup_failed``); for a typed task of a type osmo ships, on a root
  osmo, a fork of a sandboxed warm runner given the same view
  (``osmo.runtime.process.warm``).
- exec: the command in a new sandbox over the attempt's own view, in the node's namespaces
  (it sees what the task sees, its network and uid included; a pid namespace of its own).
- port-forward: to a port a process of the task listens on, from inside the node's network
  namespace (never the host's loopback).
- close: the node's namespaces end with the node.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

from osmo.layout import AttemptDirs
from osmo.runtime.api import (
    Attempt,
    Connector,
    ExecCommand,
    Launch,
    Paths,
    PrepareError,
    ProcessHandle,
    Runtime,
)
from osmo.runtime.process import mounts
from osmo.runtime.process.groups import ProcessGroups
from osmo.runtime.process.netns import NodeNetwork
from osmo.runtime.process.ports import listener_connector
from osmo.runtime.process.runtime import ProcessRuntime, image_note, term_env
from osmo.runtime.process.sandbox import Sandbox, View
from osmo.runtime.process.warm import BINDS_MAX, WarmKey, WarmRunners, WarmStart
from osmo.scheduler.types import PrepareAttempt
from osmo.tasktypes.registry import builtin_type

__all__ = ["SANDBOX_PATHS", "SandboxRuntime", "attempt_view", "hand_over", "sandbox_env"]

SANDBOX_PATHS = Paths(linked_inputs=True)
"""The host's paths; the sandbox binds the attempt's folder read-only, inputs included."""
_MAX_INPUT_BINDS = 2000  # each is 3 bubblewrap arguments; bubblewrap takes at most 9,000


class SandboxRuntime(ProcessRuntime):
    """Host processes in bubblewrap, in the node's namespaces (see the module docstring).

    A process runtime whose launches are sandboxed: its description, kill, reap, release
    and clean-up are the process runtime's (over a sandboxing ``ProcessGroups``).

    Args:
        sandbox: a working sandbox that joined ``network``.
        network: the node's namespaces its tasks share (closed with the runtime).
        hidden: folders no task sees (osmo's home).
        note: a line for each attempt's log (what its network lacks); None: nothing to say.
        warm: the node's warm runners: a typed task of a type osmo ships starts as a fork
            of a sandboxed runner, in the view it would have cold (a root osmo only;
            :meth:`warm_key`).
        warm_commands: every command starts so (what the runtime contract checks).
    """

    def __init__(self, sandbox: Sandbox, network: NodeNetwork, *, hidden: Sequence[Path] = (),
                 note: str | None = None, warm: WarmRunners | None = None,
                 warm_commands: bool = False) -> None:
        if warm is not None and (sandbox.owner is None or mounts.unsupported()):
            warm.close()  # a non-root osmo: a runner would share its tasks' uid
            warm = None
        super().__init__(note=note, groups=ProcessGroups(sandbox), warm=warm,
                         warm_commands=warm_commands)
        self.sandbox: Sandbox = sandbox
        self.network = network
        self._hidden = [Path(p).absolute() for p in hidden]
        self._masked: list[Path] = []
        if warm is not None:
            warm.enclose(sandbox, self._hidden)

    def hide(self, path: Path) -> None:
        """Also hide ``path`` from every task started after this call.

        A folder (another osmo home on this host) or a file (a token file the server or
        worker was given; covered only where a shown folder holds it).
        """
        path = Path(path).absolute()
        found = self._hidden
        if path.is_file():
            if not self.sandbox.shows(str(path)):
                return  # a file no shown folder holds is not there anyway
            found = self._masked
        if path not in found:
            found.append(path)

    def paths(self, cmd: PrepareAttempt) -> Paths:
        """The host's paths, inputs linked (:data:`SANDBOX_PATHS`)."""
        return SANDBOX_PATHS

    def prepare(self, launch: Launch, attempt: Attempt, *,
                progress: Callable[[str], None]) -> Launch:
        """``launch`` with its view, its cache folder and, for a root pool, its hand-over.

        Raises:
            PrepareError: the view is more than bubblewrap can take.
            OSError: the hand-over failed.
        """
        task, dirs = attempt.task, attempt.dirs
        code = tuple(Path(p) for p in task.resolved.paths) if task.resolved else ()
        view = attempt_view(dirs, attempt.cmd, tuple(self._hidden), tuple(self._masked), code)
        if self.sandbox.owner is not None:
            hand_over(dirs, self.sandbox.owner)
        notes = tuple(n for n in (self.note, image_note(task)) if n)
        run: View | WarmStart = view
        key = self._sandboxed_key(launch, attempt, view)
        if key is not None and self.warm is not None and self.warm.ready(key):
            run = WarmStart(key, view)
            notes += (f"warm start: forked from a runner of {key.type or 'commands'} (in its "
                      "sandbox)",)
        return replace(launch, run=run, env={**launch.env, **sandbox_env(launch.env, dirs.work)},
                       notes=(*launch.notes, *notes))

    def _sandboxed_key(self, launch: Launch, attempt: Attempt, view: View) -> WarmKey | None:
        """The sandboxed runner ``launch`` starts from (None: it starts cold).

        Only a type osmo ships (or the runner of commands, which imports none): a runner is
        its attempts' parent, with their uid in the node's user namespace, and reads their
        folders once they run a program, so no custom type's import code may run in one.
        """
        key = self._warm_key(launch, attempt)
        if key is None or view.code or len(view.readonly) + len(view.writable) > BINDS_MAX:
            return None
        if key.type and not builtin_type(key.type):
            return None
        return replace(key, sandboxed=True)

    def start(self, launch: Launch) -> ProcessHandle:
        """Spawn bubblewrap over the launch's view, or fork it warm. Raises StartError."""
        if isinstance(launch.run, WarmStart) and self.warm is not None:
            return self.warm.start(launch.run.key, launch)
        return self._groups.start(launch.argv, cwd=launch.cwd, env=launch.env,
                                  view=_view(launch))

    def exec(self, launch: Launch, command: Sequence[str], *, tty: bool,
             term: str | None) -> ExecCommand:
        """``command`` in a new sandbox over the attempt's view, in the node's namespaces.

        With a TTY it is started by ``setsid -w -c`` inside: a session leader in the
        sandbox's own pid namespace, whose shell can then move its jobs to the terminal's
        foreground (a leader outside the namespace is invisible to it).
        """
        inner = ["setsid", "-w", "-c", *command] if tty else list(command)
        return ExecCommand(self.sandbox.argv(inner, _view(launch)), launch.cwd,
                           {**launch.env, **term_env(tty, term)}, ctty=False,
                           pass_fds=self.sandbox.fds, enter=self.sandbox.entered)

    def connector(self, launch: Launch, handle: ProcessHandle) -> Connector:
        """To the ports a process of the task listens on, from inside the node's network."""
        return listener_connector(handle.pid, self.network.socket)

    def close(self) -> None:
        """End its warm runners (and what runs of them), then the node's namespaces."""
        super().close()
        self.network.close()



def _view(launch: Launch) -> View:
    view = launch.run.view if isinstance(launch.run, WarmStart) else launch.run
    if not isinstance(view, View):
        raise TypeError(f"{launch!r} was not prepared by a sandboxed runtime")
    return view


def attempt_view(dirs: AttemptDirs, cmd: PrepareAttempt, hidden: tuple[Path, ...],
                 masked: tuple[Path, ...] = (), code: tuple[Path, ...] = ()) -> View:
    """What a sandboxed attempt sees of the ``hidden`` folders (osmo's homes; the docstring).

    ``cmd.inputs`` are its resolved input references; those that are folders are bound
    read-only (a ``url`` input's download and a copy sit in paths bound read-only already).
    ``masked``: files it must not see; ``code``: folders a typed task imports its type from
    (``TaskSpec.resolved.paths``), shown read-only.

    Raises:
        PrepareError: more input folders outside osmo's store than bubblewrap can bind.
    """
    bound: list[Path] = []
    for path in sorted({Path(ref) for ref in cmd.inputs.values() if ref.startswith("/")}):
        # inputs inside the attempt's folder (its checked links) are bound with it, and a
        # folder inside one already bound needs nothing more (bubblewrap takes ≤ 9,000 args)
        if not path.is_relative_to(dirs.root) and not (bound and path.is_relative_to(bound[-1])):
            bound.append(path)
    if len(bound) > _MAX_INPUT_BINDS:
        raise PrepareError(f"{len(bound):,} input folders outside osmo's store are more than a "
                           f"sandbox can bind ({_MAX_INPUT_BINDS:,}); run it with --sandbox off "
                           "or give it fewer, larger inputs")
    return View(hidden=hidden, readonly=(dirs.root, dirs.url_inputs, *bound),
                writable=(dirs.work, dirs.output_partial, dirs.files), cwd=dirs.work,
                masked=masked, code=code)


def hand_over(dirs: AttemptDirs, owner: tuple[int, int]) -> None:
    """Give a sandboxed attempt of a root pool what it writes (``owner``: its host ids).

    Its ``work/``, ``output.partial/`` and ``files/``, and what preparing wrote in them (its
    files, its credentials' files), become ``owner``'s; its folder and its inputs' folders
    get the search bit for others if they lack it (the umask's), so that it can reach its
    inputs, never the right to list or write them. Inputs themselves (links of blobs) are
    left alone. The pool (root) still reads, ingests and removes all of it.
    """
    uid, gid = owner
    for top in (dirs.work, dirs.output_partial, dirs.files):
        if not top.exists():
            continue
        os.chown(top, uid, gid)
        for folder, subfolders, names in os.walk(top):
            for name in (*subfolders, *names):
                os.lchown(os.path.join(folder, name), uid, gid)
    for reached in (dirs.root, dirs.inputs, dirs.url_inputs):
        try:
            mode = os.stat(reached).st_mode
        except FileNotFoundError:
            continue
        if not mode & 0o001:
            os.chmod(reached, stat.S_IMODE(mode) | 0o001)


def sandbox_env(env: dict[str, str], work: Path) -> dict[str, str]:
    """Variables to add for a sandboxed task whose complete environment is ``env``."""
    return {} if "XDG_CACHE_HOME" in env else {"XDG_CACHE_HOME": str(work / ".cache")}


def _conforms(runtime: SandboxRuntime) -> Runtime:
    """Never called: mypy checks here that SandboxRuntime keeps the runtime contract."""
    return runtime
