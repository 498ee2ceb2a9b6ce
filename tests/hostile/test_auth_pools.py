"""Workers are bound to pools: a worker token names the pools it may serve (issue 26, item 8).

The attack as tried: a worker token claimed pool ``secure`` with cpu 1000 / gpu 64, drew that
pool's task and got its credential from ``worker_secrets``. Now the token of pool ``a`` is
refused at registration (a clear error; the real ``osmo worker`` exits 2 saying which pools
its token may serve), draws nothing, and the credential goes only to the worker of ``secure``.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from osmo.errors import NotAllowed, UsageError
from osmo.transport.rpc import ApiClient
from osmo.transport.zenoh_link import Link
from tests.conftest import Osmo, ended, write
from tests.e2e.cluster import Cluster

GREEDY = {"id": "rogue", "pool": "secure", "address": "127.0.0.1",
          "capacity": {"cpu": 1000, "gpu": 64}}


def _secure_spec(tmp: Path) -> Path:
    return write(tmp / "secure.yaml", """
workflow:
  name: secure
  pool: secure
  tasks:
  - name: t
    credentials:
      robot: {ROBOT: key}
    command: [sh, -c, "test \\"$ROBOT\\" = TOP-s3cret-42 && echo got-it > {{output}}/out"]
""")


def test_a_worker_token_of_pool_a_cannot_serve_pool_secure(tmp_path: Path) -> None:
    c = Cluster(tmp_path)
    c.start_server()
    link = Link.client([c.endpoint], "local")
    try:
        c.osmo("credential", "set", "robot", "--payload", "key=TOP-s3cret-42", check=True)
        rogue = c.token("rogue", pool="a")
        api = ApiClient(link, timeout=10, token=rogue)
        with pytest.raises(NotAllowed, match="may serve only pool 'a'"):
            api.call("worker_register", GREEDY)
        refused = [ln for ln in (c.osmo.home / "server.log").read_text().splitlines()
                   if "refused 'worker_register' from rogue (worker)" in ln]
        assert len(refused) == 1, refused
        # the real worker process with that token says why and stops (no retry loop)
        proc = c.start_worker("rogue-2", pool="secure", token=rogue, wait=False)
        assert proc.wait(timeout=60) == 2
        assert "may serve only pool 'a'" in c.worker_log("rogue-2")
        assert "Traceback" not in c.worker_log("rogue-2")
        # the pool's own worker draws the task and gets the credential; the rogue nothing
        c.start_worker("s1", pool="secure")
        wf = c.osmo.submit(_secure_spec(tmp_path))
        done = c.osmo.wait_for(wf, ended)
        assert done["status"] == "COMPLETED", done
        assert done["tasks"][0]["node"] == "s1"
        assert Path(done["tasks"][0]["output"], "out").read_text() == "got-it\n"
        assert set(c.nodes()) == {"s1"}
        with pytest.raises(NotAllowed):
            api.call("worker_secrets", {"id": "rogue", "attempt_id": f"{wf}:t:0"})
        # in its own pool the same token is welcome
        api.call("worker_register", dict(GREEDY, pool="a", capacity={"cpu": 1}))
    finally:
        link.close()
        c.stop()


def test_tokens_name_their_pools(osmo: Osmo) -> None:
    r = osmo("token", "create", "w", "--role", "worker")
    assert r.code == 2 and "--pool" in r.err and "Traceback" not in r.err
    r = osmo("token", "create", "u", "--role", "user", "--pool", "a")
    assert r.code == 2 and "only worker tokens" in r.err
    osmo("token", "create", "w", "--role", "worker", "--pool", "a", "--pool", "b", check=True)
    osmo("token", "create", "any", "--role", "worker", "--pool", "*", check=True)
    rows = {t["name"]: t for t in json.loads(osmo("token", "list", "--format", "json",
                                                  check=True).out)}
    assert rows["w"]["pools"] == ["a", "b"] and rows["any"]["pools"] == ["*"]
    assert rows["admin"]["pools"] is None
    assert "w  worker  pools a, b  live" in osmo("token", "list", check=True).out


def test_accept_token_binds_worker_pools(tmp_path: Path) -> None:
    from osmo.server.auth import accept_tokens
    from osmo.store.sqlite import Store

    store = Store(tmp_path / "state.db")
    secret, other = (write(tmp_path / name, "osmo_" + name * 43) for name in "xy")
    accept_tokens(store, (f"k8s:worker@gpu,cpu:{secret}", f"admin-k:admin:{other}"))
    assert store.token_pools("k8s") == ["gpu", "cpu"]
    assert store.token_pools("admin-k") is None
    with pytest.raises(UsageError, match="NAME:worker@POOL"):
        accept_tokens(store, (f"bare:worker:{secret}",))
    with pytest.raises(UsageError, match="only worker tokens"):
        accept_tokens(store, (f"u:user@a:{secret}",))
    store.close()
