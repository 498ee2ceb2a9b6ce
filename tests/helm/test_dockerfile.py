"""The Dockerfile's shape, checked by reading it (``test_dockerfile_build.py`` builds it).

A small parser reads instructions (comments dropped, ``\\`` continuations joined) into stages,
then the tests check what the chart relies on: a builder and a slim Python 3.12 runtime stage,
the ``OSMO_EXTRAS`` build argument reaching ``pip install``, a non-root numeric user,
``OSMO_HOME=/var/lib/osmo`` and ``osmo`` as the entrypoint; and that .dockerignore keeps what the
build copies and drops local state.
"""

from __future__ import annotations

import fnmatch
import json
import re
from dataclasses import dataclass, field

from tests.helm.chart import REPO

DOCKERFILE = REPO / "Dockerfile"


@dataclass
class Stage:
    """One ``FROM`` and the instructions under it."""

    base: str
    name: str
    instructions: list[tuple[str, str]] = field(default_factory=list)

    def args(self, keyword: str) -> list[str]:
        return [a for k, a in self.instructions if k == keyword]


def parse(text: str) -> tuple[dict[str, str], list[Stage]]:
    """Global ``ARG`` defaults and the stages of a Dockerfile."""
    lines: list[str] = []
    pending = ""
    for raw in text.splitlines():
        if raw.lstrip().startswith("#") or not raw.strip():
            continue
        if raw.rstrip().endswith("\\"):
            pending += raw.rstrip()[:-1] + " "
            continue
        lines.append(pending + raw)
        pending = ""
    global_args: dict[str, str] = {}
    stages: list[Stage] = []
    for line in lines:
        keyword, _, rest = line.strip().partition(" ")
        keyword, rest = keyword.upper(), rest.strip()
        if keyword == "FROM":
            m = re.fullmatch(r"(?:--platform=\S+\s+)?(\S+)(?:\s+AS\s+(\S+))?", rest, re.IGNORECASE)
            assert m, f"cannot parse FROM {rest}"
            stages.append(Stage(m.group(1), m.group(2) or str(len(stages))))
        elif not stages:
            assert keyword == "ARG", f"{keyword} before the first FROM"
            name, _, default = rest.partition("=")
            global_args[name] = default
        else:
            stages[-1].instructions.append((keyword, rest))
    return global_args, stages


def resolve(value: str, args: dict[str, str]) -> str:
    return re.sub(r"\$\{?(\w+)\}?", lambda m: args.get(m.group(1), m.group(0)), value)


GLOBAL_ARGS, STAGES = parse(DOCKERFILE.read_text())
RUNTIME = STAGES[-1]


def test_multi_stage_on_python_312_slim() -> None:
    assert len(STAGES) >= 2
    assert [resolve(s.base, GLOBAL_ARGS) for s in STAGES] == ["python:3.12-slim"] * len(STAGES)
    builder = STAGES[0].name
    copies = RUNTIME.args("COPY")
    assert any(c.startswith(f"--from={builder} ") for c in copies), copies
    assert not any(k == "COPY" and not a.startswith("--from=") for k, a in RUNTIME.instructions), \
        "the runtime stage takes only the built virtualenv, never the source tree"


def test_osmo_extras_build_arg_reaches_pip_install() -> None:
    builder = STAGES[0]
    assert "OSMO_EXTRAS=" in builder.args("ARG")  # declared in the stage, empty = core
    runs = " ".join(builder.args("RUN"))
    assert re.search(r"\$\{?OSMO_EXTRAS\}?", runs)
    assert "pip install" in runs


def test_runtime_runs_as_a_numeric_non_root_user() -> None:
    users = RUNTIME.args("USER")
    assert users, "the runtime stage must set USER"
    stage_args = dict(a.partition("=")[::2] for a in RUNTIME.args("ARG"))
    user = resolve(users[-1], stage_args).split(":")[0]
    assert user.isdigit() and int(user) != 0, users[-1]
    assert stage_args.get("OSMO_UID") == "10001"  # the chart's podSecurityContext.runAsUser


def test_runtime_environment_and_entrypoint() -> None:
    env = " ".join(RUNTIME.args("ENV"))
    assert "OSMO_HOME=/var/lib/osmo" in env
    assert "/opt/osmo/bin" in env
    assert json.loads(RUNTIME.args("ENTRYPOINT")[-1]) == ["osmo"]


def test_dockerignore_keeps_the_build_inputs_and_drops_local_state() -> None:
    rules = [r.strip() for r in (REPO / ".dockerignore").read_text().splitlines()
             if r.strip() and not r.startswith("#")]

    def ignored(path: str) -> bool:
        verdict = False
        for rule in rules:
            negate = rule.startswith("!")
            pattern = rule.lstrip("!").rstrip("/").removeprefix("**/")
            if fnmatch.fnmatch(path, pattern) or fnmatch.fnmatch(path.split("/")[-1], pattern) \
                    or path.startswith(pattern + "/"):
                verdict = not negate
        return verdict

    sources = [s for line in STAGES[0].args("COPY") for s in line.split()[:-1]]
    assert sources
    for source in sources:
        assert (REPO / source).exists(), source
        assert not ignored(source), f"{source} is copied but .dockerignore drops it"
    assert not ignored("osmo/cli/main.py")
    for local in (".venv", ".git", ".cache", "tests/conftest.py", "osmo/__pycache__/x.pyc"):
        assert ignored(local), local


def test_runtime_installs_the_sandbox_whatever_the_extra_packages() -> None:
    """Tasks run in bubblewrap, in the node's network namespace whose outbound network is
    slirp4netns's (entered with util-linux's setpriv/nsenter): the image installs them in
    every build (issue #26: it had no bwrap, so ``--sandbox auto`` ran every
    task unsandboxed beside the state store, and ``--sandbox on`` could never start)."""
    installs = [run for run in RUNTIME.args("RUN") if "apt-get install" in run]
    assert len(installs) == 1, installs
    words = installs[0].split()
    assert {"bubblewrap", "slirp4netns", "util-linux"} <= set(words), installs[0]
    assert "--no-install-recommends" in words
    assert "if" not in words, "the sandbox must not depend on OSMO_APT_PACKAGES being set"
    assert re.search(r"\$\{?OSMO_APT_PACKAGES\}?", installs[0])  # the extras still go here
    assert "rm -rf /var/lib/apt/lists/*" in installs[0]
    assert "bwrap --version" in installs[0] and "slirp4netns --version" in installs[0]
