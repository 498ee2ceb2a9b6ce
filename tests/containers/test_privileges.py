"""What a container task may do as root: OSMO's pod capabilities, no new privileges (podman).

OSMO's task pods set ``privileged: false`` and no ``capabilities``, so they keep Kubernetes'
default container set (the container runtime's, without ``NET_RAW``). A podman container
keeps podman's defaults otherwise; osmo names the set itself and adds
``no-new-privileges``, so a setuid file or file capability gains nothing.
"""

from __future__ import annotations

from pathlib import Path

from tests.conftest import Osmo, write
from tests.containers.submitting import submitted_id

KEPT = ("CHOWN", "DAC_OVERRIDE", "FOWNER", "FSETID", "KILL", "SETGID", "SETUID", "SETPCAP",
        "NET_BIND_SERVICE", "SYS_CHROOT", "MKNOD", "AUDIT_WRITE", "SETFCAP")
_BITS = {"CHOWN": 0, "DAC_OVERRIDE": 1, "FOWNER": 3, "FSETID": 4, "KILL": 5, "SETGID": 6,
         "SETUID": 7, "SETPCAP": 8, "NET_BIND_SERVICE": 10, "NET_RAW": 13, "SYS_CHROOT": 18,
         "MKNOD": 27, "AUDIT_WRITE": 29, "SETFCAP": 31}


def test_a_container_task_keeps_only_the_pod_capabilities(cosmo: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "caps.yaml", """
workflow:
  name: caps
  tasks:
  - name: t
    image: alpine:3.18
    command: [sh, -c, "grep -E '^(CapBnd|CapEff|NoNewPrivs)' /proc/self/status > {{output}}/caps"]
""")
    r = cosmo("submit", str(spec), "--wait", timeout=300)
    assert r.code == 0, r.out + r.err
    wf = submitted_id(r.out)
    got = tmp_path / "got"
    cosmo("artifacts", "get", f"{wf}:t", "-o", str(got), check=True)
    fields = dict(line.split(":\t") for line in (got / "caps").read_text().splitlines())
    want = sum(1 << _BITS[name] for name in KEPT)
    assert int(fields["CapBnd"], 16) == want, fields
    assert int(fields["CapEff"], 16) == want, fields  # root in the container: all it keeps
    assert fields["NoNewPrivs"] == "1", fields
