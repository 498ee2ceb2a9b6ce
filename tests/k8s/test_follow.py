"""One attempt's pod through the real client against the stand-in: the status table's rows
played by status scripts, the watch's recoveries (410 Gone, a watch gone silent), logs, the
kill (delete with the 3 s grace) and the clean-up (the pod and its owned Secret go).
"""

from __future__ import annotations

import io
import threading
from typing import Any

import pytest

from osmo.runtime.container.run import RegistryAuth
from osmo.runtime.kubernetes.config import KubePool
from osmo.runtime.kubernetes.follow import PodFollower
from osmo.runtime.kubernetes.kube import Kube
from osmo.runtime.kubernetes.manifest import PodPlan, pod_manifest, secret_manifest
from osmo.runtime.kubernetes.podwatch import PodWatch
from osmo.runtime.kubernetes.status import Outcome, Verdict
from tests.k8s import scripts
from tests.k8s.conftest import Cluster
from tests.k8s.scripts import SCRIPTS, Script
from tests.k8s.store import PODS, SECRETS

POOL = KubePool(namespace="default")


def plan(name: str, command: str = "true", **extra: Any) -> PodPlan:
    return PodPlan(attempt_id=f"wf-1:{name}:0", workflow_id="wf-1", task=name, retry=0,
                   instance="test", image="alpine:3.18", argv=("sh", "-c", command), **extra)


class Run:
    """A follower of one pod, its log and notes."""

    def __init__(self, api: Cluster, plan: PodPlan, secret: dict[str, str] | None = None,
                 silence: int = 20, watch: PodWatch | None = None) -> None:
        self.out, self.notes, self.stop = io.BytesIO(), [], threading.Event()
        self.waits: list[str] = []
        self.name = plan.name
        body = pod_manifest(plan, POOL, secret=plan.name if secret else None)
        owned = secret_manifest(plan, secret, POOL, owner_uid="") if secret else None
        self.follower = PodFollower(Kube(api.client), body, owned, out=self.out,
                                    note=self.notes.append, stop=self.stop, silence=silence,
                                    waiting=self.waits.append, watch=watch)

    def run(self) -> Verdict:
        return self.follower.run()


def scripted(api: Cluster, script: Script, task: str = "scripted", silence: int = 20,
             watch: PodWatch | None = None) -> Run:
    made = Run(api, plan(task), silence=silence, watch=watch)
    api.kubelet.script(made.name, script)
    return made


@pytest.mark.parametrize(("script", "outcome", "code", "words"), [
    ("unschedulable-running-succeeded", Outcome.EXITED, 0, ""),
    ("image-pull-error", Outcome.START_FAILED, None, "nvcr.io/nvidia/nosuch:1.0"),
    ("oom-killed", Outcome.EXITED, 137, "OOMKilled"),
    ("evicted", Outcome.LOST, None, "evicted"),
    ("preempted", Outcome.LOST, None, "PreemptionByScheduler"),
    ("node-lost", Outcome.LOST, None, "node was lost"),
])
def test_each_scripted_life_gives_its_verdict(api: Cluster, script: str, outcome: Outcome,
                                              code: int | None, words: str) -> None:
    run = scripted(api, SCRIPTS[script])
    found = run.run()
    assert (found.outcome, found.exit_code) == (outcome, code), found
    assert words in found.message, found
    assert api.core.list_namespaced_pod("default").items == []  # deleted whatever happened


def test_unschedulable_is_said_once_then_cleared_and_the_log_arrives(api: Cluster) -> None:
    run = scripted(api, SCRIPTS["unschedulable-running-succeeded"])
    assert run.run().exit_code == 0
    assert any("unschedulable: 0/1 nodes are available" in n for n in run.notes), run.notes
    [reason, cleared] = run.waits  # once per reason, whatever the watch repeats; then ""
    assert reason == "unschedulable: 0/1 nodes are available: 1 Insufficient nvidia.com/gpu."
    assert cleared == ""
    assert run.out.getvalue() == b"hello from a script\n"


def test_a_silent_watch_is_replaced(api: Cluster) -> None:
    run = scripted(api, SCRIPTS["watch-stalls"], silence=1)
    assert run.run().exit_code == 0


def test_followers_share_one_watch_of_the_nodes_pods(api: Cluster) -> None:
    shared = PodWatch(Kube(api.client), "default", labels="osmo.dev/instance=test")
    runs = [scripted(api, SCRIPTS["unschedulable-running-succeeded"], task=f"t{i}",
                     watch=shared) for i in range(3)]
    runs.append(scripted(api, SCRIPTS["evicted"], task="lost", watch=shared))
    done: dict[str, Verdict] = {}
    threads = [threading.Thread(target=lambda r=r: done.update({r.name: r.run()}))
               for r in runs]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    assert [(done[r.name].outcome, done[r.name].exit_code) for r in runs] == [
        (Outcome.EXITED, 0)] * 3 + [(Outcome.LOST, None)], done
    assert all(r.out.getvalue() == b"hello from a script\n" for r in runs[:3])
    assert api.server.calls[("watch", "pods")] == 1  # not one per pod
    assert api.core.list_namespaced_pod("default").items == []


def test_a_watch_too_old_lists_again(api: Cluster) -> None:
    go = threading.Event()
    script = Script((scripts.scheduled(), scripts.running(), scripts.stall_watches(),
                     scripts.wait(go), scripts.succeeded()))
    run = scripted(api, script, silence=2)
    done: list[Verdict] = []
    thread = threading.Thread(target=lambda: done.append(run.run()))
    thread.start()
    while not any(c[0] == "watch" for c in api.server.calls) and thread.is_alive():
        thread.join(0.05)
    api.server.store.compact()  # the next watch from the follower's version gets 410
    go.set()
    thread.join(60)
    assert done and done[0].exit_code == 0, done
    assert api.server.calls[("list", "pods")] >= 1


def test_a_real_pod_exits_with_its_code_and_log(api: Cluster, images: dict[str, str]) -> None:
    run = Run(api, plan("real", "echo out; echo err >&2; exit 3"))
    found = run.run()
    assert (found.outcome, found.exit_code) == (Outcome.EXITED, 3)
    assert sorted(run.out.getvalue().decode().split()) == ["err", "out"]
    assert api.server.writes == {("create", "pods"): 1, ("delete", "pods"): 1}


def test_credentials_go_in_a_secret_owned_by_the_pod(api: Cluster,
                                                     images: dict[str, str]) -> None:
    run = Run(api, plan("cred", 'echo "token=$TOKEN"', secret_env=("TOKEN",)),
              secret={"TOKEN": "s3cr3t"})
    found = run.run()
    assert found.exit_code == 0 and run.out.getvalue() == b"token=s3cr3t\n"
    assert api.server.writes == {("create", "pods"): 1, ("create", "secrets"): 1,
                                 ("delete", "pods"): 1}  # the Secret goes with its owner
    assert list(api.server.store.objects([PODS, SECRETS])) == []


def test_a_pull_secret_is_made_before_its_pod_and_deleted_after(
        api: Cluster, images: dict[str, str]) -> None:
    pulled = plan("pulled", "true")
    secret = secret_manifest(pulled, {}, POOL, registry=RegistryAuth("r.example", "u", "p"))
    follower = PodFollower(Kube(api.client), pod_manifest(pulled, POOL, secret=pulled.name,
                                                          pulls_with_secret=True),
                           secret, out=io.BytesIO(), note=print, stop=threading.Event())
    assert follower.run().exit_code == 0
    assert api.server.writes == {("create", "secrets"): 1, ("create", "pods"): 1,
                                 ("delete", "pods"): 1, ("delete", "secrets"): 1}
    assert list(api.server.store.objects([PODS, SECRETS])) == []


def test_a_kill_deletes_the_pod_with_its_grace(api: Cluster, images: dict[str, str]) -> None:
    run = Run(api, plan("killed", "trap 'exit 143' TERM; echo up; while :; do sleep 0.1; done"))
    done: list[Verdict] = []
    thread = threading.Thread(target=lambda: done.append(run.run()))
    thread.start()
    while b"up" not in run.out.getvalue() and thread.is_alive():
        thread.join(0.1)
    run.stop.set()
    thread.join(60)
    assert done and (done[0].outcome, done[0].exit_code) == (Outcome.EXITED, 143), done
    assert any("3 s grace" in n for n in run.notes), run.notes
    assert api.core.list_namespaced_pod("default").items == []
