"""Authorization is default deny, declared once: every verb x every role through the real API.

Issue 26 item 9: a verb missing from the admin list used to be open to every user, and no test
called an admin verb with a user token. Here the server's one table (``osmo.server.auth.API``)
is compared with a copy pinned in this file, and then every verb is called by each kind of
caller (no token, a worker, a user, another user, an admin) against a real server: a caller
whose role the table leaves out gets the role refusal (and one ``refused`` line in the log);
one it names gets through the role check (its request may still fail for other reasons). Verbs
that act on a workflow let only its submitter (or an admin) through. Adding a verb to the table
without pinning its roles here, or widening a verb's roles, fails this test.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import pytest

from osmo.config import read_server_info
from osmo.errors import NotAllowed, NotAuthenticated, OsmoError, UsageError
from osmo.layout import Home
from osmo.transport.rpc import ApiClient
from osmo.transport.zenoh_link import Link
from tests.conftest import Osmo, write

ADMIN, USERS, WORKERS, ANY = "admin", "admin user", "admin worker", "admin user worker"
OWNED = "admin user (owner)"  # users only on workflows they submitted

PINNED: dict[str, str] = {
    "ping": ANY,
    "shutdown": ADMIN, "token_create": ADMIN, "token_list": ADMIN, "token_revoke": ADMIN,
    "credential_set": ADMIN, "credential_delete": ADMIN, "artifact_gc": ADMIN,
    "worker_register": WORKERS, "worker_drain": WORKERS, "worker_report": WORKERS,
    "worker_log": WORKERS, "worker_secrets": WORKERS, "worker_session": WORKERS,
    "worker_beat": WORKERS, "worker_swept": WORKERS,
    "submit": USERS, "get": USERS, "status": USERS, "list": USERS, "logs": USERS,
    "events": USERS, "spec": USERS, "pools": USERS, "lineage": USERS,
    "artifact_list": USERS, "artifact_get": USERS, "credential_list": USERS,
    "dataset_list": USERS, "dataset_info": USERS, "dataset_tag": USERS,
    "dataset_download": USERS, "dataset_upload": USERS,
    "cancel": OWNED, "restart": OWNED, "workflow_tag": OWNED, "exec_open": OWNED,
    "forward_open": OWNED,
}
"""Every verb and who may call it, written down a second time on purpose."""

HELD = """
workflow:
  name: held
  tasks:
  - name: t
    command: [sh, -c, "sleep 120"]
"""
WF = "held-1"  # submitted by alice

# a request per verb that passes or fails only after the role check; none changes much
REQUESTS: dict[str, dict[str, Any]] = {
    "token_create": {"name": "../bad"}, "token_revoke": {"name": "nobody-has-this"},
    "credential_set": {"name": "c", "payload": {}}, "credential_delete": {"name": "none"},
    "worker_register": {}, "worker_drain": {"id": "nobody"},
    "worker_report": {"id": "nobody", "report": {}},
    "worker_log": {"id": "nobody", "attempt_id": "x", "records": ""},
    "worker_secrets": {"id": "nobody", "attempt_id": "x"},
    "worker_session": {"id": "nobody", "ticket": "x"},
    "worker_beat": {"id": "nobody"}, "worker_swept": {"id": "nobody", "instance": "x"},
    "submit": {}, "get": {"workflow_id": WF}, "status": {"workflow_id": WF},
    "logs": {"workflow_id": WF}, "events": {"workflow_id": WF}, "spec": {"workflow_id": WF},
    "lineage": {}, "artifact_list": {"workflow_id": WF}, "artifact_get": {},
    "dataset_info": {"ref": "none"}, "dataset_tag": {}, "dataset_download": {},
    "dataset_upload": {}, "cancel": {"workflow_id": WF}, "restart": {"workflow_id": WF},
    "workflow_tag": {"workflow_id": WF, "add": ["x"]},
    "exec_open": {"workflow_id": WF, "task": "t", "command": ["true"]},
    "forward_open": {"workflow_id": WF, "task": "t", "ports": [1]},
}
CALLERS = ("anonymous", "worker", "bob", "alice", "admin")
ROLE = {"worker": "worker", "bob": "user", "alice": "user", "admin": "admin"}


@pytest.fixture(scope="module")
def callers(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Osmo, dict]]:
    """A server, alice's running workflow, and an API client per kind of caller."""
    osmo = Osmo(tmp_path_factory.mktemp("matrix") / "home")
    tokens: dict[str, str | None] = {"anonymous": None}
    for name in ("bob", "alice"):
        tokens[name] = osmo("token", "create", name, "--role", "user", check=True).out.strip()
    tokens["worker"] = osmo("token", "create", "w", "--role", "worker", "--pool", "default",
                            check=True).out.strip()
    tokens["admin"] = (osmo.home / "auth" / "admin.token").read_text().strip()
    osmo("--token", str(tokens["alice"]), "submit",
         str(write(osmo.home.parent / "held.yaml", HELD)), check=True)
    osmo.wait_for(WF, lambda i: i["tasks"][0]["status"] == "RUNNING")
    info = read_server_info(Home(osmo.home))
    assert info is not None
    link = Link.client([info.endpoint], info.cluster)
    yield osmo, {who: ApiClient(link, timeout=20, token=tokens[who]) for who in CALLERS}
    link.close()
    osmo.stop_server()


def _role_refusal(exc: BaseException | None) -> bool:
    return isinstance(exc, NotAllowed) and "needs role" in str(exc)


def _call(client: ApiClient, verb: str) -> OsmoError | None:
    try:
        client.call(verb, REQUESTS.get(verb, {}))
    except OsmoError as exc:
        return exc
    return None


def test_the_table_is_the_pinned_one() -> None:
    from osmo.server.auth import API, VERBS

    table = {verb: " ".join(sorted(r.value for r in rule.roles)) + (" (owner)" * rule.owner)
             for verb, rule in API.items()}
    assert table == PINNED, "a verb's roles changed, or a verb was added or removed: pin it"
    assert {v: frozenset(r.value for r in roles) for v, roles in VERBS.items()} == {
        v: frozenset(rule.split(" (")[0].split()) for v, rule in PINNED.items()}


def test_every_verb_for_every_caller(callers: tuple[Osmo, dict]) -> None:
    osmo, clients = callers
    log = osmo.home / "server.log"
    wrong: list[str] = []
    for verb in sorted(PINNED, key=lambda v: v == "shutdown"):  # shutdown last
        allowed = PINNED[verb].split(" (")[0].split()
        for who in CALLERS:
            if verb == "shutdown" and who == "admin":
                continue  # would stop the server; the refusals above are what matter
            before = log.read_text().count("refused")
            got = _call(clients[who], verb)
            if who == "anonymous":
                ok = isinstance(got, NotAuthenticated)
            elif ROLE[who] not in allowed:
                ok = _role_refusal(got) and log.read_text().count("refused") == before + 1
            elif "(owner)" in PINNED[verb] and who == "bob":
                ok = isinstance(got, NotAllowed) and "submitted by" in str(got)
            else:  # through the role check; the handler may still refuse the request
                ok = not _role_refusal(got) and not isinstance(got, NotAuthenticated)
            if not ok:
                wrong.append(f"{verb} as {who}: {type(got).__name__}: {got}")
    assert not wrong, "\n".join(wrong)
    assert "Traceback" not in log.read_text()


def test_an_unknown_verb_is_refused_for_everyone(callers: tuple[Osmo, dict]) -> None:
    _, clients = callers
    for who in CALLERS:
        got = _call(clients[who], "credential_dump")
        assert isinstance(got, NotAuthenticated if who == "anonymous" else UsageError), who
        if who != "anonymous":
            assert "unknown API verb" in str(got)


def test_a_user_never_reaches_an_admin_verb(callers: tuple[Osmo, dict]) -> None:
    """The attack of the issue: with a user token, set a credential and mint a token."""
    osmo, clients = callers
    for verb, request in (("credential_set", {"name": "x", "payload": {"k": "v"}}),
                          ("token_create", {"name": "mine", "role": "admin"})):
        with pytest.raises(NotAllowed, match="needs role admin"):
            clients["bob"].call(verb, request)
    listed = json.loads(osmo("token", "list", "--format", "json", check=True).out)
    assert "mine" not in {t["name"] for t in listed}
    assert "x" not in osmo("credential", "list", check=True).out.split()
