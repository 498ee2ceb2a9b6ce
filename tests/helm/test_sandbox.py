"""The chart runs tasks sandboxed or not at all (issue #26, item 5).

Every pod that runs tasks (each pool's workers; the server only with ``server.localPool``)
gets ``--sandbox on`` from ``sandbox.mode``, so a pod where bubblewrap cannot work fails to
start instead of running tasks unsandboxed beside its credentials, and the security context
bubblewrap needs in a pod: its own user namespace (``hostUsers: false``) with an unmasked
``/proc``, and seccomp and AppArmor profiles that allow namespaces and mounts. Never a
privileged pod, never a capability, never privilege escalation. The server runs no local
pool unless asked, and then keeps the tight default context.
"""

from __future__ import annotations

from typing import Any

import helm_python as helm
import pytest

from tests.helm.chart import FULLNAME, container, flag, lint, render

SANDBOXED_POD = {"hostUsers": False}
SANDBOXED_CONTEXT = {"seccompProfile": {"type": "Unconfined"},
                     "appArmorProfile": {"type": "Unconfined"}}


def pods(values: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Every pod-owning object (server, workers, router) by name."""
    out = render(values)
    return {o["metadata"]["name"]: o for o in out.of_kind("Deployment") + out.of_kind("StatefulSet")}


def server(values: dict[str, Any]) -> dict[str, Any]:
    return pods(values)[f"{FULLNAME}-server"]


def worker(values: dict[str, Any], pool: str = "default") -> dict[str, Any]:
    return pods(values)[f"{FULLNAME}-worker-{pool}"]


def assert_sandboxed(owner: dict[str, Any], name: str) -> None:
    """The pod runs tasks in bubblewrap: what bwrap needs, and nothing of a privileged pod."""
    pod = owner["spec"]["template"]["spec"]
    c = container(owner, name)
    assert pod.get("hostUsers") is False, pod
    for key, value in SANDBOXED_CONTEXT.items():
        assert pod["securityContext"][key] == value, pod["securityContext"]
    assert c["securityContext"]["procMount"] == "Unmasked"
    assert_unprivileged(owner, name)


def assert_tight(owner: dict[str, Any], name: str) -> None:
    """The pod runs no task: the default context, nothing relaxed for bubblewrap."""
    pod = owner["spec"]["template"]["spec"]
    assert "hostUsers" not in pod
    assert pod["securityContext"]["seccompProfile"] == {"type": "RuntimeDefault"}
    assert "appArmorProfile" not in pod["securityContext"]
    assert "procMount" not in container(owner, name)["securityContext"]
    assert_unprivileged(owner, name)


def assert_unprivileged(owner: dict[str, Any], name: str) -> None:
    pod = owner["spec"]["template"]["spec"]
    for c in pod["containers"] + pod.get("initContainers", []):
        context = c["securityContext"]
        assert context.get("privileged") is not True, c["name"]
        assert context["allowPrivilegeEscalation"] is False, c["name"]
        assert context["capabilities"] == {"drop": ["ALL"]}, c["name"]
        assert "add" not in context["capabilities"]
    assert pod["securityContext"]["runAsNonRoot"] is True
    assert pod["securityContext"]["runAsUser"] == 10001
    assert not any(pod.get(k) for k in ("hostPID", "hostIPC", "hostNetwork"))


def test_workers_run_tasks_with_sandbox_on() -> None:
    pools = {"pools": [{"name": "cpu", "replicas": 1}, {"name": "gpu", "replicas": 0,
                                                        "extraArgs": ["--label", "x=y"]}]}
    for pool in ("cpu", "gpu"):
        dep = worker(pools, pool)
        assert flag(container(dep, "worker")["args"], "--sandbox") == ["on"]
        assert_sandboxed(dep, "worker")


def test_the_server_runs_no_local_pool_by_default() -> None:
    sts = server({})
    args = container(sts, "server")["args"]
    assert "--no-local-pool" in args
    assert flag(args, "--sandbox") == []
    assert_tight(sts, "server")


def test_a_server_asked_for_a_local_pool_runs_it_sandboxed() -> None:
    sts = server({"server": {"localPool": True}})
    args = container(sts, "server")["args"]
    assert "--no-local-pool" not in args
    assert flag(args, "--sandbox") == ["on"]
    assert_sandboxed(sts, "server")


def test_the_router_is_never_relaxed() -> None:
    values = {"router": {"enabled": True}, "auth": {"enabled": True, "password": "pw"},
              "server": {"localPool": True}}
    assert_tight(pods(values)[f"{FULLNAME}-router"], "zenohd")


@pytest.mark.parametrize("mode", ["auto", "off"])
def test_the_mode_is_the_operators_choice(mode: str) -> None:
    values = {"sandbox": {"mode": mode}, "server": {"localPool": True}}
    assert f'WARNING: sandbox.mode is "{mode}"' in render(values).notes
    assert "sandbox.mode" not in render({}).notes
    for owner, name in ((worker(values), "worker"), (server(values), "server")):
        assert flag(container(owner, name)["args"], "--sandbox") == [mode]
        if mode == "off":  # nothing to sandbox with: the pods keep the tight context
            assert_tight(owner, name)
        else:
            assert_sandboxed(owner, name)


def test_profiles_of_the_operators_own_replace_unconfined() -> None:
    """A cluster that forbids Unconfined (Pod Security "baseline") uses Localhost profiles."""
    values = {"sandbox": {"podSecurityContext": {
        "seccompProfile": {"type": "Localhost", "localhostProfile": "osmo-bwrap.json"},
        "appArmorProfile": {"type": "Localhost", "localhostProfile": "osmo-bwrap"}}}}
    context = worker(values)["spec"]["template"]["spec"]["securityContext"]
    assert context["seccompProfile"] == {"type": "Localhost",
                                         "localhostProfile": "osmo-bwrap.json"}
    assert context["appArmorProfile"] == {"type": "Localhost", "localhostProfile": "osmo-bwrap"}
    assert server({})["spec"]["template"]["spec"]["securityContext"]["seccompProfile"] == {
        "type": "RuntimeDefault"}  # the base context is not changed by the merge


@pytest.mark.parametrize("mode", [True, "maybe", ""])
def test_schema_refuses_a_mode_that_is_not_on_auto_or_off(mode: object) -> None:
    """``mode: on`` unquoted is YAML for true: refused, not read as some mode."""
    values = {"sandbox": {"mode": mode}}
    assert any("/sandbox/mode" in p for p in lint(values)), lint(values)
    with pytest.raises(helm.HelmValuesError, match="schema"):
        render(values)


def test_schema_refuses_a_local_pool_that_is_not_a_boolean() -> None:
    with pytest.raises(helm.HelmValuesError, match="schema"):
        render({"server": {"localPool": "yes"}})


def test_host_users_needs_the_proc_mount_removed() -> None:
    """Kubernetes takes ``procMount: Unmasked`` only with ``hostUsers: false``: the chart says
    so at render, and the README's way out (``procMount: null``) renders."""
    with pytest.raises(helm.HelmRenderError, match="only with hostUsers false"):
        render({"sandbox": {"hostUsers": True}})
    dep = worker({"sandbox": {"hostUsers": True, "containerSecurityContext": {"procMount": None}}})
    assert "hostUsers" not in dep["spec"]["template"]["spec"]
    assert "procMount" not in container(dep, "worker")["securityContext"]
    assert flag(container(dep, "worker")["args"], "--sandbox") == ["on"]
