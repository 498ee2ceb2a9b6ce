"""``helm lint`` passes on the defaults and the example; bad values are refused with a message.

values.schema.json catches shapes (``helm lint`` and ``helm template`` both report them);
validate.yaml catches what a schema cannot say (a pool name used twice, TLS without
certificates), which ``helm template``/``install`` report and ``helm lint`` only logs.
"""

from __future__ import annotations

import json

import helm_python as helm
import pytest

from tests.helm.chart import EXAMPLES, PEM, lint, load_values, render, tls_values


def test_lint_is_clean_for_the_defaults() -> None:
    assert lint() == []


@pytest.mark.parametrize("example", sorted(p.name for p in EXAMPLES.glob("*.yaml")))
def test_lint_is_clean_for_each_example(example: str) -> None:
    assert lint(load_values(EXAMPLES / example)) == []


def test_lint_is_clean_with_every_feature_on() -> None:
    values = {"router": {"enabled": True}, "auth": {"enabled": True, "password": "pw"},
              "tls": {"enabled": True, "mtls": True, "existingSecret": "a",
                      "client": {"existingSecret": "b"}},
              "server": {"persistence": {"enabled": False}, "plainTcp": False}}
    assert lint(values) == []


# (values, a fragment of the message that must name the problem)
BAD_SHAPES = [
    ({"pools": [{"name": "cpu"}]}, "missing property 'replicas'"),
    ({"pools": [{"replicas": 1}]}, "missing property 'name'"),
    ({"pools": [{"name": "cpu", "replicas": -1}]}, "/pools/0/replicas"),
    ({"pools": [{"name": "cpu", "replicas": "two"}]}, "/pools/0/replicas"),
    ({"pools": [{"name": "CPU_pool", "replicas": 1}]}, "/pools/0/name"),
    ({"pools": [{"name": "cpu", "replicas": 1, "gpu": 1}]}, "'gpu' not allowed"),
    ({"pools": [{"name": "cpu", "replicas": 1, "resources": {"limits": {"cpu": "lots"}}}]},
     "/pools/0/resources/limits/cpu"),
    ({"pools": [{"name": "cpu", "replicas": 1, "resources": {"limit": {"cpu": 1}}}]},
     "'limit' not allowed"),
    ({"pools": [{"name": "cpu", "replicas": 1, "tolerations": [{"key": "a", "operator": "Maybe"}]}]},
     "/pools/0/tolerations/0/operator"),
    ({"server": {"resources": {"requests": {"memory": []}}}}, "/server/resources/requests/memory"),
    ({"server": {"persistence": {"size": "big"}}}, "/server/persistence/size"),
    ({"service": {"port": 70000}}, "/service/port"),
    ({"replicaCount": 2}, "'replicaCount' not allowed"),
    ({"tls": {"enabled": "yes"}}, "/tls/enabled"),
]


@pytest.mark.parametrize(("values", "message"), BAD_SHAPES, ids=[m for _, m in BAD_SHAPES])
def test_schema_rejects_bad_values(values: dict, message: str) -> None:
    problems = lint(values)
    assert any(message in p for p in problems), problems
    with pytest.raises(helm.HelmValuesError, match="schema"):
        render(values)


BAD_COMBINATIONS = [
    ({"pools": [{"name": "a", "replicas": 1}, {"name": "a", "replicas": 2}]}, 'name "a" is used twice'),
    ({"tls": {"enabled": True}}, "set tls.existingSecret, or all of tls.ca"),
    ({"tls": {"enabled": True, "mtls": True, "existingSecret": "s"}}, "tls.client.existingSecret"),
    ({"auth": {"enabled": True}}, "auth.password"),
    ({"server": {"plainTcp": False}}, "needs tls.enabled"),
    ({"router": {"enabled": True}}, "router.enabled needs auth.enabled"),
    ({"router": {"enabled": True}, "auth": {"enabled": True, "password": "pw", "serverUser": "osmo"}},
     "auth.serverUser must differ from auth.user"),
    ({"sandbox": {"hostUsers": True}}, "allows procMount Unmasked only with hostUsers false"),
    # task pods fetching their data log in as auth.podUser: only the router confines it
    ({"auth": {"enabled": True, "password": "pw"}, "pools": [
        {"name": "k", "replicas": 1, "kind": "kubernetes", "kubernetes": {}}]},
     "a kubernetes pool without workClaim needs router.enabled"),
    ({"router": {"enabled": True}, "auth": {"enabled": True, "password": "pw", "podUser": "osmo"},
      "pools": [{"name": "k", "replicas": 1, "kind": "kubernetes", "kubernetes": {}}]},
     "auth.podUser must differ"),
    ({**tls_values(), "tls": {**tls_values()["tls"], "mtls": True, "client": {"cert": PEM, "key": PEM}},
      "pools": [{"name": "k", "replicas": 1, "kind": "kubernetes", "kubernetes": {}}]},
     "tls.mtls with a kubernetes pool without workClaim needs auth.enabled"),
]


@pytest.mark.parametrize(("values", "message"), BAD_COMBINATIONS, ids=[m for _, m in BAD_COMBINATIONS])
def test_template_refuses_inconsistent_values(values: dict, message: str) -> None:
    with pytest.raises(helm.HelmRenderError, match=message):
        render(values)


def _keys(values: dict, prefix: str = "") -> list[str]:
    """Dotted key paths of values.yaml; resources and probe timings count as one value each."""
    out = []
    for key, value in values.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict) and value and not path.endswith(
                ("resources", "seccompProfile", "appArmorProfile", "capabilities")) \
                and ".probes." not in path:
            out.extend(_keys(value, path + "."))
        else:
            out.append(path)
    return out


def test_chart_readme_documents_every_value() -> None:
    from tests.helm.chart import CHART

    readme = (CHART / "README.md").read_text()
    values = load_values(CHART / "values.yaml")
    missing = [k for k in _keys(values) if f"`{k}`" not in readme]
    schema = json.loads((CHART / "values.schema.json").read_text())
    pool_keys = schema["definitions"]["pool"]["properties"]
    missing += [f"pools[].{k}" for k in pool_keys if f"| `{k}` |" not in readme]
    assert missing == []
    top = set(schema["properties"]) - {"global"}
    assert top == set(values), "values.yaml and values.schema.json disagree on top-level keys"
