"""The commands of docs/how-to/helm.md ("Deploy with Helm") agree with the chart.

Each ``helm install`` there is rendered with the same release, namespace, ``--set`` and ``-f``
values; the ``port-forward`` and ``osmo --server`` lines must name the Service and port that
render produces, and the Secrets the example expects must be the ones the commands create.
"""

from __future__ import annotations

import re
import shlex

import helm_python as helm

from tests.helm.chart import REPO, load_values, render

PAGE = "docs/how-to/helm.md"
TEXT = (REPO / PAGE).read_text()


def commands() -> list[list[str]]:
    """Shell commands of the page's ``sh`` blocks, continuations joined."""
    out = []
    for block in re.findall(r"```sh\n(.*?)```", TEXT, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            if line.strip():
                out.append(shlex.split(line))
    return out


def merge(into: dict, new: dict) -> None:
    """Deep-merge ``new`` into ``into``, as helm layers -f files and --set."""
    for key, value in new.items():
        if isinstance(value, dict) and isinstance(into.get(key), dict):
            merge(into[key], value)
        else:
            into[key] = value


def test_the_page_is_in_the_site() -> None:
    assert "how-to/helm.md" in (REPO / "mkdocs.yml").read_text()


def test_helm_installs_render_and_match_the_port_forward() -> None:
    cmds = commands()
    installs = [c for c in cmds if c[:2] == ["helm", "install"]]
    assert len(installs) == 2
    secrets_created = {c[c.index("generic") + 1] for c in cmds if "generic" in c}
    for argv in installs:
        release, chart = argv[2], argv[3]
        assert (REPO / chart).resolve() == (REPO / "helm" / "osmo").resolve()
        namespace = argv[argv.index("-n") + 1]
        values: dict = {}
        for i, arg in enumerate(argv):
            if arg == "-f":
                merge(values, load_values(REPO / argv[i + 1]))
            if arg == "--set":
                merge(values, helm.parse_set_string(argv[i + 1]))
        out = render(values, release=release, namespace=namespace)
        service = out.get("Service", release)
        mounted = {v["secret"]["secretName"] for o in out.of_kind("Deployment")
                   for v in o["spec"]["template"]["spec"].get("volumes", []) if "secret" in v}
        assert mounted <= secrets_created, "the example mounts Secrets the page never creates"
        ports = {p["port"] for p in service["spec"]["ports"]}
        forwards = [c for c in cmds if "port-forward" in c]
        assert forwards and all(f"svc/{release}" in c for c in forwards)
        assert {int(c[-1].split(":")[0]) for c in forwards} <= ports
    servers = {c[c.index("--server") + 1] for c in cmds if c[:1] == ["osmo"]}
    assert servers == {"tcp/127.0.0.1:7447"}


def test_docker_build_uses_the_extras_argument() -> None:
    builds = [c for c in commands() if c[:2] == ["docker", "build"]]
    assert builds and all("OSMO_EXTRAS=" in " ".join(c) for c in builds)
