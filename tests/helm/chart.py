"""Render and lint the osmo Helm chart offline, for the chart tests.

Helm comes from PyPI's ``helm-python-sdk`` (Helm v4's Go SDK behind a C ABI, loaded with
ctypes): ``lint`` is ``helm lint`` and :func:`render` is ``helm template``, with no helm binary,
cluster or network. Rendered manifests are returned as plain dicts for assertions and as YAML
files for ``kubernetes-validate``.
"""

from __future__ import annotations

import base64
import copy
import json
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import helm_python as helm
import yaml
import zenoh

from osmo.config import free_port

REPO = Path(__file__).resolve().parents[2]
CHART = REPO / "helm" / "osmo"
EXAMPLES = REPO / "helm" / "examples"
RELEASE = "demo"
NAMESPACE = "robots"
FULLNAME = "demo-osmo"

helm.disable_logging()  # lint mode logs each template `fail`; the tests read the report instead

# A CA, certificate and key are only stored and mounted by the chart, never parsed: any PEM-ish
# text proves the wiring.
PEM = "-----BEGIN CERTIFICATE-----\nMIIB\n-----END CERTIFICATE-----\n"


@dataclass(frozen=True)
class Rendered:
    """The objects one ``helm template`` produced, and the NOTES text."""

    objects: list[dict[str, Any]]
    notes: str

    def get(self, kind: str, name: str) -> dict[str, Any]:
        """The one object of ``kind`` called ``name``; fails the test if absent."""
        found = [o for o in self.objects if o["kind"] == kind and o["metadata"]["name"] == name]
        assert len(found) == 1, f"{kind}/{name}: found {len(found)} in {self.names()}"
        return found[0]

    def of_kind(self, kind: str) -> list[dict[str, Any]]:
        """Every object of ``kind``."""
        return [o for o in self.objects if o["kind"] == kind]

    def names(self) -> list[str]:
        """``Kind/name`` of every object, for failure messages."""
        return [f"{o['kind']}/{o['metadata']['name']}" for o in self.objects]


def load_values(path: Path) -> dict[str, Any]:
    """A values file as a dict."""
    values: dict[str, Any] = yaml.safe_load(path.read_text()) or {}
    return values


def render(values: dict[str, Any] | None = None, release: str = RELEASE,
           namespace: str = NAMESPACE) -> Rendered:
    """``helm template RELEASE helm/osmo -n NAMESPACE`` with ``values`` over the chart defaults.

    Raises:
        helm_python.HelmValuesError: the values break values.schema.json.
        helm_python.HelmRenderError: a template failed (e.g. a ``fail`` check in validate.yaml).
    """
    with helm.Chart.load(CHART) as chart:
        manifests = chart.render(values=copy.deepcopy(values or {}), name=release,
                                 namespace=namespace, is_install=True)
    objects: list[dict[str, Any]] = []
    notes = ""
    for path, text in sorted(manifests.items()):
        if path.endswith("NOTES.txt"):
            notes = text
            continue
        objects.extend(doc for doc in yaml.safe_load_all(text) if doc)
    return Rendered(objects, notes)


def lint(values: dict[str, Any] | None = None) -> list[str]:
    """``helm lint --strict``: the warnings and errors it reports (empty = clean)."""
    report = helm.lint(CHART, copy.deepcopy(values or {}), strict=True)
    messages = [f"{m['path']}: {m['error']}" for m in report["messages"] if m["severity"] >= 2]
    return messages + list(report["errors"])


def container(pod_owner: dict[str, Any], name: str) -> dict[str, Any]:
    """The container called ``name`` in a Deployment's or StatefulSet's pod template."""
    found = [c for c in pod_owner["spec"]["template"]["spec"]["containers"] if c["name"] == name]
    assert len(found) == 1, f"no container {name!r}"
    return found[0]


def env(c: dict[str, Any]) -> dict[str, Any]:
    """A container's env as name → value (or valueFrom)."""
    return {e["name"]: e.get("value", e.get("valueFrom")) for e in c.get("env", [])}


def flag(args: list[str], name: str) -> list[str]:
    """Every value given to ``--name`` in an argument list."""
    return [args[i + 1] for i, a in enumerate(args[:-1]) if a == name]


def mounts(c: dict[str, Any]) -> dict[str, str]:
    """A container's volume mounts as volume name → mount path."""
    return {m["name"]: m["mountPath"] for m in c.get("volumeMounts", [])}


def volumes(pod_owner: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """A pod template's volumes by name."""
    return {v["name"]: v for v in pod_owner["spec"]["template"]["spec"].get("volumes", [])}


def tls_values(**extra: Any) -> dict[str, Any]:
    """Values turning on chart-created TLS (and anything in ``extra``)."""
    values: dict[str, Any] = {"tls": {"enabled": True, "ca": PEM, "cert": PEM, "key": PEM}}
    values.update(extra)
    return values


ROUTER = {"router": {"enabled": True}, "auth": {"enabled": True, "password": "pw"}}
"""Values with the standalone router (which needs user/password auth)."""


def auth_secret(values: dict[str, Any]) -> dict[str, str]:
    """The rendered zenoh auth Secret's keys, decoded."""
    data = render(values).get("Secret", f"{FULLNAME}-auth")["data"]
    return {k: base64.b64decode(v).decode() for k, v in data.items()}


def router_config(values: dict[str, Any]) -> dict[str, Any]:
    """The rendered ``router.json5`` (plain JSON)."""
    files = render(values).get("ConfigMap", f"{FULLNAME}-zenoh")["data"]
    config: dict[str, Any] = json.loads(files["router.json5"])
    return config


def local_router_config(config: dict[str, Any], dictionary: str, folder: Path) -> tuple[
        dict[str, Any], str]:
    """``config`` listening on a free loopback port with ``dictionary`` written in
    ``folder``; the config and its endpoint."""
    port = free_port(0)
    (folder / "dictionary").write_text(dictionary)
    config = json.loads(json.dumps(config))
    config["listen"]["endpoints"] = [f"tcp/127.0.0.1:{port}"]
    config["transport"]["auth"]["usrpwd"]["dictionary_file"] = str(folder / "dictionary")
    return config, f"tcp/127.0.0.1:{port}"


@contextmanager
def zenoh_router(config: dict[str, Any], dictionary: str, folder: Path) -> Iterator[str]:
    """A real zenoh router in this process running the rendered ``config`` on loopback, with
    the password ``dictionary``; yields its endpoint."""
    config, endpoint = local_router_config(config, dictionary, folder)
    session = zenoh.open(zenoh.Config.from_json5(json.dumps(config)))
    try:
        yield endpoint
    finally:
        session.close()


def zenoh_login(endpoint: str, user: str, password: str) -> zenoh.Session:
    """A zenoh client session logged in to ``endpoint`` as ``user``."""
    return zenoh.open(zenoh.Config.from_json5(json.dumps({
        "mode": "client", "connect": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"user": user, "password": password}}}})))
