"""Hostile values against the Kubernetes runtime's manifests (issue #28).

- An image, label value or environment value that would break a manifest is refused at
  submit (``osmo validate`` here: the same loader), every one with its position.
- Names that are not label values (workflow, task) never reach a manifest as such.
- A task cannot read another attempt's Secret: its pod has no API credentials and names only
  its own Secret.
"""

from __future__ import annotations

import json
from pathlib import Path

from osmo.runtime.container.run import Mount
from osmo.runtime.kubernetes.config import KubePool
from osmo.runtime.kubernetes.manifest import PodPlan, pod_manifest
from tests.conftest import Osmo
from tests.k8s.validation import SchemaCheck, check

SPEC = """\
workflow:
  name: hostile
  tasks:
  - name: t
    image: "alpine:3.18 --privileged"
    command: ["true"]
    environment:
      "1BAD": "x"
      "A B": "y"
      OK: "nul\\0here"
"""


def test_unusable_image_and_environment_are_refused_with_positions(tmp_path: Path) -> None:
    spec = tmp_path / "wf.yaml"
    spec.write_text(SPEC)
    r = Osmo(tmp_path / "home")("validate", str(spec))
    assert r.code == 2, r.out + r.err
    text = r.out + r.err
    assert f"{spec}:5:12:" in text and "image" in text, text  # the image
    assert f"{spec}:8:7:" in text and "'1BAD'" in text, text
    assert f"{spec}:9:7:" in text and "'A B'" in text, text
    assert f"{spec}:10:11:" in text and "NUL" in text, text


def test_hostile_names_make_valid_manifests() -> None:
    schema = SchemaCheck("1.33")
    for name in ("a b/c", "--privileged", "x" * 300, "名前", "a\nb"):
        plan = PodPlan(attempt_id=f"{name}:{name}:0", workflow_id=name, task=name, retry=0,
                       instance=name, image="alpine:3.18", argv=("true",))
        pod = pod_manifest(plan, KubePool())
        assert check("pods", pod) == [] and schema(pod) == [], name


def test_a_pod_names_only_its_own_secret_and_gets_no_api_credentials() -> None:
    plans = [PodPlan(attempt_id=f"wf:t{i}:0", workflow_id="wf", task=f"t{i}", retry=0,
                     instance="i", image="alpine:3.18", argv=("true",), secret_env=("TOKEN",),
                     mounts=(Mount(Path(f"/r/t{i}/output.partial"), "/osmo/data/output",
                                   read_only=False),))
             for i in range(2)]
    pods = [pod_manifest(p, KubePool(), secret=p.name) for p in plans]
    assert plans[0].name != plans[1].name
    for plan, pod in zip(plans, pods, strict=True):
        spec = pod["spec"]
        assert spec["automountServiceAccountToken"] is False  # no token: no API access
        assert "serviceAccountName" not in spec
        named = {ref["secretKeyRef"]["name"] for env in spec["containers"][0]["env"]
                 if (ref := env.get("valueFrom"))}
        assert named == {plan.name}
        assert not [v for v in spec["volumes"] if "secret" in v or "projected" in v]
        assert plans[1 - plans.index(plan)].name not in json.dumps(pod)
