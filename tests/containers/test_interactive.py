"""``osmo workflow exec`` and ``port-forward`` into a container task (real podman)."""

from __future__ import annotations

import hashlib
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

from osmo.config import free_port
from tests.conftest import REPO, Osmo, write


def _running(osmo: Osmo, spec: Path) -> str:
    wf = osmo.submit(spec)
    osmo.wait_for(wf, lambda i: i["tasks"][0]["status"] in ("RUNNING", "FAILED", "COMPLETED"),
                  timeout=300)
    return wf


def test_exec_and_port_forward_reach_the_tasks_container(cosmo: Osmo, python_image: str,
                                                         tmp_path: Path) -> None:
    port, local = free_port(0), free_port(0)
    wf = _running(cosmo, write(tmp_path / "web.yaml", f"""
workflow:
  name: boxed-web
  tasks:
  - name: t
    image: {python_image}
    environment: {{GREETING: hola}}
    command: [sh, -c, "cd /tmp && head -c 300000 /dev/urandom > blob && python3 -m http.server {port}"]
"""))
    try:
        r = cosmo("workflow", "exec", wf, "t", "--", "sh", "-c",
                  'echo "$GREETING $OSMO_TASK"; test -d /osmo/data/output && echo in-box; exit 4')
        assert r.code == 4 and r.out == "hola t\nin-box\n", r.err
        want = cosmo("workflow", "exec", wf, "t", "--", "sha256sum", "/tmp/blob", check=True)
        proc = subprocess.Popen([sys.executable, "-m", "osmo", "workflow", "port-forward", wf,
                                 "t", "--port", f"{local}:{port}"], env=cosmo.env, cwd=REPO,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert proc.stdout is not None and proc.stdout.readline().startswith("Forwarding")
            deadline = time.monotonic() + 60
            while True:
                try:
                    body = urllib.request.urlopen(f"http://127.0.0.1:{local}/blob",
                                                  timeout=30).read()
                    break
                except OSError:
                    assert time.monotonic() < deadline
                    time.sleep(0.3)
            assert hashlib.sha256(body).hexdigest() == want.out.split()[0]
        finally:
            proc.kill()
            proc.communicate(timeout=30)
    finally:
        cosmo("cancel", wf)
