"""What ``helm template`` renders for the osmo chart, object by object.

Each test renders the chart with a few values and asserts on the objects Kubernetes would get:
one worker Deployment per pool with the right ``osmo worker`` flags, the server StatefulSet with
its volume, the Services, probes, and the Secrets wired in when TLS or auth is on.
"""

from __future__ import annotations

import base64

import pytest

from tests.helm.chart import (
    EXAMPLES,
    FULLNAME,
    PEM,
    container,
    env,
    flag,
    load_values,
    mounts,
    render,
    tls_values,
    volumes,
)

TWO_POOLS = {"pools": [
    {"name": "cpu", "replicas": 3, "platform": "x86",
     "resources": {"requests": {"cpu": "500m", "memory": "1Gi"},
                   "limits": {"cpu": "1500m", "memory": "2Gi"}},
     "labels": {"sim": "mujoco", "tier": 2}},
    {"name": "gpu", "replicas": 0,
     "resources": {"limits": {"cpu": 8, "memory": "32Gi", "nvidia.com/gpu": 2}},
     "nodeSelector": {"nvidia.com/gpu.present": "true"},
     "tolerations": [{"key": "nvidia.com/gpu", "operator": "Exists", "effect": "NoSchedule"}],
     "affinity": {"nodeAffinity": {"requiredDuringSchedulingIgnoredDuringExecution": {
         "nodeSelectorTerms": [{"matchExpressions": [
             {"key": "gpu", "operator": "In", "values": ["a100"]}]}]}}},
     "env": [{"name": "MUJOCO_GL", "value": "egl"}],
     "drainTimeout": 1200, "runtimeClassName": "nvidia"},
]}


def workers(values: dict) -> dict[str, dict]:
    """Worker Deployments by pool name."""
    out = render(values)
    deps = [d for d in out.of_kind("Deployment")
            if d["metadata"]["labels"]["app.kubernetes.io/component"] == "worker"]
    return {d["metadata"]["labels"]["osmo.dev/pool"]: d for d in deps}


def test_each_pool_is_one_deployment_with_its_replicas() -> None:
    deps = workers(TWO_POOLS)
    assert sorted(deps) == ["cpu", "gpu"]
    assert deps["cpu"]["metadata"]["name"] == f"{FULLNAME}-worker-cpu"
    assert deps["cpu"]["spec"]["replicas"] == 3
    assert deps["gpu"]["spec"]["replicas"] == 0
    assert len(workers({"pools": []})) == 0


def test_worker_args_come_from_the_pool() -> None:
    args = container(workers(TWO_POOLS)["cpu"], "worker")["args"]
    assert args[:2] == ["worker", "--connect"]
    assert flag(args, "--connect") == [f"tcp/{FULLNAME}:7447"]
    assert flag(args, "--pool") == ["cpu"]
    assert flag(args, "--name") == ["$(POD_NAME)"]
    assert flag(args, "--platform") == ["x86"]
    assert flag(args, "--cpus") == ["1.5"]           # from limits, millicores as a number
    assert flag(args, "--memory") == ["2Gi"]
    assert flag(args, "--gpus") == []
    assert sorted(flag(args, "--label")) == ["sim=mujoco", "tier=2"]
    assert flag(args, "--drain-timeout") == ["600"]
    assert all(isinstance(a, str) for a in args)


def test_gpu_pool_resources_scheduling_and_drain() -> None:
    dep = workers(TWO_POOLS)["gpu"]
    c = container(dep, "worker")
    pod = dep["spec"]["template"]["spec"]
    assert c["resources"]["limits"]["nvidia.com/gpu"] == 2
    assert flag(c["args"], "--gpus") == ["2"]
    assert flag(c["args"], "--cpus") == ["8"]
    assert flag(c["args"], "--memory") == ["32Gi"]
    assert flag(c["args"], "--drain-timeout") == ["1200"]
    assert pod["terminationGracePeriodSeconds"] > 1200
    assert pod["nodeSelector"] == {"nvidia.com/gpu.present": "true"}
    assert pod["tolerations"] == TWO_POOLS["pools"][1]["tolerations"]
    assert pod["affinity"] == TWO_POOLS["pools"][1]["affinity"]
    assert pod["runtimeClassName"] == "nvidia"
    assert env(c)["MUJOCO_GL"] == "egl"


def test_capacity_overrides_what_resources_imply() -> None:
    values = {"pools": [{"name": "p", "replicas": 1, "capacity": {"cpus": 3, "gpus": 0, "memory": "5Gi"},
                         "resources": {"limits": {"cpu": "8", "memory": "9Gi"}}}]}
    args = container(workers(values)["p"], "worker")["args"]
    assert (flag(args, "--cpus"), flag(args, "--gpus"), flag(args, "--memory")) == (["3"], ["0"], ["5Gi"])


def test_requests_are_used_when_there_are_no_limits() -> None:
    values = {"pools": [{"name": "p", "replicas": 1,
                         "resources": {"requests": {"cpu": "250m", "memory": "512Mi"}}}]}
    args = container(workers(values)["p"], "worker")["args"]
    assert (flag(args, "--cpus"), flag(args, "--memory")) == (["0.25"], ["512Mi"])


def test_termination_grace_exceeds_the_drain_timeout() -> None:
    for dep in workers(TWO_POOLS).values():
        drain = int(flag(container(dep, "worker")["args"], "--drain-timeout")[0])
        assert dep["spec"]["template"]["spec"]["terminationGracePeriodSeconds"] > drain


def test_server_statefulset_keeps_osmo_home_on_a_volume_claim() -> None:
    sts = render().get("StatefulSet", f"{FULLNAME}-server")
    assert sts["spec"]["replicas"] == 1
    assert sts["spec"]["serviceName"] == f"{FULLNAME}-server-headless"
    [claim] = sts["spec"]["volumeClaimTemplates"]
    assert claim["metadata"]["name"] == "data"
    assert claim["spec"]["resources"]["requests"]["storage"] == "20Gi"
    c = container(sts, "server")
    assert mounts(c)["data"] == "/var/lib/osmo"
    assert env(c)["OSMO_HOME"] == "/var/lib/osmo/home"  # its own folder on the volume
    assert c["args"][:2] == ["server", "run"]
    assert flag(c["args"], "--listen") == ["tcp/0.0.0.0:7447"]


def test_server_without_persistence_uses_an_empty_dir() -> None:
    sts = render({"server": {"persistence": {"enabled": False}}}).get("StatefulSet", f"{FULLNAME}-server")
    assert "volumeClaimTemplates" not in sts["spec"]
    assert volumes(sts)["data"] == {"name": "data", "emptyDir": {}}


def test_service_exposes_the_zenoh_ports() -> None:
    svc = render().get("Service", FULLNAME)
    assert [(p["name"], p["port"]) for p in svc["spec"]["ports"]] == [("zenoh", 7447)]
    assert svc["spec"]["selector"]["app.kubernetes.io/component"] == "server"
    svc = render(tls_values()).get("Service", FULLNAME)
    assert [(p["name"], p["port"]) for p in svc["spec"]["ports"]] == [("zenoh", 7447), ("zenoh-tls", 7448)]
    headless = render().get("Service", f"{FULLNAME}-server-headless")
    assert headless["spec"]["clusterIP"] == "None"


def test_probes_run_osmo_health() -> None:
    out = render(TWO_POOLS)
    server = container(out.get("StatefulSet", f"{FULLNAME}-server"), "server")
    for probe in ("startupProbe", "livenessProbe", "readinessProbe"):
        cmd = server[probe]["exec"]["command"]
        assert cmd[:2] == ["osmo", "health"] and flag(cmd, "--server") == ["tcp/127.0.0.1:7447"]
    for dep in workers(TWO_POOLS).values():
        c = container(dep, "worker")
        for probe in ("startupProbe", "livenessProbe", "readinessProbe"):
            assert c[probe]["exec"]["command"] == ["osmo", "health", "--worker"]
        assert env(c)["OSMO_HOME"] == "/var/lib/osmo/home"
        assert env(c)["OSMO_SERVER"] == f"tcp/{FULLNAME}:7447"


def test_pods_run_as_non_root_with_resources() -> None:
    out = render(TWO_POOLS)
    for owner in out.of_kind("StatefulSet") + out.of_kind("Deployment"):
        pod = owner["spec"]["template"]["spec"]
        assert pod["securityContext"]["runAsNonRoot"] is True
        assert pod["securityContext"]["runAsUser"] != 0
        assert pod["automountServiceAccountToken"] is False
        for c in pod["containers"]:
            assert c["securityContext"]["allowPrivilegeEscalation"] is False
    server = container(out.get("StatefulSet", f"{FULLNAME}-server"), "server")
    assert server["resources"]["requests"]["memory"] == "512Mi"


def test_tls_secrets_are_created_and_mounted_in_server_and_workers() -> None:
    out = render(tls_values(**TWO_POOLS))
    secret = out.get("Secret", f"{FULLNAME}-tls")
    assert base64.b64decode(secret["data"]["tls.crt"]).decode() == PEM
    sts = out.get("StatefulSet", f"{FULLNAME}-server")
    server = container(sts, "server")
    assert flag(server["args"], "--listen") == ["tcp/0.0.0.0:7447", "tls/0.0.0.0:7448"]
    assert flag(server["args"], "--zenoh-config") == ["/etc/osmo/zenoh/server.json5"]
    assert volumes(sts)["tls-server"]["secret"]["secretName"] == f"{FULLNAME}-tls"
    assert mounts(server)["tls-server"] == "/etc/osmo/tls/server"
    assert volumes(sts)["zenoh-config"]["configMap"]["name"] == f"{FULLNAME}-zenoh"
    for dep in workers(tls_values(**TWO_POOLS)).values():
        c = container(dep, "worker")
        assert flag(c["args"], "--connect") == [f"tls/{FULLNAME}:7448"]
        assert flag(c["args"], "--zenoh-config") == ["/etc/osmo/zenoh/client.json5"]
        assert env(c)["OSMO_ZENOH_CONFIG"] == "/etc/osmo/zenoh/client.json5"
        assert volumes(dep)["tls-server"]["secret"]["secretName"] == f"{FULLNAME}-tls"
        assert mounts(c)["tls-server"] == "/etc/osmo/tls/server"
        assert "tls-client" not in volumes(dep)


def test_tls_only_keeps_tcp_on_loopback_for_the_probes() -> None:
    out = render(tls_values(server={"plainTcp": False}))
    server = container(out.get("StatefulSet", f"{FULLNAME}-server"), "server")
    assert flag(server["args"], "--listen") == ["tcp/127.0.0.1:7447", "tls/0.0.0.0:7448"]
    ports = out.get("Service", FULLNAME)["spec"]["ports"]
    assert [p["name"] for p in ports] == ["zenoh-tls"]


def test_existing_secrets_are_used_and_none_created() -> None:
    values = {"tls": {"enabled": True, "mtls": True, "existingSecret": "my-server-tls",
                      "client": {"existingSecret": "my-worker-tls"}},
              "auth": {"enabled": True, "existingSecret": "my-auth"},
              "tokens": {"existingSecret": "my-tokens"}}
    out = render(values)
    assert out.of_kind("Secret") == []
    sts = out.get("StatefulSet", f"{FULLNAME}-server")
    dep = out.get("Deployment", f"{FULLNAME}-worker-default")
    for owner in (sts, dep):
        vols = volumes(owner)
        assert vols["tls-server"]["secret"]["secretName"] == "my-server-tls"
        assert vols["auth"]["secret"]["secretName"] == "my-auth"
    assert volumes(dep)["tls-client"]["secret"]["secretName"] == "my-worker-tls"
    assert mounts(container(dep, "worker"))["tls-client"] == "/etc/osmo/tls/client"
    assert volumes(sts)["tokens"]["secret"]["secretName"] == "my-tokens"
    ref = next(e for e in container(dep, "worker")["env"] if e["name"] == "OSMO_TOKEN")
    assert ref["valueFrom"]["secretKeyRef"] == {"name": "my-tokens", "key": "worker-default"}


def test_api_tokens_are_on_by_default() -> None:
    out = render(TWO_POOLS)
    secret = out.get("Secret", f"{FULLNAME}-tokens")
    tokens = {k: base64.b64decode(v).decode() for k, v in secret["data"].items()}
    assert sorted(tokens) == ["admin", "worker-cpu", "worker-gpu"]  # one per pool
    assert all(t.startswith("osmo_") and len(t) > 40 for t in tokens.values())
    assert len(set(tokens.values())) == 3
    assert secret["metadata"]["annotations"]["helm.sh/resource-policy"] == "keep"
    sts = out.get("StatefulSet", f"{FULLNAME}-server")
    server = container(sts, "server")
    assert flag(server["args"], "--accept-token") == [  # each pool's token serves that pool
        "helm-admin:admin:/etc/osmo/tokens/admin",
        "helm-worker-cpu:worker@cpu:/etc/osmo/tokens/worker-cpu",
        "helm-worker-gpu:worker@gpu:/etc/osmo/tokens/worker-gpu"]
    assert mounts(server)["tokens"] == "/etc/osmo/tokens"
    assert volumes(sts)["tokens"]["secret"] == {"secretName": f"{FULLNAME}-tokens",
                                                "defaultMode": 0o400}
    for pool, dep in workers(TWO_POOLS).items():
        ref = next(e for e in container(dep, "worker")["env"] if e["name"] == "OSMO_TOKEN")
        assert ref["valueFrom"]["secretKeyRef"] == {"name": f"{FULLNAME}-tokens",
                                                    "key": f"worker-{pool}"}
        assert not any("osmo_" in a for a in container(dep, "worker")["args"])  # env only
    # no zenoh authentication by default: the network listener needs --insecure, and says so
    assert "--insecure" in server["args"]
    assert "WARNING: zenoh authentication is off" in out.notes
    assert "osmo token create" in out.notes
    mtls = {"tls": {"enabled": True, "mtls": True, "existingSecret": "s",
                    "client": {"existingSecret": "c"}}}
    secured = container(render(mtls).get("StatefulSet", f"{FULLNAME}-server"), "server")
    assert "--insecure" not in secured["args"]
    passworded = render({"auth": {"enabled": True, "password": "pw"}})
    assert "--insecure" not in container(passworded.get("StatefulSet", f"{FULLNAME}-server"),
                                         "server")["args"]
    assert "WARNING" not in passworded.notes


def test_auth_secret_and_init_container_fill_in_the_client_config() -> None:
    out = render({"auth": {"enabled": True, "user": "robot", "password": "s3cret"}})
    secret = out.get("Secret", f"{FULLNAME}-auth")
    decoded = {k: base64.b64decode(v).decode() for k, v in secret["data"].items()}
    assert decoded == {"user": "robot", "password": "s3cret", "dictionary": "robot:s3cret\n"}
    for owner in (out.get("StatefulSet", f"{FULLNAME}-server"),
                  out.get("Deployment", f"{FULLNAME}-worker-default")):
        pod = owner["spec"]["template"]["spec"]
        [init] = pod["initContainers"]
        assert init["command"][:2] == ["python", "/etc/osmo/zenoh/render-client-config.py"]
        assert init["command"][-1] == "/run/osmo/zenoh/client.json5"
        assert volumes(owner)["zenoh-client-config"]["emptyDir"]["medium"] == "Memory"
        assert volumes(owner)["auth"]["secret"]["secretName"] == f"{FULLNAME}-auth"
    worker = container(out.get("Deployment", f"{FULLNAME}-worker-default"), "worker")
    assert env(worker)["OSMO_ZENOH_CONFIG"] == "/run/osmo/zenoh/client.json5"
    server = container(out.get("StatefulSet", f"{FULLNAME}-server"), "server")
    assert flag(server["args"], "--zenoh-config") == ["/etc/osmo/zenoh/server.json5"]
    probe = server["livenessProbe"]["exec"]["command"]
    assert probe[:2] == ["env", "OSMO_ZENOH_CONFIG=/run/osmo/zenoh/client.json5"]
    assert probe[2:4] == ["osmo", "health"]
    # The password sits only in the Secret, never in the ConfigMap.
    config_map = out.get("ConfigMap", f"{FULLNAME}-zenoh")
    assert "s3cret" not in str(config_map)


ROUTER = {"router": {"enabled": True}, "auth": {"enabled": True, "password": "pw"}}


def test_router_only_when_enabled() -> None:
    assert [d for d in render().of_kind("Deployment") if d["metadata"]["name"].endswith("-router")] == []
    out = render(ROUTER)
    router = out.get("Deployment", f"{FULLNAME}-router")
    zenohd = container(router, "zenohd")
    assert zenohd["image"] == "eclipse/zenoh:1.10.2"
    assert zenohd["args"] == ["-c", "/etc/osmo/zenoh/router.json5"]
    assert out.get("Service", FULLNAME)["spec"]["selector"]["app.kubernetes.io/component"] == "router"
    server = container(out.get("StatefulSet", f"{FULLNAME}-server"), "server")
    assert flag(server["args"], "--connect") == [f"tcp/{FULLNAME}:7447"]
    assert flag(server["args"], "--listen") == []
    assert flag(server["livenessProbe"]["exec"]["command"], "--server") == [f"tcp/{FULLNAME}:7447"]
    assert "router.json5" in out.get("ConfigMap", f"{FULLNAME}-zenoh")["data"]


def test_example_values_render_cpu_and_gpu_pools_with_existing_tls() -> None:
    values = load_values(EXAMPLES / "cpu-gpu-pools.yaml")
    deps = workers(values)
    assert sorted(deps) == ["cpu", "gpu"]
    gpu = container(deps["gpu"], "worker")
    assert gpu["resources"]["limits"]["nvidia.com/gpu"] == 1
    assert flag(gpu["args"], "--gpus") == ["1"]
    assert deps["gpu"]["spec"]["template"]["spec"]["tolerations"][0]["key"] == "nvidia.com/gpu"
    assert volumes(deps["gpu"])["tls-server"]["secret"]["secretName"] == "osmo-server-tls"
    assert render(values).of_kind("Secret") == []


@pytest.mark.parametrize("values", [{}, TWO_POOLS, ROUTER])
def test_notes_tell_how_to_reach_the_server(values: dict) -> None:
    notes = render(values).notes
    assert f"port-forward svc/{FULLNAME} 7447:7447" in notes
    assert "osmo --server tcp/127.0.0.1:7447" in notes


def test_numeric_quantities_become_plain_numbers() -> None:
    values = {"pools": [{"name": "p", "replicas": 1,
                         "resources": {"limits": {"cpu": 0.5, "memory": 8589934592, "nvidia.com/gpu": 8}}}]}
    args = container(workers(values)["p"], "worker")["args"]
    assert (flag(args, "--cpus"), flag(args, "--memory"), flag(args, "--gpus")) == (["0.5"], ["8589934592"], ["8"])


def test_log_limits_reach_the_server_and_the_workers() -> None:
    assert flag(container(workers(TWO_POOLS)["cpu"], "worker")["args"], "--log-limit") == []
    values = {**TWO_POOLS, "server": {"logLimit": "256Mi"}, "worker": {"logLimit": "32Mi"}}
    rendered = render(values)
    server = container(rendered.get("StatefulSet", f"{FULLNAME}-server"), "server")["args"]
    assert flag(server, "--log-limit") == ["256Mi"]
    assert flag(container(workers(values)["cpu"], "worker")["args"], "--log-limit") == ["32Mi"]


@pytest.mark.parametrize(("worker", "expected"), [
    ({}, []),                                            # the worker's own default
    ({"workdirSizeLimit": "100Gi"}, [str(50 << 30)]),    # half the emptyDir's limit
    ({"workdirSizeLimit": "10G"}, [str(5 * 10**9)]),
    ({"workdirSizeLimit": "100Gi", "storeLimit": "20Gi"}, ["20Gi"]),
])
def test_the_worker_store_limit_stays_below_the_scratch_limit(worker: dict, expected: list) -> None:
    args = container(workers({**TWO_POOLS, "worker": worker})["cpu"], "worker")["args"]
    assert flag(args, "--store-limit") == expected
