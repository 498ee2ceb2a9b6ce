"""The zenoh configs the chart renders are ones zenoh itself accepts.

zenoh rejects unknown keys, so loading each rendered file with ``zenoh.Config`` proves the TLS
and user/password settings are spelt as zenoh spells them. The init container's script
(files/render-client-config.py) is run here on the rendered client config, as in the pod.
"""

from __future__ import annotations

import json
import stat
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

from tests.helm.chart import CHART, FULLNAME, render, tls_values

FEATURES = {
    "tls": tls_values(),
    "mtls": tls_values(tls={"enabled": True, "mtls": True, "existingSecret": "s",
                            "client": {"existingSecret": "c"}}),
    "auth": {"auth": {"enabled": True, "password": "pw"}},
    "router-tls-auth": tls_values(router={"enabled": True}, auth={"enabled": True, "password": "pw"}),
}


def config_files(values: dict) -> dict[str, str]:
    """The zenoh ConfigMap's files."""
    data: dict[str, str] = render(values).get("ConfigMap", f"{FULLNAME}-zenoh")["data"]
    return data


@pytest.mark.parametrize("case", sorted(FEATURES))
def test_rendered_configs_load_in_zenoh(case: str) -> None:
    files = config_files(FEATURES[case])
    for name, text in files.items():
        if name.endswith(".json5"):
            zenoh.Config.from_json5(text)  # raises on any key zenoh does not know


def test_mtls_settings_on_both_sides() -> None:
    files = config_files(FEATURES["mtls"])
    server = json.loads(files["server.json5"])["transport"]["link"]["tls"]
    client = json.loads(files["client.json5"])["transport"]["link"]["tls"]
    assert server["enable_mtls"] is True
    assert server["listen_certificate"] == "/etc/osmo/tls/server/tls.crt"
    assert client["root_ca_certificate"] == "/etc/osmo/tls/server/ca.crt"
    assert client["connect_certificate"] == "/etc/osmo/tls/client/tls.crt"


def test_router_config_listens_and_checks_passwords() -> None:
    router = json.loads(config_files(FEATURES["router-tls-auth"])["router.json5"])
    assert router["mode"] == "router"
    assert router["listen"]["endpoints"] == ["tcp/0.0.0.0:7447", "tls/0.0.0.0:7448"]
    assert router["scouting"]["multicast"]["enabled"] is False
    assert router["transport"]["auth"]["usrpwd"] == {"dictionary_file": "/etc/osmo/auth/dictionary"}


def test_init_script_fills_in_user_and_password(tmp_path: Path) -> None:
    files = config_files(FEATURES["auth"])
    script = tmp_path / "render-client-config.py"
    script.write_text(files["render-client-config.py"])
    assert files["render-client-config.py"] == (CHART / "files" / "render-client-config.py").read_text()
    (tmp_path / "client.json5").write_text(files["client.json5"])
    (tmp_path / "user").write_text("robot\n")
    (tmp_path / "password").write_text("s3cret")
    dest = tmp_path / "out.json5"
    subprocess.run([sys.executable, str(script), str(tmp_path / "client.json5"),
                    str(tmp_path / "user"), str(tmp_path / "password"), str(dest)],
                   check=True, timeout=60)
    config = json.loads(dest.read_text())
    assert config["transport"]["auth"]["usrpwd"] == {"user": "robot", "password": "s3cret"}
    assert stat.S_IMODE(dest.stat().st_mode) == 0o600
    zenoh.Config.from_json5(dest.read_text())
