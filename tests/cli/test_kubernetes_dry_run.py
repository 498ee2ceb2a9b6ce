"""``osmo submit SPEC --dry-run --runtime kubernetes``: the objects a workflow's attempts would
create as pods, printed without a cluster, each valid against the Kubernetes 1.33 schema and
the API server's rules; a group gets its Service (and its PodGroup under a gang scheduler)."""

from __future__ import annotations

import json
from pathlib import Path

from tests.conftest import Osmo
from tests.k8s.validation import SchemaCheck, check

TUTORIALS = Path(__file__).parent.parent / "containers" / "osmo_tutorials"
KINDS = {"Pod": "pods", "Secret": "secrets", "Service": "services"}


def test_the_group_tutorial_as_objects(tmp_path: Path) -> None:
    pool = tmp_path / "pool.json"
    pool.write_text(json.dumps({"namespace": "robots", "gang": "volcano"}))
    r = Osmo(tmp_path / "home")("submit", str(TUTORIALS / "group_tasks_communication.yaml"),
                                "--dry-run", "--runtime", "kubernetes",
                                "--kubernetes-config", str(pool))
    assert r.code == 0, r.err
    found = json.loads(r.out)
    kinds = [item["kind"] for item in found["items"]]
    assert kinds == ["Service", "PodGroup", "Pod", "Pod"], kinds
    schema = SchemaCheck("1.33")
    for item in found["items"]:
        assert schema(item) == [], item["kind"]
        if item["kind"] in KINDS:
            assert check(KINDS[item["kind"]], item) == [], item["kind"]
    service = found["items"][0]["metadata"]["name"]
    client = found["items"][3]
    assert f"server.{service}" in " ".join(client["spec"]["containers"][0]["command"])
    assert client["metadata"]["annotations"]["scheduling.k8s.io/group-name"] == service


def test_runtime_without_dry_run_is_a_usage_error(tmp_path: Path) -> None:
    r = Osmo(tmp_path / "home")("submit", str(TUTORIALS / "hello_world.yaml"), "--runtime",
                                "kubernetes")
    assert r.code == 2 and "--dry-run" in r.err, r.err


def test_the_workflow_s_priority_picks_the_pods_priority_class(tmp_path: Path) -> None:
    pool = tmp_path / "pool.json"
    pool.write_text(json.dumps({"priorityClasses": {"HIGH": "osmo-high", "default": "osmo-std"}}))
    osmo = Osmo(tmp_path / "home")

    def classes(*priority: str) -> list[str | None]:
        r = osmo("submit", str(TUTORIALS / "hello_world.yaml"), "--dry-run", "--runtime",
                 "kubernetes", "--kubernetes-config", str(pool), *priority)
        assert r.code == 0, r.err
        return [item["spec"].get("priorityClassName") for item in json.loads(r.out)["items"]
                if item["kind"] == "Pod"]

    assert classes("--priority", "HIGH") == ["osmo-high"]
    assert classes() == ["osmo-std"]  # NORMAL has no class of its own here: the default
