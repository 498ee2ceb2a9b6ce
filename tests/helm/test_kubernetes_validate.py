"""Rendered manifests are valid Kubernetes objects: ``kubernetes-validate --strict``, offline.

Strict mode rejects unknown fields, so a misspelt or misplaced key in a template fails here. The
schemas ship inside the PyPI package; the versions are pinned: the chart's minimum (kubeVersion
in Chart.yaml) and the newest the package knows.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.helm.chart import EXAMPLES, load_values, render, tls_values

KUBE_VERSIONS = ["1.30.0", "1.37.0"]
VALIDATE = Path(sys.executable).parent / "kubernetes-validate"

CASES = {
    "defaults": {},
    "example-cpu-gpu-pools": load_values(EXAMPLES / "cpu-gpu-pools.yaml"),
    "router-tls-mtls-auth": tls_values(
        router={"enabled": True}, auth={"enabled": True, "password": "pw"},
        server={"plainTcp": False, "persistence": {"enabled": False}},
        worker={"workdirSizeLimit": "50Gi"},
        service={"type": "LoadBalancer", "loadBalancerSourceRanges": ["10.0.0.0/8"]},
        pools=[{"name": "p", "replicas": 2, "priorityClassName": "high",
                "extraVolumes": [{"name": "data", "persistentVolumeClaim": {"claimName": "d"}}],
                "extraVolumeMounts": [{"name": "data", "mountPath": "/data", "readOnly": True}],
                "env": [{"name": "NODE", "valueFrom": {"fieldRef": {"fieldPath": "spec.nodeName"}}}],
                "image": {"repository": "osmo", "tag": "sim"}}]),
    "no-pools": {"pools": []},
    "local-pool-own-profiles": {"server": {"localPool": True}, "sandbox": {
        "mode": "auto", "podSecurityContext": {
            "seccompProfile": {"type": "Localhost", "localhostProfile": "osmo-bwrap.json"},
            "appArmorProfile": {"type": "Localhost", "localhostProfile": "osmo-bwrap"}}}},
    "kubernetes-pool": {"pools": [{"name": "pods", "replicas": 1, "kind": "kubernetes",
                                   "kubernetes": {"workClaim": "osmo-work", "gang": "volcano",
                                                  "namespace": "osmo-tasks"}}]},
}
CASES["router-tls-mtls-auth"]["tls"].update(mtls=True, client={"cert": "c", "key": "k"})


@pytest.mark.parametrize("kube_version", KUBE_VERSIONS)
@pytest.mark.parametrize("case", sorted(CASES))
def test_rendered_manifests_validate_strictly(case: str, kube_version: str, tmp_path: Path) -> None:
    objects = render(CASES[case]).objects
    assert objects
    files = []
    for i, obj in enumerate(objects):
        path = tmp_path / f"{i:02d}-{obj['kind']}-{obj['metadata']['name']}.yaml"
        path.write_text(yaml.safe_dump(obj))
        files.append(str(path))
    proc = subprocess.run([str(VALIDATE), "--strict", "--quiet", "-k", kube_version, *files],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_the_oldest_version_checked_is_the_charts_minimum() -> None:
    from tests.helm.chart import CHART

    minimum = load_values(CHART / "Chart.yaml")["kubeVersion"]
    assert minimum == f">={KUBE_VERSIONS[0]}-0", minimum
