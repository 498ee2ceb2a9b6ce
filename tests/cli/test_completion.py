"""Shell completion (``osmo completion bash|zsh|fish``), driven through the real shells.

Each shell loads the generated script and completes through the real CLI (an ``osmo`` on
PATH that runs this tree's code): verbs from the argument parser, workflow ids and task names
from a running server, and nothing, quickly, with no server or a server that never answers;
completing never starts a server.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import REPO, Osmo, write


@pytest.fixture
def shell_env(osmo: Osmo, tmp_path: Path) -> dict[str, str]:
    """The environment of a shell whose ``osmo`` is this tree's CLI on ``osmo``'s home."""
    bin_dir = tmp_path / "bin"
    write(bin_dir / "osmo", f'#!/bin/sh\nexec {sys.executable} -m osmo "$@"\n').chmod(0o755)
    return dict(osmo.env, PATH=f"{bin_dir}:{os.environ['PATH']}", PYTHONPATH=str(REPO))


def _need(shell: str) -> None:
    """Skip without ``shell`` (``./dev test`` installs it, and fails a skip: OSMO_NO_SKIPS)."""
    if shutil.which(shell) is None:
        pytest.skip(f"{shell} is not installed (Debian package {shell}; ./dev test installs it)")


def _shell(argv: list[str], env: dict[str, str]) -> str:
    proc = subprocess.run(argv, env=env, cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc.stdout


def _bash_complete(line: str, env: dict[str, str]) -> list[str]:
    """What bash's completion function for ``osmo`` offers at the end of ``line``."""
    words = line.split() + ([""] if line.endswith(" ") else [])
    script = f"""
source <(osmo completion bash)
COMP_LINE={line!r}; COMP_POINT=${{#COMP_LINE}}; COMP_TYPE=9
COMP_WORDS=({" ".join(repr(w) for w in words)}); COMP_CWORD={len(words) - 1}
_python_argcomplete osmo {words[-1]!r} {words[-2]!r}
printf '%s\\n' "${{COMPREPLY[@]}}"
"""
    return [w.strip() for w in _shell(["bash", "-c", script], env).splitlines() if w.strip()]


def test_bash_loads_the_script(shell_env: dict[str, str]) -> None:
    out = _shell(["bash", "-c", "source <(osmo completion bash); complete -p osmo"], shell_env)
    assert out.strip().endswith("-F _python_argcomplete osmo"), out


def test_zsh_loads_the_script(shell_env: dict[str, str], tmp_path: Path) -> None:
    _need("zsh")
    script = write(tmp_path / "osmo.zsh", _shell(["osmo", "completion", "zsh"], shell_env))
    _shell(["zsh", "-n", str(script)], shell_env)  # parses
    env = dict(shell_env, ZDOTDIR=str(tmp_path))  # no user rc files
    out = _shell(["zsh", "-c", 'autoload -U compinit && compinit -u -D && '
                  'eval "$(osmo completion zsh)" && whence -w _python_argcomplete && '
                  'print -r -- $_comps[osmo]'], env)
    assert out.split() == ["_python_argcomplete:", "function", "_python_argcomplete"], out


def test_fish_completes_verbs_through_the_script(shell_env: dict[str, str]) -> None:
    _need("fish")
    out = _shell(["fish", "--no-config", "-c",
                  "osmo completion fish | source; complete -C 'osmo que'"], shell_env)
    assert [w.split("\t")[0] for w in out.splitlines()] == ["query"], out


def test_bash_completes_verbs_options_and_subverbs(shell_env: dict[str, str]) -> None:
    assert _bash_complete("osmo que", shell_env) == ["query"]
    assert "--reuse" in _bash_complete("osmo submit --re", shell_env)
    assert sorted(_bash_complete("osmo completion ", shell_env)) == ["bash", "fish", "zsh"]


def test_workflow_ids_and_task_names_come_from_the_server(osmo: Osmo,
                                                          shell_env: dict[str, str],
                                                          tmp_path: Path) -> None:
    spec = write(tmp_path / "wf.yaml", """
workflow:
  name: complete-me
  tasks:
  - {name: first-task, command: ["true"]}
  - {name: second-task, command: ["true"]}
""")
    ids = [osmo.submit(spec, "--wait") for _ in range(2)]
    assert sorted(_bash_complete("osmo query ", shell_env)) == sorted(ids)
    assert _bash_complete(f"osmo query {ids[1]}", shell_env) == [ids[1]]
    assert sorted(_bash_complete(f"osmo logs {ids[0]} -t ", shell_env)) == [
        "first-task", "second-task"]
    assert sorted(_bash_complete(f"osmo workflow cancel {ids[0]} ", shell_env)) == sorted(ids)


def test_no_server_completes_nothing_and_starts_none(osmo: Osmo,
                                                     shell_env: dict[str, str]) -> None:
    assert _bash_complete("osmo query ", shell_env) == []
    assert osmo.server_pid() is None and not (osmo.home / "server.json").exists()


def test_a_server_that_never_answers_does_not_hang_completion(shell_env: dict[str, str]) -> None:
    with socket.socket() as silent:  # accepts connections, never says a word
        silent.bind(("127.0.0.1", 0))
        silent.listen()
        env = dict(shell_env, OSMO_SERVER=f"tcp/127.0.0.1:{silent.getsockname()[1]}")
        started = time.monotonic()
        assert _bash_complete("osmo query ", env) == []
        assert time.monotonic() - started < 15
