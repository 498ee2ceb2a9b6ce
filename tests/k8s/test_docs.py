"""docs/tutorials/kubernetes.md: its pool configuration is what the worker reads, and its
dry-run command runs as written (from a folder holding the tutorial and that configuration).
The worker command it shows is what ``tests/k8s/test_tutorials_k8s.py`` runs."""

from __future__ import annotations

import json
import re
import shlex
import shutil
from pathlib import Path

from osmo.runtime.kubernetes.config import load_pool
from tests.conftest import REPO, Osmo

DOC = REPO / "docs" / "tutorials" / "kubernetes.md"
TUTORIALS = REPO / "tests" / "containers" / "osmo_tutorials"


def blocks(kind: str) -> list[str]:
    return re.findall(rf"^```{kind}\n(.*?)^```", DOC.read_text(), re.S | re.M)


def test_the_documented_pool_configuration_loads(tmp_path: Path) -> None:
    (config,) = blocks("json")
    (tmp_path / "pool.json").write_text(config)
    pool = load_pool(tmp_path / "pool.json")
    assert pool.namespace == "osmo-tasks" and pool.data_image == "osmo:0.1.0"
    assert pool.platforms["dgx"].tolerations[0]["key"] == "nvidia.com/gpu"


def test_the_documented_commands(tmp_path: Path) -> None:
    worker, dry_run = (shlex.split(b.replace("\\\n", " ")) for b in blocks("shell"))
    assert worker[:2] == ["osmo", "worker"] and "--kubernetes-config" in worker
    (tmp_path / "pool.json").write_text(blocks("json")[0])
    shutil.copy(TUTORIALS / "hello_world.yaml", tmp_path)
    osmo = Osmo(tmp_path / "home")
    osmo.env["PYTHONPATH"] = str(REPO)  # this checkout's osmo, run from another folder
    r = osmo(*dry_run[1:], cwd=tmp_path)
    assert r.code == 0, r.err
    pod, secret = json.loads(r.out)["items"]
    assert pod["kind"] == "Pod" and pod["metadata"]["namespace"] == "osmo-tasks"
    mounts = pod["spec"]["containers"][0]["volumeMounts"]
    assert {m["mountPath"] for m in mounts} == {"/osmo/data/output"}
    assert [c["name"] for c in pod["spec"]["initContainers"]] == ["osmo-fetch"]
    assert secret["kind"] == "Secret" and set(secret["data"]) == {"osmo-fetch-ticket",
                                                                 "osmo-collect-ticket"}
