"""The Kubernetes API stand-in, driven only through the official ``kubernetes`` client.

Wire tests (no container runs): create/get/list/patch/replace/delete with the real server's
codes and Status bodies, selectors and pages, watches with resourceVersion and 410, owner
garbage collection, PodGroups, nodes, refused objects, counted writes, and every status
script. Pod tests run the pods for real under ``podman kube play``: init container and
emptyDir, logs (also followed), Secrets, graceful deletion, gangs, unschedulable pods,
pull failures, OOM, native sidecars. Nothing of podman may be left after a test (fixture).
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pydantic
import pytest
import urllib3
from kubernetes import client, config, watch
from kubernetes.client.rest import ApiException

from tests.k8s import scripts
from tests.k8s.conftest import Cluster
from tests.k8s.podman_pods import read_log
from tests.k8s.scripts import SCRIPTS, Script

NS = "default"
BUSYBOX = "alpine:3.18"  # tests/containers/images.py builds it offline


def pod(name: str, command: str = "true", *, image: str = BUSYBOX, **spec: Any) -> dict[str, Any]:
    """A pod of one container ``main`` running ``sh -c command``, never restarted."""
    body: dict[str, Any] = {
        "apiVersion": "v1", "kind": "Pod", "metadata": {"name": name},
        "spec": {"restartPolicy": "Never",
                 "containers": [{"name": "main", "image": image,
                                 "command": ["sh", "-c", command]}]}}
    body["spec"].update(spec)
    return body


def unplaceable(name: str) -> dict[str, Any]:
    """A pod no node can take: it stays Pending and never reaches podman."""
    body = pod(name)
    body["spec"]["containers"][0]["resources"] = {"requests": {"cpu": "1000"}}
    return body


def version(c: Cluster) -> str:
    """The current resourceVersion (a watch from it sees everything that follows)."""
    return str(c.core.list_namespaced_pod(NS).metadata.resource_version)


def summary(event: dict[str, Any]) -> tuple[str, str, str | None]:
    """(type, phase, what explains it) of a watch event of a pod."""
    status = event["raw_object"].get("status") or {}
    conditions = {c["type"]: c for c in status.get("conditions") or []}
    detail = status.get("reason")
    target = conditions.get("DisruptionTarget")
    if detail is None and target and target["status"] == "True":
        detail = target.get("reason")
    if detail is None and status.get("containerStatuses"):
        state = status["containerStatuses"][0]["state"]
        (kind, info), = state.items()
        detail = ("running" if kind == "running" else
                  info.get("reason") if kind == "waiting" else
                  f"{info.get('reason')}:{info.get('exitCode')}")
    scheduled = conditions.get("PodScheduled")
    if detail is None and scheduled and scheduled["status"] == "False":
        detail = scheduled.get("reason")
    return event["type"], status.get("phase", ""), detail


def watch_pod(c: Cluster, name: str, since: str, until: Callable[[dict[str, Any]], bool],
              timeout: int = 120) -> list[dict[str, Any]]:
    """The watch events of pod ``name`` after version ``since``, up to the first ``until``."""
    seen: list[dict[str, Any]] = []
    stream = watch.Watch()
    for event in stream.stream(c.core.list_namespaced_pod, NS, resource_version=since,
                               field_selector=f"metadata.name={name}",
                               timeout_seconds=timeout):
        seen.append(event)
        if until(event):
            stream.stop()
            return seen
    raise AssertionError(f"pod {name} never got there; saw {[summary(e) for e in seen]}")


def phase_is(*phases: str) -> Callable[[dict[str, Any]], bool]:
    return lambda event: (event["raw_object"].get("status") or {}).get("phase") in phases


def deleted(event: dict[str, Any]) -> bool:
    return event["type"] == "DELETED"


def body_of(exc: ApiException) -> dict[str, Any]:
    return json.loads(exc.body)  # type: ignore[no-any-return]


# ---------------------------------------------------------------------- the wire


def test_create_get_list_and_delete_with_the_real_servers_answers(api: Cluster) -> None:
    created = api.core.create_namespaced_pod(NS, unplaceable("p1"))
    assert created.metadata.uid and created.status.phase == "Pending"
    assert created.spec.scheduler_name == "default-scheduler"  # server-side defaults
    with pytest.raises(ApiException) as exists:
        api.core.create_namespaced_pod(NS, unplaceable("p1"))
    assert exists.value.status == 409
    assert body_of(exists.value) == {
        "kind": "Status", "apiVersion": "v1", "metadata": {}, "status": "Failure",
        "message": 'pods "p1" already exists', "reason": "AlreadyExists",
        "details": {"name": "p1", "kind": "pods"}, "code": 409}
    labelled = unplaceable("p2")
    labelled["metadata"]["labels"] = {"osmo.workflow": "wf-1"}
    api.core.create_namespaced_pod(NS, labelled)
    assert [p.metadata.name for p in api.core.list_namespaced_pod(NS).items] == ["p1", "p2"]
    assert [p.metadata.name for p in api.core.list_namespaced_pod(
        NS, label_selector="osmo.workflow in (wf-1,wf-2)").items] == ["p2"]
    assert [p.metadata.name for p in api.core.list_pod_for_all_namespaces(
        field_selector="metadata.name!=p2").items] == ["p1"]
    assert api.core.list_namespaced_pod("elsewhere").items == []
    assert api.core.read_namespaced_pod("p2", NS).metadata.labels == {"osmo.workflow": "wf-1"}
    gone = api.core.delete_namespaced_pod("p1", NS, grace_period_seconds=3)
    assert gone.metadata.name == "p1"  # an unbound pod goes at once, whatever the grace
    with pytest.raises(ApiException) as missing:
        api.core.read_namespaced_pod("p1", NS)
    assert missing.value.status == 404 and body_of(missing.value)["reason"] == "NotFound"
    assert body_of(missing.value)["message"] == 'pods "p1" not found'
    with pytest.raises(ApiException) as bad:
        api.core.list_namespaced_pod(NS, label_selector="a in b")
    assert bad.value.status == 400


def test_a_kubeconfig_points_the_client_at_the_stand_in(api: Cluster, tmp_path: Path) -> None:
    path = api.server.kubeconfig(tmp_path / "kubeconfig")
    loaded = config.new_client_from_config(config_file=str(path))
    try:
        core = client.CoreV1Api(loaded)
        core.create_namespaced_pod(NS, unplaceable("via-kubeconfig"))
        assert [p.metadata.name for p in core.list_namespaced_pod(NS).items] == [
            "via-kubeconfig"]
        terminating = core.read_namespaced_pod("via-kubeconfig", NS)
        assert terminating.status.phase == "Pending"
    finally:
        loaded.close()


def test_pages_patches_replacement_and_collections(api: Cluster) -> None:
    for i in range(5):
        api.core.create_namespaced_secret(NS, client.V1Secret(
            metadata=client.V1ObjectMeta(name=f"s{i}", labels={"batch": str(i % 2)}),
            string_data={"k": f"v{i}"}))
    page = api.core.list_namespaced_secret(NS, limit=2)
    names = [s.metadata.name for s in page.items]
    while page.metadata._continue:
        page = api.core.list_namespaced_secret(NS, limit=2, _continue=page.metadata._continue)
        names += [s.metadata.name for s in page.items]
    assert names == ["s0", "s1", "s2", "s3", "s4"]
    patched = api.core.patch_namespaced_secret("s0", NS, {"metadata": {"labels": {"x": "y"}}})
    assert patched.metadata.labels == {"batch": "0", "x": "y"}
    patched = api.core.patch_namespaced_secret(
        "s0", NS, [{"op": "remove", "path": "/metadata/labels/x"}])
    assert patched.metadata.labels == {"batch": "0"}
    stale = api.core.read_namespaced_secret("s1", NS)
    api.core.patch_namespaced_secret("s1", NS, {"metadata": {"labels": {"n": "1"}}})
    with pytest.raises(ApiException) as conflict:
        api.core.replace_namespaced_secret("s1", NS, stale)
    assert conflict.value.status == 409 and body_of(conflict.value)["reason"] == "Conflict"
    api.core.delete_collection_namespaced_secret(NS, label_selector="batch=1")
    assert [s.metadata.name for s in api.core.list_namespaced_secret(NS).items] == [
        "s0", "s2", "s4"]


def test_refused_objects_list_every_cause(api: Cluster) -> None:
    bad = pod("Not_A_Name", image="")
    bad["metadata"]["labels"] = {"osmo.task": "has spaces"}
    bad["spec"]["containers"][0]["volumeMounts"] = [{"name": "nowhere", "mountPath": "/x"}]
    with pytest.raises(ApiException) as refused:
        api.core.create_namespaced_pod(NS, bad)
    status = body_of(refused.value)
    assert (refused.value.status, status["reason"]) == (422, "Invalid")
    assert [c["field"] for c in status["details"]["causes"]] == [
        "metadata.name", "metadata.labels", "spec.containers[0].image",
        "spec.containers[0].volumeMounts[0].name"]
    assert status["message"].startswith('Pod "Not_A_Name" is invalid: [metadata.name: ')
    assert api.core.list_namespaced_pod(NS).items == []
    with pytest.raises(ApiException) as undecodable:
        api.core.create_namespaced_secret(NS, {"metadata": {"name": "s"}, "data": {"k": "%%"}})
    assert undecodable.value.status == 400


def post_untyped(c: Cluster, body: dict[str, Any]) -> tuple[int, dict[str, Any]]:
    """POST a pod through the client's untyped path (as DynamicClient and older clients do)."""
    request = c.client.param_serialize("POST", "/api/v1/namespaces/{namespace}/pods",
                                       path_params={"namespace": NS}, body=body,
                                       header_params={"Content-Type": "application/json"})
    response = c.client.call_api(*request)
    response.read()
    return response.status, json.loads(response.data)


def test_the_schema_option_refuses_what_fails_the_strict_schema(
        api: Cluster, strict_api: Cluster) -> None:
    body = unplaceable("typo")
    body["spec"]["containers"][0]["imagePulPolicy"] = "Never"  # misspelt: unknown field
    body["spec"]["priority"] = "high"  # wrong type
    # kubernetes 37.x checks typed calls itself (pydantic models) before sending anything.
    with pytest.raises(pydantic.ValidationError):
        strict_api.core.create_namespaced_pod(NS, body)
    # What reaches the server untyped passes by default, and is refused when asked.
    assert post_untyped(api, body)[0] == 201
    code, status = post_untyped(strict_api, body)
    assert (code, status["reason"]) == (422, "Invalid")
    assert {c["field"] for c in status["details"]["causes"]} == {"spec.containers[0]",
                                                                  "spec.priority"}
    assert "imagePulPolicy" in status["message"]
    assert strict_api.core.create_namespaced_pod(NS, unplaceable("fine")).metadata.name == "fine"


def test_a_watch_streams_changes_after_its_version(api: Cluster) -> None:
    since = version(api)
    api.core.create_namespaced_pod(NS, unplaceable("w1"))
    api.core.patch_namespaced_pod("w1", NS, {"metadata": {"labels": {"a": "b"}}})
    api.core.delete_namespaced_pod("w1", NS)
    events = watch_pod(api, "w1", since, deleted)
    types = [e["type"] for e in events]
    assert types[0] == "ADDED" and types[-1] == "DELETED"
    assert set(types[1:-1]) == {"MODIFIED"}  # the patch, and the scheduler's verdict
    assert any(e["object"].metadata.labels == {"a": "b"} for e in events[1:])
    assert events[-1]["object"].metadata.name == "w1"
    versions = [int(e["object"].metadata.resource_version) for e in events]
    assert versions == sorted(versions) and versions[0] > int(since)


def test_a_watch_from_a_compacted_version_gets_410(api: Cluster) -> None:
    since = version(api)
    api.core.create_namespaced_secret(NS, client.V1Secret(metadata=client.V1ObjectMeta(name="s")))
    api.server.store.compact()
    # The client (37.x) retries a 410 once from the same version, then raises; it never
    # yields the ERROR event. With timeout_seconds it raises at once.
    for extra in ({}, {"timeout_seconds": 5}):
        with pytest.raises(ApiException) as gone:
            for _ in watch.Watch().stream(api.core.list_namespaced_secret, NS,
                                          resource_version=since, **extra):
                pass
        assert gone.value.status == 410 and "too old resource version" in gone.value.reason
    # On the wire: HTTP 200, one ERROR event carrying the Status, as the real server sends.
    raw = api.core.list_namespaced_secret(NS, watch=True, resource_version=since,
                                          _preload_content=False)
    assert raw.status == 200
    (line,) = raw.data.decode().splitlines()
    event = json.loads(line)
    assert event["type"] == "ERROR"
    assert (event["object"]["code"], event["object"]["reason"]) == (410, "Expired")
    # Relisting gives a version to watch from again.
    fresh = api.core.list_namespaced_secret(NS).metadata.resource_version
    api.core.delete_namespaced_secret("s", NS)
    events = list(watch.Watch().stream(api.core.list_namespaced_secret, NS,
                                       resource_version=fresh, timeout_seconds=1))
    assert [e["type"] for e in events] == ["DELETED"]


def test_owned_secrets_are_collected_with_their_pod(api: Cluster) -> None:
    def secret(name: str, owner: client.V1Pod | None, uid: str | None = None) -> None:
        refs = [client.V1OwnerReference(api_version="v1", kind="Pod", name="owner",
                                        uid=uid or owner.metadata.uid)] if owner or uid else None
        api.core.create_namespaced_secret(NS, client.V1Secret(
            metadata=client.V1ObjectMeta(name=name, owner_references=refs),
            string_data={"token": "t"}))

    def names() -> list[str]:
        return [s.metadata.name for s in api.core.list_namespaced_secret(NS).items]

    owner = api.core.create_namespaced_pod(NS, unplaceable("owner"))
    secret("owned", owner)
    secret("free", None)
    secret("dangling", None, uid="0000-no-such-owner")  # collected at once, as the real GC does
    assert names() == ["owned", "free"]
    api.core.delete_namespaced_pod("owner", NS, propagation_policy="Background")
    assert names() == ["free"]
    owner = api.core.create_namespaced_pod(NS, unplaceable("owner"))
    secret("orphan", owner)
    api.core.delete_namespaced_pod("owner", NS, propagation_policy="Orphan")
    kept = api.core.read_namespaced_secret("orphan", NS)
    assert kept.metadata.owner_references is None


@pytest.mark.parametrize("group,version_", [("scheduling.run.ai", "v2alpha2"),
                                            ("scheduling.volcano.sh", "v1beta1"),
                                            ("scheduling.x-k8s.io", "v1alpha1")])
def test_podgroups_of_each_gang_scheduler(api: Cluster, group: str, version_: str) -> None:
    body = {"apiVersion": f"{group}/{version_}", "kind": "PodGroup",
            "metadata": {"name": "g1", "labels": {"osmo.workflow": "wf"}},
            "spec": {"minMember": 2}}
    made = api.custom.create_namespaced_custom_object(group, version_, NS, "podgroups", body)
    assert made["metadata"]["uid"] and made["spec"] == {"minMember": 2}
    with pytest.raises(ApiException) as exists:
        api.custom.create_namespaced_custom_object(group, version_, NS, "podgroups", body)
    assert body_of(exists.value)["message"] == f'podgroups.{group} "g1" already exists'
    listed = api.custom.list_namespaced_custom_object(group, version_, NS, "podgroups",
                                                      label_selector="osmo.workflow=wf")
    assert [g["metadata"]["name"] for g in listed["items"]] == ["g1"]
    api.custom.delete_namespaced_custom_object(group, version_, NS, "podgroups", "g1")
    with pytest.raises(ApiException) as missing:
        api.custom.get_namespaced_custom_object(group, version_, NS, "podgroups", "g1")
    assert missing.value.status == 404


def test_nodes_show_their_allocatable_resources_and_labels(api: Cluster) -> None:
    api.kubelet.add_node("gpu-1", cpu="16", memory="64Gi", gpus=8,
                         labels={"osmo.platform": "dgx"})
    nodes = {n.metadata.name: n for n in api.core.list_node().items}
    assert set(nodes) == {"node-1", "gpu-1"}
    assert nodes["gpu-1"].status.allocatable["nvidia.com/gpu"] == "8"
    assert nodes["gpu-1"].status.allocatable["cpu"] == "16"
    assert nodes["gpu-1"].metadata.labels["osmo.platform"] == "dgx"
    assert api.core.read_node("node-1").status.allocatable["memory"] == "8Gi"


def test_writes_are_counted_per_verb_and_resource(api: Cluster) -> None:
    api.core.create_namespaced_pod(NS, unplaceable("c1"))
    api.core.read_namespaced_pod("c1", NS)
    api.core.patch_namespaced_pod("c1", NS, {"metadata": {"labels": {"a": "b"}}})
    api.core.delete_namespaced_pod("c1", NS)
    with pytest.raises(ApiException):
        api.core.delete_namespaced_pod("c1", NS)  # refused writes are requests too
    assert api.server.writes == {("create", "pods"): 1, ("patch", "pods"): 1,
                                 ("delete", "pods"): 2}
    assert api.server.calls[("get", "pods")] == 1


def test_log_requests_the_server_refuses(api: Cluster) -> None:
    two = unplaceable("two")
    two["spec"]["containers"].append({"name": "side", "image": BUSYBOX})
    api.core.create_namespaced_pod(NS, two)
    with pytest.raises(ApiException) as which:
        api.core.read_namespaced_pod_log("two", NS)
    assert which.value.status == 400 and "choose one of: [main side]" in which.value.body
    with pytest.raises(ApiException) as unknown:
        api.core.read_namespaced_pod_log("two", NS, container="nope")
    assert unknown.value.status == 400
    with pytest.raises(ApiException) as waiting:
        api.core.read_namespaced_pod_log("two", NS, container="main")
    assert waiting.value.status == 400 and "is waiting to start" in waiting.value.body
    with pytest.raises(ApiException) as missing:
        api.core.read_namespaced_pod_log("nobody", NS)
    assert missing.value.status == 404


# ---------------------------------------------------------------------- status scripts

STARTED = [("ADDED", "Pending", None), ("MODIFIED", "Pending", "ContainerCreating"),
           ("MODIFIED", "Running", "running")]
EXPECTED = {
    "unschedulable-running-succeeded": [
        ("ADDED", "Pending", None), ("MODIFIED", "Pending", "Unschedulable"), *STARTED[1:],
        ("MODIFIED", "Succeeded", "Completed:0")],
    "image-pull-error": [
        *STARTED[:2], ("MODIFIED", "Pending", "ErrImagePull"),
        ("MODIFIED", "Pending", "ImagePullBackOff")],
    "oom-killed": [*STARTED, ("MODIFIED", "Failed", "OOMKilled:137")],
    "evicted": [*STARTED, ("MODIFIED", "Failed", "Evicted")],
    "preempted": [*STARTED, ("MODIFIED", "Running", "PreemptionByScheduler"),
                  ("DELETED", "Running", "PreemptionByScheduler")],
    "node-lost": [*STARTED, ("MODIFIED", "Unknown", "NodeLost"),
                  ("MODIFIED", "Unknown", "NodeLost"), ("DELETED", "Unknown", "NodeLost")],
}


def test_every_named_script_has_its_expected_sequence() -> None:
    assert set(EXPECTED) | {"watch-stalls"} == set(SCRIPTS)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_a_status_script_plays_as_described(api: Cluster, name: str) -> None:
    api.kubelet.script("scripted", SCRIPTS[name])
    since = version(api)
    api.core.create_namespaced_pod(NS, pod("scripted"))
    expected = EXPECTED[name]
    count = iter(range(len(expected) - 1, -1, -1))
    events = watch_pod(api, "scripted", since, lambda e: next(count) == 0)
    assert [summary(e) for e in events] == expected
    if name == "unschedulable-running-succeeded":
        assert api.core.read_namespaced_pod_log("scripted", NS) == "hello from a script\n"
        assert events[2]["object"].spec.node_name == "node-1"
    if events[-1]["type"] != "DELETED":
        api.core.delete_namespaced_pod("scripted", NS)


def test_a_stalled_watch_stays_open_and_silent_while_the_pod_moves_on(api: Cluster) -> None:
    go = threading.Event()
    api.kubelet.script("stalls", Script((scripts.scheduled(), scripts.running(),
                                         scripts.wait(go), scripts.stall_watches(),
                                         scripts.succeeded())))
    since = version(api)
    api.core.create_namespaced_pod(NS, pod("stalls"))
    seen = []
    stream = watch.Watch()
    with pytest.raises(urllib3.exceptions.ReadTimeoutError):
        for event in stream.stream(api.core.list_namespaced_pod, NS, resource_version=since,
                                   _request_timeout=(5, 5)):
            seen.append(summary(event))
            if event["raw_object"]["status"].get("phase") == "Running":
                go.set()  # from now on this watch hears nothing, and is not closed either
    assert seen[-1] == ("MODIFIED", "Running", "running")
    deadline = time.monotonic() + 60
    while api.core.read_namespaced_pod("stalls", NS).status.phase != "Succeeded":
        assert time.monotonic() < deadline
        time.sleep(0.1)
    resumed = watch_pod(api, "stalls", since, phase_is("Succeeded"))  # a new watch hears it
    assert summary(resumed[-1]) == ("MODIFIED", "Succeeded", "Completed:0")
    api.core.delete_namespaced_pod("stalls", NS)


# ---------------------------------------------------------------------- pods under podman


def test_a_pod_runs_under_podman_from_pending_to_succeeded(
        api: Cluster, images: dict[str, str], tmp_path: Path) -> None:
    gate = tmp_path / "gate"
    gate.mkdir()
    body = pod("hello", "cat /data/x.txt; echo waiting; "
               "while [ ! -e /gate/go ]; do sleep 0.1; done; echo done",
               volumes=[{"name": "shared", "emptyDir": {}},
                        {"name": "gate", "hostPath": {"path": str(gate)}}],
               initContainers=[{"name": "fetch", "image": BUSYBOX,
                                "command": ["sh", "-c", "echo from-init > /data/x.txt"],
                                "volumeMounts": [{"name": "shared", "mountPath": "/data"}]}])
    body["spec"]["containers"][0]["volumeMounts"] = [
        {"name": "shared", "mountPath": "/data"}, {"name": "gate", "mountPath": "/gate"}]
    since = version(api)
    api.core.create_namespaced_pod(NS, body)
    events = watch_pod(api, "hello", since, phase_is("Running", "Failed", "Succeeded"))
    running = events[-1]["object"]
    assert running.status.phase == "Running", [summary(e) for e in events]
    assert running.spec.node_name == "node-1" and running.status.pod_ip
    (init,) = running.status.init_container_statuses
    assert (init.state.terminated.exit_code, init.state.terminated.reason) == (0, "Completed")
    followed: list[str] = []
    follower = threading.Thread(target=lambda: followed.extend(watch.Watch().stream(
        api.core.read_namespaced_pod_log, "hello", NS, container="main")))
    follower.start()
    (gate / "go").touch()
    events = watch_pod(api, "hello", running.metadata.resource_version,
                       phase_is("Succeeded", "Failed"))
    done = events[-1]["object"]
    assert done.status.phase == "Succeeded"
    (main,) = done.status.container_statuses
    assert (main.state.terminated.exit_code, main.state.terminated.reason) == (0, "Completed")
    assert {c.type: c.status for c in done.status.conditions}["PodScheduled"] == "True"
    follower.join(timeout=60)
    assert followed == ["from-init", "waiting", "done"]
    assert api.core.read_namespaced_pod_log("hello", NS) == "from-init\nwaiting\ndone\n"
    assert api.core.read_namespaced_pod_log("hello", NS, tail_lines=1) == "done\n"
    assert api.core.read_namespaced_pod_log("hello", NS, container="fetch") == ""
    since = done.metadata.resource_version
    api.core.delete_namespaced_pod("hello", NS)
    assert watch_pod(api, "hello", since, deleted)[-1]["type"] == "DELETED"


def test_secrets_reach_the_pod_and_go_with_it_in_three_writes(
        api: Cluster, images: dict[str, str]) -> None:
    body = pod("secretive", 'echo "env=$TOKEN"; cat /creds/token; echo; ls /creds')
    body["spec"]["volumes"] = [{"name": "creds", "secret": {"secretName": "attempt-1"}}]
    main = body["spec"]["containers"][0]
    main["env"] = [{"name": "TOKEN", "valueFrom": {"secretKeyRef": {"name": "attempt-1",
                                                                    "key": "token"}}}]
    main["volumeMounts"] = [{"name": "creds", "mountPath": "/creds"}]
    since = version(api)
    created = api.core.create_namespaced_pod(NS, body)
    events = watch_pod(api, "secretive", since,
                       lambda e: summary(e)[2] == "CreateContainerConfigError")
    waiting = events[-1]["object"].status.container_statuses[0].state.waiting
    assert waiting.reason == "CreateContainerConfigError"  # no Secret yet: the pod waits
    assert waiting.message == 'secret "attempt-1" not found'
    api.core.create_namespaced_secret(NS, client.V1Secret(
        metadata=client.V1ObjectMeta(name="attempt-1", owner_references=[
            client.V1OwnerReference(api_version="v1", kind="Pod", name="secretive",
                                    uid=created.metadata.uid)]),
        string_data={"token": "s3cr3t"}))
    watch_pod(api, "secretive", since, phase_is("Succeeded", "Failed"))
    assert api.core.read_namespaced_pod_log("secretive", NS) == "env=s3cr3t\ns3cr3t\ntoken\n"
    api.core.delete_namespaced_pod("secretive", NS)
    assert api.core.list_namespaced_secret(NS).items == []  # collected with its owner
    assert api.server.writes == {("create", "pods"): 1, ("create", "secrets"): 1,
                                 ("delete", "pods"): 1}


def test_a_graceful_delete_stops_the_pod_and_collects_its_secret(
        api: Cluster, images: dict[str, str], tmp_path: Path) -> None:
    gate = tmp_path / "gate"
    gate.mkdir()
    body = pod("long", "trap 'while [ ! -e /gate/go ]; do sleep 0.1; done; exit 0' TERM; "
               "sleep 300 & wait", volumes=[{"name": "gate", "hostPath": {"path": str(gate)}}])
    body["spec"]["containers"][0]["volumeMounts"] = [{"name": "gate", "mountPath": "/gate"}]
    since = version(api)
    created = api.core.create_namespaced_pod(NS, body)
    api.core.create_namespaced_secret(NS, client.V1Secret(
        metadata=client.V1ObjectMeta(name="long-creds", owner_references=[
            client.V1OwnerReference(api_version="v1", kind="Pod", name="long",
                                    uid=created.metadata.uid)])))
    running = watch_pod(api, "long", since, phase_is("Running"))[-1]["object"]
    marked = api.core.delete_namespaced_pod("long", NS, grace_period_seconds=60)
    assert marked.metadata.deletion_timestamp
    assert marked.metadata.deletion_grace_period_seconds == 60
    # It got SIGTERM and is still terminating (its handler waits for the gate).
    assert api.core.read_namespaced_pod("long", NS).metadata.deletion_timestamp
    assert [s.metadata.name for s in api.core.list_namespaced_secret(NS).items] == ["long-creds"]
    (gate / "go").touch()
    events = watch_pod(api, "long", running.metadata.resource_version, deleted)
    last = events[-1]["object"].status.container_statuses[0].state.terminated
    assert last is not None and last.exit_code == 0  # left on its own, within the grace
    assert api.core.list_namespaced_secret(NS).items == []


@pytest.mark.parametrize("how", ["pod-group-name", "scheduling.k8s.io/group-name",
                                 "scheduling.x-k8s.io/pod-group", "kueue"])
def test_a_gang_starts_only_when_all_its_members_exist(
        api: Cluster, images: dict[str, str], how: str) -> None:
    groups = {"pod-group-name": ("scheduling.run.ai", "v2alpha2"),
              "scheduling.k8s.io/group-name": ("scheduling.volcano.sh", "v1beta1"),
              "scheduling.x-k8s.io/pod-group": ("scheduling.x-k8s.io", "v1alpha1")}
    if how in groups:
        group, version_ = groups[how]
        api.custom.create_namespaced_custom_object(group, version_, NS, "podgroups", {
            "apiVersion": f"{group}/{version_}", "kind": "PodGroup",
            "metadata": {"name": "gang"}, "spec": {"minMember": 2}})

    def member(name: str) -> dict[str, Any]:
        body = pod(name, "echo member")
        meta = body["metadata"]
        if how == "kueue":
            meta["labels"] = {"kueue.x-k8s.io/pod-group-name": "gang"}
            meta["annotations"] = {"kueue.x-k8s.io/pod-group-total-count": "2"}
        elif how == "scheduling.x-k8s.io/pod-group":
            meta["labels"] = {how: "gang"}
        else:
            meta["annotations"] = {how: "gang"}
        return body

    since = version(api)
    api.core.create_namespaced_pod(NS, member("first"))
    events = watch_pod(api, "first", since, lambda e: summary(e)[2] == "Unschedulable")
    waiting = {c.type: c for c in events[-1]["object"].status.conditions}["PodScheduled"]
    assert waiting.status == "False" and "has 1 of its minMember 2" in waiting.message
    assert not events[-1]["object"].spec.node_name
    api.core.create_namespaced_pod(NS, member("second"))
    for name in ("first", "second"):
        done = watch_pod(api, name, since, phase_is("Succeeded", "Failed"))[-1]["object"]
        assert done.status.phase == "Succeeded" and done.spec.node_name == "node-1"
        api.core.delete_namespaced_pod(name, NS)


def test_a_pod_that_does_not_fit_waits_until_a_node_can_take_it(
        api: Cluster, images: dict[str, str]) -> None:
    body = pod("big", "echo ran")
    body["spec"]["containers"][0]["resources"] = {"requests": {"cpu": "8", "memory": "1Gi"},
                                                  "limits": {"nvidia.com/gpu": "1"}}
    since = version(api)
    api.core.create_namespaced_pod(NS, body)
    events = watch_pod(api, "big", since, lambda e: summary(e)[2] == "Unschedulable")
    scheduled = {c.type: c for c in events[-1]["object"].status.conditions}["PodScheduled"]
    assert (scheduled.status, scheduled.reason) == ("False", "Unschedulable")
    assert scheduled.message == "0/1 nodes are available: 1 Insufficient cpu."
    assert events[-1]["object"].status.phase == "Pending"
    api.kubelet.add_node("node-2", cpu="16", memory="32Gi", gpus=1)
    done = watch_pod(api, "big", since, phase_is("Succeeded", "Failed"))[-1]["object"]
    assert done.status.phase == "Succeeded" and done.spec.node_name == "node-2"
    api.core.delete_namespaced_pod("big", NS)


def test_an_image_that_cannot_be_pulled(api: Cluster, images: dict[str, str]) -> None:
    since = version(api)
    api.core.create_namespaced_pod(NS, pod("nopull", image="nvcr.io/nvidia/nosuch:1.0"))
    events = watch_pod(api, "nopull", since, lambda e: summary(e)[2] == "ImagePullBackOff")
    pulls = [e["object"].status.container_statuses[0].state.waiting for e in events
             if summary(e)[2] == "ErrImagePull"]
    assert pulls and "nvcr.io" in pulls[0].message
    assert events[-1]["object"].status.phase == "Pending"
    with pytest.raises(ApiException) as waiting:
        api.core.read_namespaced_pod_log("nopull", NS)
    assert "is waiting to start: ImagePullBackOff" in waiting.value.body
    api.core.delete_namespaced_pod("nopull", NS, grace_period_seconds=0)


def test_a_container_over_its_memory_limit_is_oomkilled(
        api: Cluster, images: dict[str, str]) -> None:
    body = pod("hog", "x=0123456789abcdef; while true; do x=$x$x; done")
    body["spec"]["containers"][0]["resources"] = {"limits": {"memory": "20Mi"}}
    since = version(api)
    left = Path("oom").exists()  # conmon's mark of an OOM kill, in its working folder
    api.core.create_namespaced_pod(NS, body)
    done = watch_pod(api, "hog", since, phase_is("Succeeded", "Failed"))[-1]["object"]
    ended = done.status.container_statuses[0].state.terminated
    assert (done.status.phase, ended.exit_code, ended.reason) == ("Failed", 137, "OOMKilled")
    assert left or not Path("oom").exists()  # in the node's folder, not the test's
    api.core.delete_namespaced_pod("hog", NS)


def test_init_failures_and_native_sidecars(api: Cluster, images: dict[str, str]) -> None:
    broken = pod("broken", "echo never", initContainers=[
        {"name": "fetch", "image": BUSYBOX, "command": ["sh", "-c", "exit 3"]}])
    with_sidecar = pod("sidecar", "echo main-done", initContainers=[
        {"name": "collector", "image": BUSYBOX, "restartPolicy": "Always",
         "command": ["sh", "-c", "trap 'exit 0' TERM; sleep 300 & wait"]}])
    since = version(api)
    api.core.create_namespaced_pod(NS, broken)
    api.core.create_namespaced_pod(NS, with_sidecar)
    failed = watch_pod(api, "broken", since, phase_is("Succeeded", "Failed"))[-1]["object"]
    assert failed.status.phase == "Failed"
    init = failed.status.init_container_statuses[0].state.terminated
    assert (init.exit_code, init.reason) == (3, "Error")
    assert failed.status.container_statuses[0].state.waiting.reason == "PodInitializing"
    done = watch_pod(api, "sidecar", since, lambda e: phase_is("Succeeded", "Failed")(e) and all(
        "terminated" in s["state"] for s in e["raw_object"]["status"]["initContainerStatuses"]))
    assert done[-1]["object"].status.phase == "Succeeded"
    assert api.core.read_namespaced_pod_log("sidecar", NS, container="main") == "main-done\n"
    for name in ("broken", "sidecar"):
        api.core.delete_namespaced_pod(name, NS)


def test_a_deleted_pods_name_is_free_again_at_once(api: Cluster, images: dict[str, str]) -> None:
    # podman keeps a deleted pod until the node's next sweep: a new pod of that name must
    # not wait for it, nor fail on podman's name being taken
    for round_ in ("first", "second"):
        since = version(api)
        api.core.create_namespaced_pod(NS, pod("again", f"echo {round_}"))
        events = watch_pod(api, "again", since, phase_is("Succeeded", "Failed"))
        assert events[-1]["object"].status.phase == "Succeeded", [summary(e) for e in events]
        assert api.core.read_namespaced_pod_log("again", NS) == f"{round_}\n"
        since = events[-1]["object"].metadata.resource_version
        api.core.delete_namespaced_pod("again", NS, grace_period_seconds=0)
        assert watch_pod(api, "again", since, deleted)[-1]["type"] == "DELETED"


def test_a_cri_log_file_is_served_as_the_kubelet_serves_it(tmp_path: Path) -> None:
    log = tmp_path / "ctr.log"
    log.write_bytes(b"2026-11-27T19:58:13.128436922+00:00 stdout F one\n"
                    b"2026-11-27T19:58:13.2+00:00 stderr P tw\n"
                    b"2026-11-27T19:58:13.3+00:00 stdout F o\n"
                    b"2026-11-27T19:58:13.4+00:00 stdout F \n"
                    b"2026-11-27T19:58:13.5+00:00 stdout F thr")  # still being written

    def read(**how: Any) -> bytes:
        return b"".join(read_log(str(log), ended=lambda: True, **how))
    assert read(follow=False, tail=None, timestamps=False) == b"one\ntwo\n\n"
    assert read(follow=False, tail=1, timestamps=False) == b"\n"
    assert read(follow=False, tail=0, timestamps=False) == b""
    assert read(follow=False, tail=1, timestamps=True) == b"2026-11-27T19:58:13.4Z \n"
    over = threading.Event()
    lines = read_log(str(log), follow=True, tail=None, timestamps=False, ended=over.is_set)
    assert next(lines) == b"one\ntwo\n\n"
    with log.open("ab") as more:
        more.write(b"ee\n2026-11-27T19:58:13.6+00:00 stdout F four\n")
    over.set()
    assert b"".join(lines) == b"three\nfour\n"
    assert read(follow=True, tail=None, timestamps=False) == b"one\ntwo\n\nthree\nfour\n"
    assert read(follow=False, tail=None, timestamps=False) == b"one\ntwo\n\nthree\nfour\n"
    assert b"".join(read_log(str(tmp_path / "none"), follow=True, tail=None,
                             timestamps=False, ended=lambda: True)) == b""


# ---------------------------------------------------------------------- exec and port-forward


def _recv_until(sock: Any, want: bytes, timeout: float = 30) -> bytes:
    sock.settimeout(timeout)
    got = b""
    while want not in got:
        data = sock.recv(65536)
        if not data:
            break
        got += data
    return got


def test_exec_and_port_forward_reach_the_pods_container(
        api: Cluster, images: dict[str, str]) -> None:
    """The real client's ``stream`` (exec) and ``portforward`` on the stand-in's WebSocket:
    a command's streams and exit code, and bytes both ways to a port the pod listens on."""
    from kubernetes.stream import portforward, stream

    from osmo.config import free_port

    port, closed = free_port(0), free_port(0)
    since = version(api)
    api.core.create_namespaced_pod(NS, pod("web", f"exec nc -ll -p {port} -e cat"))
    watch_pod(api, "web", since, phase_is("Running", "Failed", "Succeeded"))
    run = stream(api.core.connect_get_namespaced_pod_exec, "web", NS, container="main",
                 command=["sh", "-c", "read x; echo out-$x; echo err >&2; exit 3"],
                 stdin=True, stdout=True, stderr=True, tty=False, _preload_content=False)
    try:
        run.write_stdin("hi\n")
        run.run_forever(timeout=60)
        assert (run.read_stdout(), run.read_stderr(), run.returncode) == (
            "out-hi\n", "err\n", 3)
    finally:
        run.close()
        run.sock.shutdown()  # websocket-client's close() leaves a socket the server closed open
    forward = portforward(api.core.connect_get_namespaced_pod_portforward, "web", NS,
                          ports=str(port))
    sock = forward.socket(port)
    try:
        for _ in range(2):  # one connection, several exchanges
            sock.sendall(b"ping\n" + bytes(range(256)) * 400)
            assert _recv_until(sock, bytes(range(256)) * 400) == \
                b"ping\n" + bytes(range(256)) * 400
        assert forward.error(port) is None
    finally:
        forward.close()
    refused = portforward(api.core.connect_get_namespaced_pod_portforward, "web", NS,
                          ports=str(closed))
    try:  # nothing listens there: the connection ends, the error channel says why
        assert _recv_until(refused.socket(closed), b"never") == b""
        assert "error forwarding port" in (refused.error(closed) or ""), refused.error(closed)
    finally:
        refused.close()
    api.core.delete_namespaced_pod("web", NS, grace_period_seconds=0)


def test_port_forward_requests_the_server_refuses(api: Cluster) -> None:
    from kubernetes.stream import portforward

    api.core.create_namespaced_pod(NS, unplaceable("waiting"))
    for name, ports, code in (("waiting", "80", 400), ("nobody", "80", 404)):
        with pytest.raises(ApiException) as refused:
            portforward(api.core.connect_get_namespaced_pod_portforward, name, NS, ports=ports)
        assert str(code) in str(refused.value), refused.value
    with pytest.raises(ApiException) as plain:  # not a WebSocket: the real answer
        api.core.connect_get_namespaced_pod_portforward("waiting", NS, ports="80")
    assert plain.value.status == 400 and "Upgrade request required" in plain.value.body
