"""Golden manifests of the Kubernetes runtime (``osmo.runtime.kubernetes.manifest``): a task,
a GPU task, credentials and registry credentials, a group under each gang scheduler. Each is
compared with its file in ``golden/`` (``OSMO_UPDATE_GOLDEN=1`` rewrites them) and checked
against the strict Kubernetes 1.33 schema (``kubernetes-validate``) and the API server's own
rules (names, labels: ``tests/k8s/validation.py``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import pytest

from osmo.errors import UsageError
from osmo.runtime.container.run import Mount, RegistryAuth
from osmo.runtime.kubernetes.config import GANGS, KubePool, Placement, load_pool
from osmo.runtime.kubernetes.manifest import (
    GroupPlan,
    ManifestError,
    PodPlan,
    label_value,
    object_name,
    pod_group_manifest,
    pod_manifest,
    secret_manifest,
    service_manifest,
)
from tests.k8s.validation import SchemaCheck, check

GOLDEN = Path(__file__).parent / "golden"
SCHEMA = SchemaCheck("1.33")
POOL = KubePool(namespace="osmo-tasks", placement=Placement({"osmo.dev/pool": "robots"}),
                platforms={"dgx": Placement({"nvidia.com/gpu.product": "H100"}, (
                    {"key": "nvidia.com/gpu", "operator": "Exists", "effect": "NoSchedule"},))},
                priority_classes={"default": "osmo-normal"}, image_pull_secrets=("regcred",))
RUN = Path("/var/lib/osmo/runs/wf-1/train/0")


def plan(**extra: Any) -> PodPlan:
    fields: dict[str, Any] = dict(
        attempt_id="wf-1:train:0", workflow_id="wf-1", task="train", retry=0,
        instance="a1b2c3", image="nvcr.io/nvidia/pytorch:24.05-py3",
        argv=("python", "train.py", "--out", "/osmo/data/output"),
        env={"EPOCHS": "3", "OSMO_OUTPUT": "/osmo/data/output"},
        mounts=(Mount(RUN / "output.partial", "/osmo/data/output", read_only=False),
                Mount(Path("/var/lib/osmo/runs/wf-1/prep/0/output"), "/osmo/data/input/0"),
                Mount(RUN / "files/etc/train.yaml", "/etc/train.yaml")),
        cpu=2.0, memory=4 << 30)
    fields.update(extra)
    return PodPlan(**fields)


def cases() -> dict[str, list[dict[str, Any]]]:
    """Every golden case: its objects, in the order the runtime creates them."""
    gpu = plan(gpus=2, storage=20 << 30, platform="dgx", cpu=0.5)
    secret = plan(secret_env=("WANDB_API_KEY",))
    found = {
        "task": [pod_manifest(plan(), POOL)],
        "gpu": [pod_manifest(gpu, POOL)],
        "credentials": [pod_manifest(secret, POOL, secret=secret.name),
                        secret_manifest(secret, {"WANDB_API_KEY": "not-a-real-key"}, POOL,
                                        owner_uid="00000000-0000-0000-0000-000000000001")],
    }
    pulled = plan(secret_env=("TOKEN",))
    found["registry-credentials"] = [
        secret_manifest(pulled, {"TOKEN": "not-a-real-token"}, POOL, owner_uid="unused",
                        registry=RegistryAuth("nvcr.io", "$oauthtoken", "not-a-real-key")),
        pod_manifest(pulled, POOL, secret=pulled.name, pulls_with_secret=True)]
    for gang in GANGS:
        pool = KubePool(namespace="osmo-tasks", gang=gang, queue="research")
        group = GroupPlan(object_name("wf-1", "training"), 2)
        member = plan(group=group, hostname="train", lead=True)
        labels = {"osmo.dev/instance": "a1b2c3", "osmo.dev/workflow": "wf-1",
                  "osmo.dev/group": group.name}
        objects = [service_manifest(group, labels, pool)]
        pod_group = pod_group_manifest(group, labels, pool)
        objects += [pod_group[1]] if pod_group else []
        found[f"group-{gang}"] = [*objects, pod_manifest(member, pool)]
    return found


@pytest.mark.parametrize("name", sorted(cases()))
def test_golden_manifest(name: str) -> None:
    objects = cases()[name]
    path = GOLDEN / f"{name}.json"
    text = json.dumps(objects, indent=2, sort_keys=True) + "\n"
    if os.environ.get("OSMO_UPDATE_GOLDEN") == "1":
        path.parent.mkdir(exist_ok=True)
        path.write_text(text)
    assert text == path.read_text(), f"{path} differs (OSMO_UPDATE_GOLDEN=1 rewrites it)"
    for obj in objects:
        kind = {"Pod": "pods", "Secret": "secrets", "Service": "services"}.get(obj["kind"])
        problems = [str(c) for c in SCHEMA(obj)] + [str(c) for c in check(kind, obj)] if kind \
            else [str(c) for c in SCHEMA(obj)]
        assert problems == [], (name, obj["kind"], problems)


def test_a_pod_never_runs_privileged_or_as_root() -> None:
    pod = pod_manifest(plan(), POOL)
    security = pod["spec"]["containers"][0]["securityContext"]
    assert security["runAsNonRoot"] is True and security["runAsUser"] != 0
    assert security["privileged"] is False and security["allowPrivilegeEscalation"] is False
    assert security["capabilities"] == {"drop": ["ALL"]}
    assert pod["spec"]["automountServiceAccountToken"] is False


def test_credentials_are_never_literal_values() -> None:
    secret = plan(secret_env=("TOKEN",), env={"TOKEN": "leaked?", "A": "1"})
    pod = pod_manifest(secret, POOL, secret=secret.name)
    assert "leaked?" not in json.dumps(pod)
    env = pod["spec"]["containers"][0]["env"]
    assert {"name": "TOKEN", "valueFrom": {"secretKeyRef": {"name": secret.name,
                                                            "key": "TOKEN"}}} in env


@pytest.mark.parametrize("text", ["wf-1", "a b/c:d", "x" * 80, "-lead", "é", ""])
def test_any_name_makes_a_valid_label_value(text: str) -> None:
    value = label_value(text)
    pod = pod_manifest(plan(workflow_id=text, task=text or "t"), POOL)
    assert check("pods", pod) == [], value
    assert len(value) <= 63


def test_unusable_environment_names_are_refused_with_their_name() -> None:
    with pytest.raises(ManifestError, match="'BAD=NAME'"):
        pod_manifest(plan(env={"BAD=NAME": "1"}), POOL)


def test_the_claim_work_volume_mounts_sub_paths(tmp_path: Path) -> None:
    pool = KubePool(work_claim="osmo-work", work_mount=Path("/var/lib/osmo"))
    pod = pod_manifest(plan(), pool)
    assert pod["spec"]["volumes"] == [{"name": "work", "persistentVolumeClaim":
                                       {"claimName": "osmo-work"}}]
    paths = {m["mountPath"]: m.get("subPath") for m in pod["spec"]["containers"][0]["volumeMounts"]}
    assert paths["/osmo/data/output"] == "runs/wf-1/train/0/output.partial"
    outside = KubePool(work_claim="osmo-work", work_mount=Path("/elsewhere"))
    with pytest.raises(ManifestError, match="not on the pool's work claim"):
        pod_manifest(plan(), outside)


def test_the_pool_configuration_refuses_unknown_keys_and_root(tmp_path: Path) -> None:
    conf = tmp_path / "pool.json"
    conf.write_text(json.dumps({"namespace": "x", "gnag": "kai"}))
    with pytest.raises(UsageError, match="unknown key 'gnag'"):
        load_pool(conf)
    conf.write_text(json.dumps({"runAsUser": 0}))
    with pytest.raises(UsageError, match="never run as root"):
        load_pool(conf)
    conf.write_text(json.dumps({"gang": "volcano", "platforms": {"a": {"nodeSelector":
                                                                       {"k": "v"}}}}))
    assert load_pool(conf).platforms["a"].node_selector == {"k": "v"}


def test_a_workflow_s_priority_picks_its_priority_class() -> None:
    pool = KubePool(priority_classes={"HIGH": "osmo-high", "NORMAL": "", "default": "osmo-std"})
    assert pod_manifest(plan(priority="HIGH"), pool)["spec"]["priorityClassName"] == "osmo-high"
    assert "priorityClassName" not in pod_manifest(plan(priority="NORMAL"), pool)["spec"]
    assert pod_manifest(plan(priority="LOW"), pool)["spec"]["priorityClassName"] == "osmo-std"
    assert pod_manifest(plan(), pool)["spec"]["priorityClassName"] == "osmo-std"
    assert "priorityClassName" not in pod_manifest(plan(priority="HIGH"), KubePool())["spec"]
