"""Who may talk to the server: the API refuses anonymous callers and callers without the role.

Each attack of issue 13 as it was tried: a raw zenoh session speaking osmo's JSON verbs
without a token (submit, credential list, cancel, shutdown), a user token asking for what
only an admin may (shutdown, credential values, tokens) or for another user's workflow,
a revoked token, a worker token submitting. Every refusal is a clear error on the client
and one line in ``server.log``; the server keeps running and nothing changes.
"""

from __future__ import annotations

import json
from collections.abc import Iterator

import pytest

from osmo.config import read_server_info
from osmo.layout import Home
from osmo.transport.rpc import ApiClient
from osmo.transport.zenoh_link import Link
from tests.conftest import Osmo, write

HELD = """
workflow:
  name: held
  tasks:
  - name: t
    command: [sh, -c, "sleep 60"]
"""


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Osmo]:
    """A server with a running workflow (``held-1``) submitted by its owner (admin)."""
    osmo = Osmo(tmp_path_factory.mktemp("auth") / "home")
    osmo("submit", str(write(osmo.home.parent / "held.yaml", HELD)), check=True)
    osmo("credential", "set", "robot", "--payload", "key=s3cr3t-VALUE", check=True)
    yield osmo
    osmo("cancel", "held-1")
    osmo.stop_server()


def _api(osmo: Osmo, token: str | None) -> Iterator[ApiClient]:
    info = read_server_info(Home(osmo.home))
    assert info is not None
    link = Link.client([info.endpoint], info.cluster)
    yield ApiClient(link, timeout=10, token=token)
    link.close()


@pytest.fixture
def anonymous(server: Osmo) -> Iterator[ApiClient]:
    yield from _api(server, None)


def _refusals(osmo: Osmo) -> list[str]:
    return [line for line in (osmo.home / "server.log").read_text().splitlines()
            if "refused" in line]


def _status(osmo: Osmo, wf: str) -> str:
    return str(json.loads(osmo("query", wf, "--format", "json", check=True).out)["status"])


@pytest.mark.parametrize(("verb", "request_"), [
    ("submit", {"spec": {"workflow": {"name": "evil", "tasks": [
        {"name": "t", "command": ["id"]}]}}}),
    ("credential_list", {}),
    ("cancel", {"workflow_id": "held-1"}),
    ("shutdown", {}),
    ("token_create", {"name": "mine", "role": "admin"}),
    ("worker_report", {"id": "w", "report": {"op": "exited", "attempt_id": "held-1:t:0",
                                             "exit_code": 0}}),
])
def test_an_anonymous_peer_is_refused(server: Osmo, anonymous: ApiClient, verb: str,
                                      request_: dict) -> None:
    with pytest.raises(Exception) as refused:  # the client knows it has nothing to seal with
        anonymous.call(verb, request_)
    assert type(refused.value).__name__ == "NotAuthenticated"
    assert getattr(refused.value, "exit_code", None) == 3
    assert "token" in str(refused.value)
    # a raw request in clear, as an attacker sends it, with a made-up channel header
    before = len(_refusals(server))
    link = anonymous.link
    for attachment in (None, b"osmo_not-a-token", bytes([1, 1]) + b"\0" * 24):
        replies = list(Link.replies(link.ask(link.key("api", verb), json.dumps(request_).encode(),
                                             attachment=attachment, timeout=10)))
        assert len(replies) == 1 and b"NotAuthenticated" in replies[0][0]
    new = _refusals(server)[before:]
    assert len(new) == 3 and all(f"refused an unsealed '{verb}' request" in line
                                 for line in new), new
    # nothing happened: the server answers, the workflow runs, no workflow was made
    assert _status(server, "held-1") == "RUNNING"
    assert "evil" not in server("list", check=True).out


def test_users_see_no_paths_and_may_not_do_admin_things(server: Osmo) -> None:
    token = server("token", "create", "alice", "--role", "user", check=True).out.strip()
    assert token.startswith("osmo_")
    alice = next(_api(server, token))
    info = alice.call("ping")
    assert info["identity"] == {"name": "alice", "role": "user"}
    assert str(server.home) not in json.dumps(info), "ping must reveal no paths to a user"
    admin = json.loads(server("token", "list", "--format", "json", check=True).out)
    assert {"alice", "admin"} <= {t["name"] for t in admin}
    assert all("token" not in t and "digest" not in t for t in admin)
    as_alice = dict(server.env, OSMO_TOKEN=token)
    for argv in (("server", "stop"), ("token", "list"), ("cancel", "held-1"),
                 ("credential", "delete", "robot"), ("artifacts", "gc")):
        before = len(_refusals(server))
        if argv == ("server", "stop"):
            with pytest.raises(Exception) as refused:
                alice.call("shutdown")
            assert "needs role admin" in str(refused.value)
            assert type(refused.value).__name__ == "NotAllowed"
        else:
            r = server("--token", token, *argv)
            assert r.code == 2, (argv, r)
            assert "not allowed" in r.err and "Traceback" not in r.err
        assert len(_refusals(server)) == before + 1, argv
        assert "from alice (user)" in _refusals(server)[-1]
    assert as_alice  # the environment form is the same: OSMO_TOKEN
    creds = alice.call("credential_list")
    assert "s3cr3t-VALUE" not in json.dumps(creds) and creds[0]["name"] == "robot"
    # her own workflow she may cancel, and it records her as its submitter
    wf = json.loads(server("--token", token, "submit", str(write(
        server.home.parent / "hers.yaml", HELD.replace("held", "hers"))), "--format", "json",
        check=True).out)["workflow_id"]
    listed = json.loads(server("list", "--format", "json", check=True).out)
    assert {w["id"]: w["submitted_by"] for w in listed}[wf] == "alice"
    assert "alice" in server("list", check=True).out
    assert server("--token", token, "cancel", wf).code == 0
    assert _status(server, "held-1") == "RUNNING"
    alice._link.close()  # noqa: SLF001 - the generator's link


def test_a_revoked_token_is_refused_at_once(server: Osmo) -> None:
    token = server("token", "create", "bob", "--role", "user", check=True).out.strip()
    assert server("--token", token, "list").code == 0
    server("token", "revoke", "bob", check=True)
    r = server("--token", token, "list")
    assert r.code == 3 and "unknown or revoked" in r.err and "Traceback" not in r.err
    assert "revoked" in server("token", "list", check=True).out


def test_a_worker_token_may_only_speak_for_workers(server: Osmo) -> None:
    token = server("token", "create", "w-only", "--role", "worker", "--pool", "a",
                   check=True).out.strip()
    r = server("--token", token, "submit", str(server.home.parent / "held.yaml"))
    assert r.code == 2 and "has role worker" in r.err
    r = server("--token", token, "credential", "list")
    assert r.code == 2 and "not allowed" in r.err
