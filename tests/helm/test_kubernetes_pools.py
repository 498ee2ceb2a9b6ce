"""A pool of kind ``kubernetes`` (issue #28): its worker runs ``osmo worker --runtime
kubernetes`` with the pool's configuration, a ServiceAccount of its own, and a Role in the
tasks' namespace that grants nothing beyond what the worker uses (the rendered RBAC is read
here, rule by rule); the configuration the chart writes is what the worker reads.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from osmo.runtime.kubernetes.config import load_pool
from tests.helm.chart import (
    FULLNAME,
    NAMESPACE,
    container,
    env,
    flag,
    lint,
    render,
    tls_values,
    volumes,
)

POD_GROUPS = {"kai": "scheduling.run.ai", "volcano": "scheduling.volcano.sh",
              "coscheduling": "scheduling.x-k8s.io"}


def values(**kube: Any) -> dict[str, Any]:
    return {"pools": [{"name": "cpu", "replicas": 1},
                      {"name": "pods", "replicas": 2, "kind": "kubernetes",
                       "kubernetes": {"workClaim": "osmo-work", **kube}}]}


def rules(rendered: Any, name: str = f"{FULLNAME}-kube-pods") -> set[tuple[str, str, str]]:
    return {(group, resource, verb) for rule in rendered.get("Role", name)["rules"]
            for group in rule["apiGroups"] for resource in rule["resources"]
            for verb in rule["verbs"]}


@pytest.mark.parametrize("gang", ["none", "kai", "volcano", "kueue", "coscheduling"])
def test_the_role_grants_only_what_the_worker_uses(gang: str) -> None:
    rendered = render(values(gang=gang, namespace="osmo-tasks"))
    expected = {("", "pods", v) for v in ("create", "get", "list", "watch", "delete")}
    expected |= {("", "pods/log", "get")}
    expected |= {("", "secrets", v) for v in ("create", "delete", "deletecollection")}  # not read
    expected |= {("", sub, v) for sub in ("pods/exec", "pods/portforward")
                 for v in ("create", "get")}  # exec and port-forward, nothing else of a pod
    expected |= {("", "services", v) for v in ("create", "delete", "deletecollection")}
    if gang in POD_GROUPS:
        expected |= {(POD_GROUPS[gang], "podgroups", v)
                     for v in ("create", "delete", "deletecollection")}
    assert rules(rendered) == expected
    role = rendered.get("Role", f"{FULLNAME}-kube-pods")
    assert role["metadata"]["namespace"] == "osmo-tasks"
    binding = rendered.get("RoleBinding", f"{FULLNAME}-kube-pods")
    assert binding["subjects"] == [{"kind": "ServiceAccount", "name": f"{FULLNAME}-kube-pods",
                                    "namespace": NAMESPACE}]
    nodes = rendered.get("ClusterRole", f"{NAMESPACE}-{FULLNAME}-kube-pods-nodes")
    assert nodes["rules"] == [{"apiGroups": [""], "resources": ["nodes"],
                               "verbs": ["get", "list", "watch"]}]
    assert len(rendered.of_kind("Role")) == 1 and len(rendered.of_kind("ClusterRole")) == 1


def test_read_nodes_off_leaves_no_cluster_role() -> None:
    assert render(values(readNodes=False)).of_kind("ClusterRole") == []


def test_the_worker_runs_the_kubernetes_runtime_with_the_written_pool(tmp_path: Path) -> None:
    rendered = render(values(gang="kai", queue="research", nodeSelector={"pool": "robots"},
                             platforms={"dgx": {"nodeSelector": {"gpu": "h100"}}},
                             priorityClasses={"default": "osmo-normal"}))
    deployment = rendered.get("StatefulSet", f"{FULLNAME}-worker-pods")
    worker = container(deployment, "worker")
    assert flag(worker["args"], "--runtime") == ["kubernetes"]
    assert flag(worker["args"], "--kubernetes-config") == ["/etc/osmo/kubernetes/pool.json"]
    assert env(worker)["OSMO_HOME"] == "/var/lib/osmo/home/$(POD_NAME)"
    spec = deployment["spec"]["template"]["spec"]
    assert spec["serviceAccountName"] == f"{FULLNAME}-kube-pods"
    assert spec["automountServiceAccountToken"] is True
    claim = {v["name"]: v for v in spec["volumes"]}["home"]
    assert claim == {"name": "home", "persistentVolumeClaim": {"claimName": "osmo-work"}}
    text = rendered.get("ConfigMap", f"{FULLNAME}-kube-pods")["data"]["pool.json"]
    (tmp_path / "pool.json").write_text(text)
    pool = load_pool(tmp_path / "pool.json")  # what the worker reads
    assert (pool.namespace, pool.gang, pool.queue) == (NAMESPACE, "kai", "research")
    assert pool.placement.node_selector == {"pool": "robots"}
    assert pool.platforms["dgx"].node_selector == {"gpu": "h100"}
    assert (pool.work_claim, str(pool.work_mount)) == ("osmo-work", "/var/lib/osmo")
    assert pool.kubeconfig is None  # in-cluster: its ServiceAccount's token
    other = container(rendered.get("Deployment", f"{FULLNAME}-worker-cpu"), "worker")
    assert "--runtime" not in other["args"]
    assert json.loads(text)["groupNetwork"] == "service"


def test_a_replaced_kubernetes_worker_keeps_its_name_hence_its_instance() -> None:
    """A kubernetes pool's workers are a StatefulSet: a replacement pod has its predecessor's
    name (its ``--name``, host name and home path, so its instance label) and cleans up or
    adopts what that one left; updates still replace one worker at a time; a process pool
    stays a Deployment (its tasks die with its pod)."""
    rendered = render(values())
    assert [d["metadata"]["name"] for d in rendered.of_kind("Deployment")] == [
        f"{FULLNAME}-worker-cpu"]
    workers = rendered.get("StatefulSet", f"{FULLNAME}-worker-pods")
    spec = workers["spec"]
    assert spec["replicas"] == 2
    assert spec["updateStrategy"] == {"type": "RollingUpdate"}
    assert spec["podManagementPolicy"] == "Parallel"
    assert "volumeClaimTemplates" not in spec  # the home is on the work claim
    worker = container(workers, "worker")
    assert flag(worker["args"], "--name") == ["$(POD_NAME)"]
    assert env(worker)["POD_NAME"] == {"fieldRef": {"fieldPath": "metadata.name"}}
    assert env(worker)["OSMO_HOME"] == "/var/lib/osmo/home/$(POD_NAME)"
    service = rendered.get("Service", spec["serviceName"])
    assert service["spec"]["clusterIP"] == "None"
    assert service["spec"]["selector"] == spec["selector"]["matchLabels"]
    selected = [o["metadata"]["name"] for o in rendered.objects if o["kind"] in (
        "Deployment", "StatefulSet") and service["spec"]["selector"].items()
        <= o["spec"]["template"]["metadata"]["labels"].items()]
    assert selected == [f"{FULLNAME}-worker-pods"]  # this pool's workers only
    assert "statefulset/" + f"{FULLNAME}-worker-pods" in rendered.notes
    assert "deployment/" + f"{FULLNAME}-worker-cpu" in rendered.notes


def test_a_kubernetes_pool_lints_clean() -> None:
    assert lint(values(gang="volcano")) == []


def test_without_a_work_claim_pods_get_their_data_from_the_charts_image(
        tmp_path: Path) -> None:
    rendered = render({"pools": [{"name": "pods", "replicas": 1, "kind": "kubernetes",
                                  "kubernetes": {"gang": "kai"}}]})
    deployment = rendered.get("StatefulSet", f"{FULLNAME}-worker-pods")
    worker = container(deployment, "worker")
    text = rendered.get("ConfigMap", f"{FULLNAME}-kube-pods")["data"]["pool.json"]
    (tmp_path / "pool.json").write_text(text)
    pool = load_pool(tmp_path / "pool.json")
    assert pool.work_claim is None and pool.data_image == worker["image"], (text, worker)
    assert env(worker)["OSMO_HOME"] == "/var/lib/osmo/home"
    volumes = {v["name"]: v for v in deployment["spec"]["template"]["spec"]["volumes"]}
    assert "emptyDir" in volumes["home"], volumes  # nothing shared with the task pods


AUTH_DATA = {"router": {"enabled": True}, "auth": {"enabled": True, "password": "pw"},
             "pools": [{"name": "pods", "replicas": 1, "kind": "kubernetes", "kubernetes": {}}]}


def test_with_auth_the_pods_data_containers_log_in_as_the_pod_user(tmp_path: Path) -> None:
    """auth.enabled, no workClaim: the worker's init container writes its pods' zenoh config
    (auth.podUser's password from the auth Secret, never in the pool's ConfigMap), the pool
    hands it to the pods, and the router knows that user (its rules: tests/hostile)."""
    rendered = render(AUTH_DATA)
    workers = rendered.get("StatefulSet", f"{FULLNAME}-worker-pods")
    init = workers["spec"]["template"]["spec"]["initContainers"][0]
    assert init["command"][2:] == [
        "/etc/osmo/zenoh/client.json5", "/etc/osmo/auth/user", "/etc/osmo/auth/password",
        "/run/osmo/zenoh/client.json5", "/etc/osmo/auth/pod-user",
        "/etc/osmo/auth/pod-password", "/run/osmo/zenoh/pod.json5"]
    text = rendered.get("ConfigMap", f"{FULLNAME}-kube-pods")["data"]["pool.json"]
    (tmp_path / "pool.json").write_text(text)
    pool = load_pool(tmp_path / "pool.json")
    assert pool.data_zenoh_config == "/run/osmo/zenoh/pod.json5"
    acl = json.loads(rendered.get("ConfigMap", f"{FULLNAME}-zenoh")["data"]["router.json5"])[
        "access_control"]
    assert {"id": "osmo-pods", "usernames": ["osmo-pod"]} in acl["subjects"]
    rules = {r["id"]: r for r in acl["rules"]}
    pods = next(p for p in acl["policies"] if p["id"] == "osmo-pods")
    assert [(rules[r]["messages"], rules[r]["flows"], rules[r]["key_exprs"])
            for r in pods["rules"]] == [(["query"], ["ingress"], ["osmo/local/podio/**"]),
                                        (["reply"], ["egress"], ["osmo/local/podio/**"])]
    # a pool with a work claim needs no pod user, and the router knows none
    claimed = render({**AUTH_DATA, "pools": [{**AUTH_DATA["pools"][0],
                                              "kubernetes": {"workClaim": "work"}}]})
    plain = json.loads(claimed.get("ConfigMap", f"{FULLNAME}-zenoh")["data"]["router.json5"])
    assert "osmo-pod" not in json.dumps(plain)
    assert "pod-user" not in claimed.get("Secret", f"{FULLNAME}-auth")["data"]



def test_with_tls_alone_the_pods_data_containers_get_the_ca() -> None:
    rendered = render(tls_values(pools=AUTH_DATA["pools"]))
    pool = json.loads(rendered.get("ConfigMap", f"{FULLNAME}-kube-pods")["data"]["pool.json"])
    assert pool["data"]["zenohConfig"] == "/etc/osmo/zenoh/client.json5"
    client = json.loads(rendered.get("ConfigMap", f"{FULLNAME}-zenoh")["data"]["client.json5"])
    assert client["transport"]["link"]["tls"] == {
        "root_ca_certificate": "/etc/osmo/tls/server/ca.crt"}  # what the worker copies


def test_a_worker_reads_only_its_own_users_credentials_never_the_servers() -> None:
    """The auth Secret holds every zenoh user's password and the router's dictionary; a
    worker pod (a task's neighbour) gets only its own user's keys, and a data-mode pool's
    the pods' user's, so a compromised worker cannot log in to the router as the server."""
    rendered = render({**AUTH_DATA, "pools": [
        *AUTH_DATA["pools"], {"name": "claimed", "replicas": 1, "kind": "kubernetes",
                              "kubernetes": {"workClaim": "work"}},
        {"name": "cpu", "replicas": 1}]})
    secret = rendered.get("Secret", f"{FULLNAME}-auth")
    assert {"server-password", "dictionary", "pod-password"} <= set(secret["data"])
    expected = {"pods": ["user", "password", "pod-user", "pod-password"],
                "claimed": ["user", "password"], "cpu": ["user", "password"]}
    for pool, keys in expected.items():
        kind = "Deployment" if pool == "cpu" else "StatefulSet"
        owner = rendered.get(kind, f"{FULLNAME}-worker-{pool}")
        items = volumes(owner)["auth"]["secret"].get("items")
        assert [(i["key"], i["path"]) for i in items or []] == [(k, k) for k in keys], pool
    server = rendered.get("StatefulSet", f"{FULLNAME}-server")
    assert "items" not in volumes(server)["auth"]["secret"]  # the server reads them all
