"""OSMO's tutorials end to end through pods: ``osmo submit`` to a server whose only worker is
``osmo worker --runtime kubernetes``, its pods created through the official client against
the API stand-in and run under ``podman kube play`` with the offline test images.

Each tutorial must complete with its tasks' lines in ``osmo logs``, its outputs recorded
(lineage), and no pod, Secret or Service left in the API (nor anything in podman: the
fixture checks at the end).
"""

from __future__ import annotations

import base64
import json
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from kubernetes import client, watch

from tests.conftest import REPO
from tests.containers.conftest import images, podman_env  # noqa: F401 - fixtures
from tests.containers.images import KINDS_OSMO, OSMO_IMAGE, ensure_images
from tests.containers.submitting import (
    check_serial_tutorial,
    lineage_of,
    osmo_lines,
    submitted_id,
    task_lines,
    tasks,
)
from tests.k8s.nodes import NAMESPACE, KubeCluster, started
from tests.k8s.scripts import Script, running, scheduled, wait
from tests.k8s.store import (
    COSCHEDULING,
    KAI,
    PODS,
    SECRETS,
    SERVICES,
    Resource,
)

TUTORIALS = Path(__file__).parent.parent / "containers" / "osmo_tutorials"


@pytest.fixture(scope="module")
def kube(tmp_path_factory: pytest.TempPathFactory, podman_env: dict[str, str],  # noqa: F811
         images: dict[str, str]) -> Iterator[KubeCluster]:  # noqa: F811
    for cluster in started(tmp_path_factory.mktemp("k8s"), podman_env):
        # the stand-in runs every pod on this host's network: {{host:X}} is X's node address
        cluster.start_worker("kube-1", groupNetwork="host")
        yield cluster


def run(kube: KubeCluster, name: str) -> tuple[str, dict[str, list[str]], dict[str, dict]]:
    """Submit a tutorial and wait; its id, its tasks' lines and query rows."""
    r = kube.osmo("submit", str(TUTORIALS / name), "--wait", timeout=300)
    wf_id = submitted_id(r.out)
    lines, rows = task_lines(kube.osmo, wf_id), tasks(kube.osmo, wf_id)
    assert r.code == 0, f"{r.out}{r.err}{lines}{rows}\n{kube.osmo_cluster.worker_log('kube-1')}"
    assert {row["status"] for row in rows.values()} == {"COMPLETED"}
    assert nothing_left(kube) == []
    return wf_id, lines, rows


def nothing_left(kube: KubeCluster, timeout: float = 20) -> list[str]:
    """What the API still holds once ``timeout`` passed (or nothing)."""
    deadline = time.monotonic() + timeout
    while (left := kube.left()) and time.monotonic() < deadline:
        time.sleep(0.2)
    return left


def test_hello_world_runs_as_a_pod(kube: KubeCluster) -> None:
    wf_id, lines, _ = run(kube, "hello_world.yaml")
    assert lines["hello"] == ["Hello from OSMO!"]
    osmo_log = kube.osmo("logs", wf_id, check=True).out
    assert "pod osmo-" in osmo_log and "namespace osmo-tasks" in osmo_log, osmo_log
    node = kube.osmo_cluster.nodes()["kube-1"]
    assert node["runtime"] == "kubernetes (namespace osmo-tasks)", node
    # its capacity is the stand-in node's allocatable (8 cpu, 16Gi, 1 GPU), not this machine's
    assert (node["total"]["cpu"], node["total"]["gpu"], node["total"]["memory"]) == (
        8.0, 1, 16 << 30), node


def test_serial_workflow_hands_outputs_on_between_pods(kube: KubeCluster) -> None:
    wf_id, lines, rows = run(kube, "serial_workflow.yaml")
    assert len(lines["task1"]) == 1 and re.fullmatch(r"Hello from task1 \S+", lines["task1"][0])
    check_serial_tutorial(lines, rows)
    lineage = lineage_of(kube.osmo, f"{wf_id}:task3")
    assert lineage["image"] == "ubuntu:24.04" or lineage.get("image_id"), lineage


def test_parallel_tasks_run_as_pods(kube: KubeCluster) -> None:
    _, lines, _ = run(kube, "parallel_tasks.yaml")
    for name in ("task-a", "task-b", "task-c"):
        assert lines[name] == [f"Hello from {name}"]


def test_combination_workflow_simple(kube: KubeCluster) -> None:
    _, lines, rows = run(kube, "combination_workflow_simple.yaml")
    samples = [f"sample_{i},value_{i}" for i in range(1, 11)]
    csv = Path(rows["generate-data"]["output"]) / "data" / "training_data.csv"
    assert csv.read_text().splitlines() == samples
    assert lines["train-model-a"] == ["Training Model A...", *samples, "✓ Model A complete!"]



FILES = """\
workflow:
  name: files
  tasks:
  - name: f
    image: alpine:3.18
    command: ["sh", "-c", "for f in /etc/osmo-test/config.txt rel.txt; do cat $f; echo; done; pwd; id -u; echo x > {{output}}/o"]
    files:
    - path: /etc/osmo-test/config.txt
      contents: hello-abs
    - path: rel.txt
      contents: hello-rel
"""


def test_files_at_their_paths_as_a_non_root_user(kube: KubeCluster, tmp_path: Path) -> None:
    spec = tmp_path / "files.yaml"
    spec.write_text(FILES)
    r = kube.osmo("submit", str(spec), "--wait", timeout=180)
    wf_id = submitted_id(r.out)
    lines = task_lines(kube.osmo, wf_id)
    assert r.code == 0, (r.out, r.err, lines)
    assert lines["f"] == ["hello-abs", "hello-rel", "/osmo/run/work", "1000"], lines
    assert (Path(tasks(kube.osmo, wf_id)["f"]["output"]) / "o").read_text() == "x\n"


def test_group_tasks_communication_lead_first(kube: KubeCluster) -> None:
    _, lines, _ = run(kube, "group_tasks_communication.yaml")
    assert lines["client"][0] == "Client: Starting..."
    assert lines["client"][2:] == ["Received from server: hello", "Client: Complete"]
    assert lines["server"] == ["Server: Starting...", "Server: Complete"]



def test_group_tasks_run_as_a_kai_gang(kube: KubeCluster) -> None:
    kube.start_worker("kube-gang", pool="gang", gang="kai", groupNetwork="host")
    before = kube.server.calls[("create", "podgroups.scheduling.run.ai")]
    r = kube.osmo("submit", str(TUTORIALS / "group_tasks.yaml"), "--pool", "gang", "--wait",
                  timeout=300)
    wf_id = submitted_id(r.out)
    assert r.code == 0, r.out + r.err + kube.osmo_cluster.worker_log("kube-gang")
    lines = task_lines(kube.osmo, wf_id)
    said = [line for line in lines["processor-2"] if not line.startswith("osmo: ")]
    assert said[0] == "Processor 2: Starting..."
    assert kube.server.calls[("create", "podgroups.scheduling.run.ai")] == before + 1
    assert nothing_left(kube) == []  # the PodGroup went with the group's last member



def test_a_missing_image_fails_to_start_with_a_pull_secret_of_its_own(
        kube: KubeCluster, tmp_path: Path) -> None:
    password = f"pw-{uuid.uuid4().hex}"
    kube.osmo("credential", "set", "registry://registry.invalid", "--payload", "username=me",
              "--payload", f"password={password}", check=True)
    spec = tmp_path / "missing.yaml"
    spec.write_text('workflow:\n  name: missing\n  tasks:\n  - name: pulled\n'
                    '    image: registry.invalid/osmo/nothing:1\n    command: ["true"]\n')
    since = str(kube.server.store.list(SECRETS)[1])
    r = kube.osmo("submit", str(spec), "--wait", timeout=180)
    wf_id = submitted_id(r.out)
    row = tasks(kube.osmo, wf_id)["pulled"]
    assert row["status"] == "FAILED_START_ERROR", row
    assert "image pull failed" in row["message"], row
    with client.ApiClient(client.Configuration(host=kube.server.url)) as api:
        made = [e["raw_object"] for e in watch.Watch().stream(
            client.CoreV1Api(api).list_namespaced_secret, NAMESPACE, resource_version=since,
            timeout_seconds=1) if e["type"] == "ADDED"]
    (secret,) = made  # made before its pod, deleted after it
    assert secret["type"] == "kubernetes.io/dockerconfigjson"
    auths = json.loads(base64.b64decode(secret["data"][".dockerconfigjson"]))["auths"]
    assert auths["registry.invalid"]["password"] == password
    everything = json.dumps(kube.osmo.query(wf_id)) + kube.osmo("logs", wf_id).out
    assert password not in everything
    assert nothing_left(kube) == []


SLEEPER = """\
workflow:
  name: sleeper
  tasks:
  - name: t
    image: alpine:3.18
    command: ["sh", "-c", "echo ready; exec sleep 300"]
    environment: {GREETING: hola}
"""


def test_exec_and_cancel_reach_the_pod(kube: KubeCluster, tmp_path: Path) -> None:
    spec = tmp_path / "sleeper.yaml"
    spec.write_text(SLEEPER)
    wf_id = kube.osmo.submit(spec)
    deadline = time.monotonic() + 60
    while not running_pods(kube) and time.monotonic() < deadline:
        time.sleep(0.1)
    r = kube.osmo("workflow", "exec", wf_id, "t", "--", "sh", "-c",
                  'echo "$GREETING $OSMO_TASK"; echo oops >&2; exit 7')
    assert (r.code, r.out, r.err) == (7, "hola t\n", "oops\n"), r
    proc = subprocess.run([sys.executable, "-m", "osmo", "workflow", "exec", wf_id, "t", "--",
                           "wc", "-c"], input=b"x" * 100_000, capture_output=True,
                          env=kube.osmo.env, cwd=REPO, timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip() == b"100000", proc.stderr
    started = time.monotonic()
    assert kube.osmo("cancel", wf_id).code == 0
    info = kube.osmo.wait_for(wf_id, lambda i: i["status"] not in ("RUNNING", "PENDING"))
    assert info["status"] != "COMPLETED", info
    assert nothing_left(kube) == [] and time.monotonic() - started < 30
    deletes = [k for k in kube.server.calls if k[0] == "delete" and k[1] == "pods"]
    assert deletes, kube.server.calls


WAITER = """\
workflow:
  name: waiter
  resources:
    default: {cpu: 2, memory: 1Gi}
  tasks:
  - name: w
    image: alpine:3.18
    command: ["sh", "-c", "echo started; sleep 2; echo done"]
"""


def hog(kube: KubeCluster, cpu: str, release: threading.Event) -> str:
    """A pod that is not osmo's, bound to node-1 with ``cpu`` requested until ``release``."""
    name = f"hog-{uuid.uuid4().hex[:6]}"
    kube.kubelet.script(name, Script((scheduled(), running(), wait(release))), NAMESPACE)
    core = client.CoreV1Api(client.ApiClient(client.Configuration(host=kube.server.url)))
    core.create_namespaced_pod(NAMESPACE, {
        "apiVersion": "v1", "kind": "Pod", "metadata": {"name": name},
        "spec": {"containers": [{"name": "hog", "image": "busybox",
                                 "resources": {"requests": {"cpu": cpu}}}]}})
    return name


def test_query_and_events_show_why_a_pod_waits(kube: KubeCluster, tmp_path: Path) -> None:
    """The scheduler's reason is the running task's waiting reason in osmo query and one
    event in osmo events while its pod waits; it goes once capacity frees and the pod runs."""
    spec = tmp_path / "waiter.yaml"
    spec.write_text(WAITER)
    release = threading.Event()
    name = hog(kube, "7", release)  # node-1 has 8 cpus: the task's 2 do not fit
    core = client.CoreV1Api(client.ApiClient(client.Configuration(host=kube.server.url)))
    try:
        wf_id = kube.osmo.submit(spec)
        info = kube.osmo.wait_for(wf_id, lambda i: i["tasks"][0].get("waiting") is not None,
                                  timeout=60)
        row = info["tasks"][0]
        assert row["status"] == "RUNNING", row
        assert row["waiting"]["reason"] == (
            "unschedulable: 0/1 nodes are available: 1 Insufficient cpu."), row
        assert "Insufficient cpu" in kube.osmo("query", wf_id, check=True).out
        assert "Insufficient cpu" in kube.osmo("events", wf_id, check=True).out
    finally:
        release.set()
        core.delete_namespaced_pod(name, NAMESPACE, grace_period_seconds=0)
    info = kube.osmo.wait_for(wf_id, lambda i: i["status"] in ("COMPLETED", "FAILED"),
                              timeout=120)
    assert info["status"] == "COMPLETED", info
    assert info["tasks"][0].get("waiting") is None and info["tasks"][0]["message"] == "", info
    events = kube.osmo("events", wf_id, check=True).out
    assert events.count("Insufficient cpu") == 1, events  # once, not per watch event
    assert "waits no more" in events, events
    assert "started" in "".join(task_lines(kube.osmo, wf_id).get("w", []))
    assert nothing_left(kube) == []


PLATFORMS = """\
workflow:
  name: platforms
  resources:
    gpu: {platform: gpu, cpu: 1, gpu: 1, memory: 1Gi}
    cpu: {platform: cpu, cpu: 6, memory: 1Gi}
  tasks:
  - name: on-gpu
    image: alpine:3.18
    resource: gpu
    command: ["sh", "-c", "echo gpu"]
  - name: on-cpu
    image: alpine:3.18
    resource: cpu
    command: ["sh", "-c", "echo cpu"]
"""
KIND = "osmo.dev/test-kind"


def test_a_node_serves_each_platform_of_its_nodes_labels(kube: KubeCluster,
                                                         tmp_path: Path) -> None:
    """Platforms from node labels: registered with their own capacity, shown by osmo
    resource list, and each task's pod goes to a node of its platform."""
    kube.kubelet.add_node("gpu-1", cpu="4", memory="8Gi", gpus=2, labels={KIND: "gpu"})
    kube.kubelet.add_node("cpu-1", cpu="8", memory="16Gi", labels={KIND: "cpu"})
    bound: dict[str, str] = {}

    def seen(event: Any) -> None:
        labels = event.obj.get("metadata", {}).get("labels") or {}
        if event.res == PODS and event.obj.get("spec", {}).get("nodeName"):
            bound.setdefault(labels.get("osmo.dev/task", ""), event.obj["spec"]["nodeName"])

    kube.server.store.listen(seen)
    kube.start_worker("kube-p", pool="plat", groupNetwork="host", platforms={
        "gpu": {"nodeSelector": {KIND: "gpu"}}, "cpu": {"nodeSelector": {KIND: "cpu"}}})
    node = kube.osmo_cluster.nodes()["kube-p"]
    assert {name: (p["total"]["cpu"], p["total"]["gpu"])
            for name, p in node["platforms"].items()} == {"gpu": (4, 2), "cpu": (8, 0)}, node
    listed = kube.osmo("resource", "list", check=True).out
    assert "platform gpu" in listed and "platform cpu" in listed, listed
    spec = tmp_path / "platforms.yaml"
    spec.write_text(PLATFORMS)
    r = kube.osmo("submit", str(spec), "--pool", "plat", "--wait", timeout=300)
    assert r.code == 0, r.out + r.err
    assert {bound.get("on-gpu"), bound.get("on-cpu")} == {"gpu-1", "cpu-1"}, bound
    assert (bound["on-gpu"], bound["on-cpu"]) == ("gpu-1", "cpu-1"), bound
    spec.write_text(PLATFORMS.replace("platform: cpu", "platform: arm"))
    r = kube.osmo("submit", str(spec), "--pool", "plat")
    assert r.code == 2, r.out + r.err
    assert ("requests platform 'arm' but no node in pool 'plat' has it (platforms: cpu, gpu)"
            in r.err), r.err
    assert nothing_left(kube) == []


CHAOS = """\
workflow:
  name: chaos
  tasks:
  - name: slow
    image: alpine:3.18
    command: ["sh", "-c", "echo started; sleep 8; echo survived > {{output}}/x; echo done"]
"""


def running_pods(kube: KubeCluster) -> list[str]:
    return [obj["metadata"]["name"] for _, obj in kube.server.store.objects([PODS])
            if (obj.get("status") or {}).get("phase") == "Running"]


def test_a_killed_node_adopts_its_pod_which_runs_once_and_leaves_nothing(
        kube: KubeCluster, tmp_path: Path) -> None:
    """Chaos (last in this module: it restarts the worker): SIGKILL of the node mid-run.
    Its pod runs on; the restarted node adopts it (no second pod is created), its log is
    whole with no line twice, its output is promoted; what else its previous life left
    goes, another instance's stays."""
    spec = tmp_path / "chaos.yaml"
    spec.write_text(CHAOS)
    wf_id = kube.osmo.submit(spec)
    kube.osmo.wait_for(wf_id, lambda info: any(
        t["status"] == "RUNNING" for t in info["tasks"]))
    deadline = time.monotonic() + 60
    while "started" not in task_lines(kube.osmo, wf_id).get("slow", []):
        assert time.monotonic() < deadline, kube.left()
        time.sleep(0.1)
    assert running_pods(kube), kube.left()
    (pod,) = [obj for _, obj in kube.server.store.objects([PODS])]
    instance = pod["metadata"]["labels"]["osmo.dev/instance"]
    created = kube.server.writes[("create", "pods")]
    kube.osmo_cluster.signal("kube-1", signal.SIGKILL)
    kube.osmo_cluster.workers["kube-1"].wait(30)
    assert running_pods(kube)  # a dead node's pods run on
    foreign = leave_remains(kube, instance)
    kube.start_worker("kube-1")  # it adopts its pod, deletes the rest by label
    info = kube.osmo.wait_for(wf_id, lambda i: i["status"] in ("COMPLETED", "FAILED"),
                              timeout=180)
    assert info["status"] == "COMPLETED", info
    row = info["tasks"][0]
    assert row["retry"] == 0, row
    assert (Path(row["output"]) / "x").read_text() == "survived\n"
    assert kube.server.writes[("create", "pods")] == created, "one pod, never created again"
    assert task_lines(kube.osmo, wf_id)["slow"] == ["started", "done"]
    said = osmo_lines(kube.osmo, wf_id, "slow")
    assert any("adopted by node kube-1 after its restart" in line for line in said), said
    try:  # another instance's stay
        assert sorted(nothing_left(kube, timeout=5)) == sorted(
            f"{res.kind}/{name}" for res, name in foreign)
    finally:
        for res, name in foreign:
            kube.server.store.delete(res, NAMESPACE, name)
    assert nothing_left(kube) == []


MAKES = """\
workflow:
  name: makes
  tasks:
  - name: make
    image: alpine:3.18
    command: ["sh", "-c", "echo precious-{tag} > {{{{output}}}}/kept.txt"]
"""
READS = """\
workflow:
  name: reads
  tasks:
  - name: read
    image: alpine:3.18
    command: ["sh", "-c", "cat {{{{input:0}}}}/kept.txt"]
    inputs:
    - task: {upstream}:make
"""


def test_a_tampered_input_fails_the_start_naming_it(kube: KubeCluster, data_pool: str,
                                                    tmp_path: Path) -> None:
    tag = uuid.uuid4().hex
    spec = tmp_path / "makes.yaml"
    spec.write_text(MAKES.format(tag=tag))
    r = kube.osmo("submit", str(spec), "--pool", data_pool, "--wait", timeout=180)
    assert r.code == 0, r.out + r.err
    upstream = submitted_id(r.out)
    content = f"precious-{tag}\n".encode()
    blobs = [p for p in kube.osmo_cluster.root.rglob("*") if p.is_file()
             and not p.is_symlink() and p.stat().st_size == len(content)
             and p.read_bytes() == content and "artifacts" in p.parts]
    assert blobs, "the output's blob was not found in any store"
    for blob in blobs:  # bit rot in the stores (hard links of one another on this host)
        blob.chmod(0o644)
        blob.write_bytes(b"X" * len(content))
    spec = tmp_path / "reads.yaml"
    spec.write_text(READS.format(upstream=upstream))
    r = kube.osmo("submit", str(spec), "--pool", data_pool, "--wait", timeout=180)
    row = tasks(kube.osmo, submitted_id(r.out))["read"]
    assert r.code == 1 and row["status"] == "FAILED_START_ERROR", (r.out, r.err, row)
    assert "now hashes to" in row["message"] and "it was not used" in row["message"], row
    assert nothing_left(kube) == []


GANG = "osmo-wf-crashed-gang"


# ---------------------------------------------------------------- pods with their own data

@pytest.fixture(scope="module")
def data_pool(kube: KubeCluster, podman_env: dict[str, str]) -> str:  # noqa: F811
    """A worker whose pods share no volume with it: osmo's image fetches and collects."""
    ensure_images(podman_env, KINDS_OSMO)
    kube.start_worker("kube-data", pool="data", groupNetwork="host",
                      data={"image": OSMO_IMAGE})
    return "data"


def test_serial_workflow_with_no_shared_volume(kube: KubeCluster, data_pool: str) -> None:
    made: list[dict] = []
    kube.server.store.listen(lambda e: made.append(e.obj) if (
        e.res == PODS and e.type == "ADDED") else None)
    r = kube.osmo("submit", str(TUTORIALS / "serial_workflow.yaml"), "--pool", data_pool,
                  "--no-cache", "--wait", timeout=300)
    wf_id = submitted_id(r.out)
    lines, rows = task_lines(kube.osmo, wf_id), tasks(kube.osmo, wf_id)
    assert r.code == 0, f"{r.out}{r.err}{lines}{rows}\n" + kube.osmo_cluster.worker_log(
        "kube-data")
    check_serial_tutorial(lines, rows)
    assert len(made) == 3
    for pod in made:
        spec = pod["spec"]
        assert [v for v in spec["volumes"] if "hostPath" in v or "persistentVolumeClaim" in v
                ] == [], spec["volumes"]
        assert [c["name"] for c in spec["initContainers"]] == ["osmo-fetch"]
        task = next(c for c in spec["containers"] if c["name"] == "task")
        assert "osmo-tickets" not in json.dumps(task), task  # the task never sees a ticket
    assert nothing_left(kube) == []


FAILS = """\
workflow:
  name: fails
  tasks:
  - name: broken
    image: alpine:3.18
    command: ["sh", "-c", "echo half > {{output}}/half.txt; exit 3"]
  - name: after
    image: alpine:3.18
    command: ["sh", "-c", "cat {{input:0}}/half.txt"]
    inputs:
    - task: broken
"""


def test_a_failed_pod_hands_nothing_on(kube: KubeCluster, data_pool: str,
                                       tmp_path: Path) -> None:
    spec = tmp_path / "fails.yaml"
    spec.write_text(FAILS)
    r = kube.osmo("submit", str(spec), "--pool", data_pool, "--wait", timeout=180)
    rows = tasks(kube.osmo, submitted_id(r.out))
    assert r.code == 1, (r.out, r.err, rows)
    assert (rows["broken"]["status"], rows["broken"]["exit_code"]) == ("FAILED", 3), rows
    assert not rows["broken"].get("output"), rows
    assert rows["after"]["status"] == "FAILED_UPSTREAM", rows
    assert nothing_left(kube) == []


def leave_remains(kube: KubeCluster, instance: str) -> list[tuple[Resource, str]]:
    """What a crashed life of ``instance`` leaves beside its pods (a pull Secret made before
    a pod that never came, a gang's Service and PodGroups); the same objects of another
    instance too, which must stay. Returns the other instance's."""
    with client.ApiClient(client.Configuration(host=kube.server.url)) as api:
        core, custom = client.CoreV1Api(api), client.CustomObjectsApi(api)
        for owner in (instance, "another-instance"):
            suffix = "" if owner == instance else "-other"
            labels = {"osmo.dev/instance": owner, "osmo.dev/group": GANG + suffix}
            meta = {"labels": labels, "namespace": NAMESPACE}
            core.create_namespaced_secret(NAMESPACE, {
                "metadata": {**meta, "name": f"osmo-pull{suffix}"},
                "type": "kubernetes.io/dockerconfigjson",
                "data": {".dockerconfigjson": base64.b64encode(b'{"auths": {}}').decode()}})
            core.create_namespaced_service(NAMESPACE, {
                "metadata": {**meta, "name": GANG + suffix},
                "spec": {"clusterIP": "None", "selector": {"osmo.dev/group": GANG}}})
            for res in (KAI, COSCHEDULING):
                custom.create_namespaced_custom_object(
                    res.group, res.version, NAMESPACE, res.plural,
                    {"apiVersion": f"{res.group}/{res.version}", "kind": "PodGroup",
                     "metadata": {**meta, "name": GANG + suffix}, "spec": {"minMember": 2}})
    assert len([k for k in kube.left() if not k.startswith("Pod/")]) == 2 * 4
    return [(SECRETS, "osmo-pull-other"), (SERVICES, f"{GANG}-other"),
            (KAI, f"{GANG}-other"), (COSCHEDULING, f"{GANG}-other")]


REPLACED = """\
workflow:
  name: replaced
  tasks:
  - name: slow
    image: alpine:3.18
    command: ["sh", "-c", "echo started; sleep 6; echo ran > {{output}}/x; echo done"]
"""


def test_a_replaced_worker_deletes_what_its_predecessor_left_and_the_attempt_runs_again(
        kube: KubeCluster, data_pool: str, tmp_path: Path) -> None:
    """Chaos (last in this module: it replaces the data pool's worker): the chart's
    StatefulSet replaces a lost worker pod by one of the same name on a fresh home (an
    emptyDir; same host name and home path, so the same instance). The SIGKILLed worker's
    pod is deleted by the new one (its Secret, which the pod owns, goes with it), and the
    attempt runs again there."""
    spec = tmp_path / "replaced.yaml"
    spec.write_text(REPLACED)
    wf_id = kube.osmo.submit(spec, "--pool", data_pool)
    deadline = time.monotonic() + 90
    while "started" not in task_lines(kube.osmo, wf_id).get("slow", []):
        assert time.monotonic() < deadline, (kube.left(), kube.osmo.query(wf_id))
        time.sleep(0.2)
    (pod,) = [obj for _, obj in kube.server.store.objects([PODS])]
    old = {f"{res.kind}/{obj['metadata']['name']}" for res, obj in kube.server.store.objects(
        [PODS, SECRETS]) if obj["metadata"]["labels"].get("osmo.dev/attempt")
        == pod["metadata"]["labels"]["osmo.dev/attempt"]}
    assert len(old) == 2 and any(k.startswith("Secret/") for k in old), kube.left()
    kube.osmo_cluster.signal("kube-data", signal.SIGKILL)
    kube.osmo_cluster.workers["kube-data"].wait(30)
    assert running_pods(kube) == [pod["metadata"]["name"]]  # a dead node's pod runs on
    home = kube.osmo_cluster.root / "kube-data"
    shutil.rmtree(home)  # the replacement's fresh emptyDir, at the same path
    home.mkdir()
    kube.start_worker("kube-data", pool=data_pool, groupNetwork="host",
                      data={"image": OSMO_IMAGE})
    info = kube.osmo.wait_for(wf_id, lambda i: i["status"] in ("COMPLETED", "FAILED"),
                              timeout=180)
    assert info["status"] == "COMPLETED", (info, kube.osmo_cluster.worker_log("kube-data"))
    row = info["tasks"][0]
    assert row["retry"] == 1, row  # lost with its node: run again as a new retry
    assert (Path(row["output"]) / "x").read_text() == "ran\n"
    assert task_lines(kube.osmo, wf_id)["slow"][-2:] == ["started", "done"]
    log = kube.osmo_cluster.worker_log("kube-data")
    cancelled = re.findall(r"cancelled (\S+) that this node's previous life left", log)
    assert cancelled == [f"pod/{pod['metadata']['name']}"], log  # its Secret went with it
    assert old.isdisjoint(kube.left()), kube.left()
    assert nothing_left(kube) == []
