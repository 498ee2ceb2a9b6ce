"""A secret printed in base64 or base64url is masked in the task's log too, whatever its
offset in the encoded text (issue 11, medium item), through a real task and the CLI."""

from __future__ import annotations

import base64
from pathlib import Path

from tests.conftest import Osmo, write
from tests.hostile.datarun import finished

TOKEN = "s3cr3t>>>???-Pa55w0rd"  # its base64 holds '+' and '/', so base64url differs


def stable_parts(secret: bytes) -> list[str]:
    """The parts of an encoding of ``secret`` that depend on its bytes alone, at each of the
    three offsets it can have in a longer text, in both alphabets."""
    parts = []
    for shift in range(3):
        std = base64.b64encode(b"\0" * shift + secret).decode()
        core = std[-(-8 * shift // 6):(8 * (shift + len(secret))) // 6]
        parts += [core, core.replace("+", "-").replace("/", "_")]
    return parts


def test_base64_forms_of_a_secret_are_masked(osmo: Osmo, tmp_path: Path) -> None:
    osmo("credential", "set", "api", "--payload", f"token={TOKEN}", check=True)
    spec = write(tmp_path / "m.yaml", """
workflow:
  name: masked
  tasks:
  - name: leak
    credentials: {api: {TOKEN: token}}
    command: [sh, -c, "printf %s \\"$TOKEN\\" | base64; printf %s \\"$TOKEN\\" | base64 | tr '+/' '-_' | tr -d =; printf 'user:%s' \\"$TOKEN\\" | base64; printf 'a%s' \\"$TOKEN\\" | base64 -w0 >&2; echo; echo plain $TOKEN"]
""")
    wf = finished(osmo, spec)
    logs = osmo("logs", wf, check=True).out
    assert logs.count("****") >= 5, logs
    for part in [TOKEN, *stable_parts(TOKEN.encode())]:
        assert part not in logs, f"{part!r} leaked:\n{logs}"
