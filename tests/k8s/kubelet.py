"""The stand-in's node side: scheduler, kubelet and garbage of one fake node group.

It follows the store's events (never HTTP) and acts as the control plane and the node do:

- **Scheduling** (``scheduling.py``): a new pod is bound to a node it fits, with its gang
  when it has one, or stays Pending with PodScheduled False, reason Unschedulable, and the
  scheduler's message. Pending pods are tried again when a pod goes or finishes, a node or
  a PodGroup appears, or a gang member arrives.
- **Running**: a bound pod's Secrets are resolved (a missing one keeps it waiting, reason
  CreateContainerConfigError for env or ContainerCreating for a volume, until it appears),
  then it is played with ``podman kube play`` (``podman_pods.py``). One observer looks at a
  pod's containers (``podman inspect``, one call for all the pods that changed) when podman's
  event stream says one of them started, died or was OOM-killed, or when its play ended, and
  every :data:`RELIST` seconds at all of them (as the kubelet's PLEG relists), and publishes
  the pod's status: phase, initContainerStatuses,
  containerStatuses (waiting/running/terminated with exitCode and reason Completed, Error or
  OOMKilled), conditions, podIP and hostIP (both 127.0.0.1: pods share the host's
  network). An image that cannot be pulled shows ErrImagePull with podman's message, then
  ImagePullBackOff (the pull is not retried). Native sidecars are stopped once the regular
  containers have exited.
- **Deletion**: a graceful delete stops the pod (SIGTERM, SIGKILL after the grace),
  publishes the containers' last states, then removes it from the API; a forced or
  immediate delete removes it from the API at once. What podman keeps of a deleted pod is
  garbage, removed every :data:`GC_PERIOD` seconds in one ``podman pod rm`` (as the
  kubelet's housekeeping removes dead pods' containers and sandboxes), or at once when a
  new pod needs its name.
- **Exec**: ``pods/exec`` runs ``podman exec -i`` in the running container.
- **Port-forward**: ``pods/portforward`` connects to the pod's port on the host's loopback
  (where a pod's processes listen here).
- **Logs**: ``pods/log`` reads the container's log file (CRI format, podman's ``k8s-file``
  driver; ``follow`` streams until the container exited), as the kubelet does; a container
  that has not started is a 400 "is waiting to start".
- **Status scripts** (``scripts.py``): a pod whose name has a script registered plays it
  instead of podman.

:meth:`Kubelet.close` deletes what is left and reports what podman still has.
"""

from __future__ import annotations

import queue
import socket
import subprocess
import tempfile
import threading
import uuid
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tests.k8s import scheduling
from tests.k8s import store as st
from tests.k8s.apiserver import ApiServer
from tests.k8s.podman_pods import (
    PULL_FAILURES,
    ContainerState,
    MissingSecret,
    PodmanPods,
    read_log,
)
from tests.k8s.podman_pods import translate as to_podman
from tests.k8s.scripts import Script
from tests.k8s.store import ApiError, Event, Obj
from tests.k8s.validation import decode_secret_data

__all__ = ["Kubelet"]

RELIST = 5.0  # seconds between two looks at every running pod's containers (events between)
GC_PERIOD = 2.0  # seconds between two removals of deleted pods from podman
BACKOFF = 1.0  # seconds from ErrImagePull to ImagePullBackOff
PLAY_WAIT = 30.0  # seconds a deleted pod's play may take to end before it is killed
HOST_IP = "127.0.0.1"  # every pod shares the host's network (podman_pods.py says why)


@dataclass
class _Pod:
    """What the node knows of one pod."""

    namespace: str
    name: str
    uid: str
    podman: str
    script: Script | None = None
    node: str = ""
    stage: str = "pending"  # pending, waiting, playing, running, done, deleting, gone
    play: Any = None  # the kube play process while it runs
    sidecars: list[str] = field(default_factory=list)
    limited: set[str] = field(default_factory=set)  # containers with a memory limit
    seen: dict[str, ContainerState] = field(default_factory=dict)
    waiting: tuple[str, str] | None = None  # (reason, message) for every container
    started: str = ""
    stopping_sidecars: bool = False
    killed: bool = False  # the node stopped it (an exit 137 is then no OOM)
    times: dict[str, str] = field(default_factory=dict)  # condition → lastTransitionTime


class Kubelet:
    """The node side of an :class:`ApiServer`: attach, add nodes, create pods, close.

    Args:
        api: the server whose store it follows (its ``log_source`` becomes this kubelet).
        env: the environment for podman (``CONTAINERS_CONF`` on these machines).
        folder: a private folder for manifests and Secret files (a temporary one if None).
    """

    def __init__(self, api: ApiServer, env: Mapping[str, str],
                 folder: Path | None = None) -> None:
        self.api, self.store = api, api.store
        self.prefix = f"k8s-{uuid.uuid4().hex[:8]}"
        self._tmp = None if folder else tempfile.TemporaryDirectory(prefix="osmo-kubelet-")
        base = folder or Path(self._tmp.name if self._tmp else ".")
        base.mkdir(parents=True, exist_ok=True)
        base.chmod(0o700)
        self.podman = PodmanPods(env, self.prefix, base)
        self._pods: dict[str, _Pod] = {}  # by uid
        self._scripts: dict[tuple[str, str], Script] = {}
        self._lock = threading.RLock()
        self._work: queue.Queue[Event | str | None] = queue.Queue()
        self._closed = threading.Event()
        self._threads: list[threading.Thread] = []
        self._containers: dict[str, str] = {}  # podman container name → its pod's uid
        self._changed: set[str] = set()  # uids whose containers podman said changed
        self._wake = threading.Event()  # set when _changed grew
        self._garbage: set[str] = set()  # podman pods of deleted pods, not yet removed
        self._gc_lock = threading.Lock()  # held while garbage is removed
        api.log_source = self
        api.exec_source = self
        self.store.listen(self._work.put)
        self._podman_events = self.podman.events(self._container_changed)
        self._spawn(self._control, "k8s-kubelet")
        self._spawn(self._poll, "k8s-poller")
        self._spawn(self._collect_garbage, "k8s-gc")

    # ------------------------------------------------------------------ public

    def add_node(self, name: str = "node-1", **capacity: Any) -> Obj:
        """Create a Ready node (``scheduling.node`` arguments: cpu, memory, gpus, labels,
        taints)."""
        return self.store.create(st.NODES, None, scheduling.node(name, **capacity))

    def script(self, name: str, script: Script, namespace: str = "default") -> None:
        """Play ``script`` instead of podman for the pod called ``name`` (create it after)."""
        with self._lock:
            self._scripts[(namespace, name)] = script

    def close(self) -> tuple[list[str], list[str]]:
        """Stop: remove every pod still in podman; return what podman still had afterwards
        (pods, containers): both empty when all went well."""
        self._closed.set()
        self._work.put(None)
        self._wake.set()
        control, poller, collector = self._threads[:3]
        control.join(timeout=60)  # no new work after this
        poller.join(timeout=60)
        collector.join(timeout=60)
        self._podman_events.terminate()
        self._podman_events.wait()
        with self._lock:
            left = [p for p in self._pods.values() if p.script is None]
            for pod in left:
                if pod.play is not None and pod.play.poll() is None:
                    pod.play.kill()
            threads = list(self._threads)
        for thread in threads:
            thread.join(timeout=60)
        for pod in left:
            self.podman.remove(pod.podman)
        self.sweep()
        leftovers = self.podman.leftovers()
        if self._tmp is not None:
            self._tmp.cleanup()
        return leftovers

    def __enter__(self) -> Kubelet:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ threads

    def _spawn(self, target: Any, name: str, *args: Any) -> None:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        thread.start()
        with self._lock:  # the first three (control, poller, gc) stay: close() joins them first
            self._threads = self._threads[:3] + [
                t for t in self._threads[3:] if t.is_alive()] + [thread]

    def _control(self) -> None:
        """Handle the store's events one at a time (the listener only queues them)."""
        while True:
            item = self._work.get()
            if item is None or self._closed.is_set():
                return
            try:
                self._handle(item)
            except Exception as exc:  # noqa: BLE001 - one bad event must not stop the node
                print(f"k8s stand-in kubelet: {item!r}: {exc!r}")

    def _handle(self, item: Event | str) -> None:
        if item == "schedule":
            self._schedule()
            return
        if isinstance(item, str):  # "backoff:<uid>"
            self._backoff(item.split(":", 1)[1])
            return
        if item.res == st.PODS:
            self._pod_event(item)
        if item.res == st.SECRETS and item.type == "ADDED":
            with self._lock:
                waiting = [p for p in self._pods.values() if p.stage == "waiting"]
            for pod in waiting:
                self._start(pod)
        if item.res in (st.NODES, st.KAI, st.VOLCANO, st.COSCHEDULING) or (
                item.res == st.PODS and item.type in ("ADDED", "DELETED")):
            self._schedule()

    def _pod_event(self, event: Event) -> None:
        meta = event.obj["metadata"]
        uid = meta["uid"]
        with self._lock:
            pod = self._pods.get(uid)
            if event.type == "ADDED" and pod is None:
                key = (meta.get("namespace") or "default", meta["name"])
                pod = _Pod(key[0], key[1], uid, self.podman.podman_name(*key),
                           script=self._scripts.pop(key, None))
                self._pods[uid] = pod
                if pod.script is not None:
                    self._spawn(self._play_script, f"k8s-script-{key[1]}", pod)
                return
        if pod is None:
            return
        if event.type == "DELETED":
            self._forget(pod)
        elif "deletionTimestamp" in meta and pod.stage not in ("deleting", "gone"):
            pod.stage = "deleting"
            grace = int(meta.get("deletionGracePeriodSeconds") or 0)
            self._spawn(self._terminate, f"k8s-delete-{pod.name}", pod, grace)

    # ------------------------------------------------------------------ scheduling

    def _schedule(self) -> None:
        with self._lock:
            mine = {uid: p for uid, p in self._pods.items()
                    if p.stage == "pending" and p.script is None}
        if not mine:
            return  # an empty queue: nothing to list (every pod's end would list them all)
        pods, _ = self.store.list(st.PODS)
        nodes, _ = self.store.list(st.NODES)
        live = [p for p in pods if "deletionTimestamp" not in p["metadata"]]
        bound = [p for p in live if p["spec"].get("nodeName")
                 and p.get("status", {}).get("phase") not in ("Succeeded", "Failed")]
        tried: set[str] = set()
        for obj in live:
            uid = obj["metadata"]["uid"]
            if uid not in mine or uid in tried or obj["spec"].get("nodeName"):
                continue
            gang = scheduling.gang_of(obj)
            group = [obj] if gang is None else [p for p in live if scheduling.gang_of(p) == gang]
            unbound = [p for p in group if not p["spec"].get("nodeName")
                       and p["metadata"]["uid"] in mine]
            tried |= {p["metadata"]["uid"] for p in unbound}
            why = ""
            if gang is not None:
                need, why = scheduling.min_member(gang, self.store, group)
                if need is not None and len(group) < need:
                    why = (f"pod group {gang.name!r} has {len(group)} of its minMember {need} "
                           "pods")
            chosen: dict[str, str] = {}
            if not why:
                chosen, why = scheduling.place(unbound, nodes, bound)
            for member in unbound:
                target = mine[member["metadata"]["uid"]]
                if chosen:
                    self._bind(target, chosen[member["metadata"]["name"]])
                    bound.append({**member, "spec": {**member["spec"],
                                                     "nodeName": target.node}})
                else:
                    self._publish(target, unschedulable=why)

    def _bind(self, pod: _Pod, node: str) -> None:
        with self._lock:
            pod.node, pod.started = node, st.now()

        def change(obj: Obj) -> None:
            obj["spec"]["nodeName"] = node
        self._update(pod, change)
        self._start(pod)

    # ------------------------------------------------------------------ running

    def _secret(self, namespace: str) -> Any:
        def lookup(name: str) -> dict[str, bytes] | None:
            found = self.store.find(st.SECRETS, namespace, name)
            return None if found is None else decode_secret_data(found.get("data") or {})
        return lookup

    def _start(self, pod: _Pod) -> None:
        obj = self.store.find(st.PODS, pod.namespace, pod.name)
        if obj is None or "deletionTimestamp" in obj["metadata"]:
            return
        try:
            manifest, sidecars = to_podman(obj, pod.podman, self.prefix,
                                           self.podman.folder / pod.podman,
                                           self._secret(pod.namespace), pod.node)
        except MissingSecret as missing:
            with self._lock:
                pod.stage = "waiting"
                pod.waiting = ("CreateContainerConfigError" if missing.for_env
                               else "ContainerCreating", str(missing))
            self._publish(pod)
            return
        self._reclaim(pod.podman)
        path = self.podman.write(pod.podman, manifest)
        with self._lock:
            for container in self.podman.played[pod.podman]:
                self._containers[f"{pod.podman}-{container}"] = pod.uid
            pod.stage, pod.waiting, pod.sidecars = "playing", None, sidecars
            pod.limited = {c["name"] for c in obj["spec"]["containers"]
                           + obj["spec"].get("initContainers", [])
                           if ((c.get("resources") or {}).get("limits") or {}).get("memory")}
            if "osmo-standin-inits" not in manifest["spec"]:
                self.podman.make_sub_paths(manifest)
                pod.play = self.podman.play(path)
        self._publish(pod)
        self._spawn(self._await_play, f"k8s-play-{pod.name}", pod, manifest, path)

    def _await_play(self, pod: _Pod, manifest: Obj, path: Path) -> None:
        if pod.play is None:  # init containers first, on their own (podman_pods.py)
            failed = self.podman.run_inits(pod.podman, manifest)
            with self._lock:
                stage = pod.stage
            if stage == "gone":
                self._discard(pod)  # its init containers may have come after
            with self._lock:
                if pod.stage != "playing":
                    return  # deleted meanwhile
                if failed:
                    pod.stage = "running"  # the poller publishes the failed init container
                    self._look_at(pod.uid)
                    return
                self.podman.make_sub_paths(manifest)
                pod.play = self.podman.play(path)
        out, err = pod.play.communicate()
        with self._lock:
            failed = pod.play.returncode != 0
            pod.play = None
            gone = pod.stage == "gone"
            if pod.stage != "playing" and not gone:
                return  # being deleted: _terminate removes it
        if gone:  # it left the API while being played: what the play made goes too
            self._discard(pod)
            return
        with self._lock:
            pod.stage = "running"
            self._look_at(pod.uid)  # its containers run now (or ran)
            if failed and "init container" not in err:
                pull = any(marker in err for marker in PULL_FAILURES)
                message = " ".join(line for line in err.strip().splitlines()
                                   if not line.startswith(("time=", "Trying to pull",
                                                           "failed to connect to syslog")))
                pod.waiting = ("ErrImagePull" if pull else "CreateContainerError",
                               message or err.strip())
                pod.stage = "waiting-pull" if pull else "failed-create"
        if pod.waiting is not None:
            self.podman.remove(pod.podman)
            self._publish(pod)
            if pod.stage == "waiting-pull":
                threading.Timer(BACKOFF, self._work.put, (f"backoff:{pod.uid}",)).start()

    def _backoff(self, uid: str) -> None:
        with self._lock:
            pod = self._pods.get(uid)
            if pod is None or pod.stage != "waiting-pull" or pod.waiting is None:
                return
            obj = self.store.find(st.PODS, pod.namespace, pod.name)
            image = obj["spec"]["containers"][0].get("image", "") if obj else ""
            pod.waiting = ("ImagePullBackOff", f'Back-off pulling image "{image}"')
        self._publish(pod)

    def _container_changed(self, name: str) -> None:
        """podman's events: container ``name`` started, died or was OOM-killed."""
        with self._lock:
            uid = self._containers.get(name)
            if uid is not None:
                self._look_at(uid)

    def _look_at(self, uid: str) -> None:
        """Have the poller look at this pod's containers soon (the lock is held)."""
        self._changed.add(uid)
        self._wake.set()

    def _poll(self) -> None:
        """Look at the containers of the pods that changed (all, every RELIST seconds);
        publish what changed."""
        while not self._closed.is_set():
            told = self._wake.wait(RELIST)
            if self._closed.is_set():
                return
            self._wake.clear()
            with self._lock:
                uids = self._changed if told else set(self._pods)
                self._changed = set()
                active = [p for uid, p in self._pods.items()
                          if uid in uids and p.stage in ("playing", "running")]
            if not active:
                continue
            try:
                self._observe(active)
            except Exception as exc:  # noqa: BLE001 - the poller must outlive one bad look
                print(f"k8s stand-in poller: {exc!r}")

    def _observe(self, pods: list[_Pod]) -> None:
        states = self.podman.states({p.podman: self.podman.played.get(p.podman, [])
                                     for p in pods})
        for pod in pods:
            seen = states.get(pod.podman, {})
            with self._lock:
                if pod.stage not in ("playing", "running"):
                    continue
                changed = seen != pod.seen
                pod.seen = seen
                regular = [n for n in seen if n not in pod.sidecars]
                finished = bool(regular) and all(seen[n].ended for n in regular)
                stop = [f"{pod.podman}-{n}" for n in pod.sidecars
                        if finished and not pod.stopping_sidecars and n in seen
                        and not seen[n].ended]
                if stop:
                    pod.stopping_sidecars = True
            if stop:
                self._spawn(self.podman.stop_containers, f"k8s-sidecars-{pod.name}", stop, 10)
            if changed:
                phase = self._publish(pod)
                if phase in ("Succeeded", "Failed") and all(s.ended for s in seen.values()):
                    with self._lock:
                        if pod.stage == "running":
                            pod.stage = "done"
                    self._work.put("schedule")  # what it held is free again

    # ------------------------------------------------------------------ status

    def _update(self, pod: _Pod, change: Any) -> Obj | None:
        try:
            return self.store.update(st.PODS, pod.namespace, pod.name, change)
        except ApiError:
            return None  # it went meanwhile

    def _publish(self, pod: _Pod, unschedulable: str = "") -> str:
        """Publish the pod's status from what the node knows; return the phase."""
        obj = self.store.find(st.PODS, pod.namespace, pod.name)
        if obj is None:
            return ""
        with self._lock:
            status = self._status(pod, obj, unschedulable)

        def change(current: Obj) -> None:
            current["status"] = status
        self._update(pod, change)
        return str(status["phase"])

    def _status(self, pod: _Pod, obj: Obj, unschedulable: str) -> Obj:
        spec = obj["spec"]
        inits = [c for c in spec.get("initContainers") or [] if c["name"] not in pod.sidecars]
        sidecars = [c for c in spec.get("initContainers") or [] if c["name"] in pod.sidecars]
        status: Obj = {"qosClass": obj.get("status", {}).get("qosClass", "BestEffort")}
        if unschedulable:
            status["phase"] = "Pending"
            status["conditions"] = [self._condition(pod, "PodScheduled", False, "Unschedulable",
                                                    unschedulable)]
            return status
        init_states = [self._container(pod, c, "PodInitializing") for c in inits + sidecars]
        inits_done = all(self._ended_ok(pod, c["name"]) for c in inits)
        main_states = [self._container(pod, c, "ContainerCreating" if inits_done
                                       else "PodInitializing") for c in spec["containers"]]
        phase = self._phase(pod, inits, spec["containers"], spec.get("restartPolicy"))
        ready = all("running" in s["state"] for s in main_states)
        status.update(phase=phase, hostIP=HOST_IP, hostIPs=[{"ip": HOST_IP}],
                      startTime=pod.started, containerStatuses=main_states)
        if init_states:
            status["initContainerStatuses"] = init_states
        if any(s.state == "running" or s.ended for s in pod.seen.values()):
            status.update(podIP=HOST_IP, podIPs=[{"ip": HOST_IP}])  # the host's network
        done = "PodCompleted" if phase in ("Succeeded", "Failed") else "ContainersNotReady"
        status["conditions"] = [
            self._condition(pod, "PodScheduled", True),
            self._condition(pod, "Initialized", inits_done, "" if inits_done
                            else "ContainersNotInitialized"),
            self._condition(pod, "ContainersReady", ready, "" if ready else done),
            self._condition(pod, "Ready", ready, "" if ready else done)]
        return status

    def _condition(self, pod: _Pod, kind: str, value: bool, reason: str = "",
                   message: str = "") -> Obj:
        mark = f"{kind}={value}"
        if mark not in pod.times:
            pod.times = {k: v for k, v in pod.times.items() if not k.startswith(kind + "=")}
            pod.times[mark] = st.now()
        entry = {"type": kind, "status": str(value), "lastTransitionTime": pod.times[mark]}
        if reason:
            entry["reason"] = reason
        if message:
            entry["message"] = message
        return entry

    def _ended_ok(self, pod: _Pod, name: str) -> bool:
        seen = pod.seen.get(name)
        return seen is not None and seen.ended and seen.exit_code == 0

    def _phase(self, pod: _Pod, inits: list[Obj], containers: list[Obj],
               restart: str | None) -> str:
        seen = pod.seen
        if any(seen.get(c["name"]) and seen[c["name"]].ended and seen[c["name"]].exit_code
               for c in inits) and restart != "Always":
            return "Failed"
        states = [seen.get(c["name"]) for c in containers]
        if states and all(s is not None and s.ended for s in states):
            if restart == "Always":
                return "Running"
            return "Succeeded" if all(s and s.exit_code == 0 for s in states) else "Failed"
        if any(s is not None and (s.state == "running" or s.ended) for s in states):
            return "Running"
        return "Pending"

    def _container(self, pod: _Pod, spec: Obj, before: str) -> Obj:
        name = spec["name"]
        seen = pod.seen.get(name)
        base: Obj = {"name": name, "image": spec.get("image", ""), "imageID": "",
                     "restartCount": 0, "ready": False, "started": False}
        if pod.waiting is not None:
            reason, message = pod.waiting
            return {**base, "state": {"waiting": {"reason": reason, "message": message}}}
        if seen is None or not (seen.state == "running" or seen.ended):
            return {**base, "state": {"waiting": {"reason": before}}}
        base.update(containerID=f"podman://{seen.container_id}",
                    imageID=f"sha256:{seen.image_id}")
        if seen.state == "running":
            return {**base, "ready": True, "started": True,
                    "state": {"running": {"startedAt": seen.started}}}
        oom = seen.oom_killed or (seen.exit_code == 137 and name in pod.limited
                                  and not pod.killed)
        reason = "OOMKilled" if oom else ("Completed" if seen.exit_code == 0 else "Error")
        return {**base, "state": {"terminated": {
            "exitCode": seen.exit_code, "reason": reason, "startedAt": seen.started,
            "finishedAt": seen.finished or st.now(),
            "containerID": f"podman://{seen.container_id}"}}}

    # ------------------------------------------------------------------ deletion

    def _terminate(self, pod: _Pod, grace: int) -> None:
        """A graceful delete: stop, publish the last states, remove from podman and API."""
        if pod.script is None:
            with self._lock:
                play, pod.killed = pod.play, True
            if play is not None and play.poll() is None:
                try:  # let it end (killed half-way it can leave a pod no removal saw)
                    play.wait(timeout=PLAY_WAIT)
                except subprocess.TimeoutExpired:
                    play.kill()
            # the containers first, then the pod's sandbox, as the kubelet does: stopping the
            # infra container at once would kill a shared PID namespace's processes outright
            self.podman.stop_containers([f"{pod.podman}-{c}" for c in
                                         self.podman.played.get(pod.podman, [])], grace)
            self.podman.stop(pod.podman, grace)
            seen = self.podman.states({pod.podman: self.podman.played.get(pod.podman, [])}
                                      ).get(pod.podman, {})
            with self._lock:
                pod.seen = {**pod.seen, **seen}
            self._publish(pod)
            self._discard(pod)
        else:
            def change(obj: Obj) -> None:
                for status in obj.get("status", {}).get("containerStatuses") or []:
                    if "terminated" not in status.get("state", {}):
                        status["state"] = {"terminated": {"exitCode": 137, "reason": "Error",
                                                          "finishedAt": st.now()}}
            self._update(pod, change)
        self.store.remove(st.PODS, pod.namespace, pod.name)

    def _forget(self, pod: _Pod) -> None:
        """The pod left the API: make sure podman has nothing of it either."""
        with self._lock:
            self._pods.pop(pod.uid, None)
            was, pod.stage = pod.stage, "gone"
            play = pod.play
        if play is not None and play.poll() is None:
            # its play ends first (killing it half-way can leave a pod no removal saw)
            self._spawn(self._remove_after_play, f"k8s-remove-{pod.name}", pod, play)
        elif pod.script is None and was not in ("deleting", "pending"):
            self._discard(pod)

    def _remove_after_play(self, pod: _Pod, play: Any) -> None:
        try:
            play.wait(timeout=PLAY_WAIT)
        except subprocess.TimeoutExpired:
            play.kill()
            play.wait()
        self._discard(pod)

    def _discard(self, pod: _Pod) -> None:
        """What podman has of a deleted pod is garbage: the next sweep removes it."""
        with self._lock:
            self._garbage.add(pod.podman)
            for container in self.podman.played.get(pod.podman, []):
                self._containers.pop(f"{pod.podman}-{container}", None)

    def _collect_garbage(self) -> None:
        while not self._closed.wait(GC_PERIOD):
            try:
                self.sweep()
            except Exception as exc:  # noqa: BLE001 - the collector must outlive one failure
                print(f"k8s stand-in gc: {exc!r}")

    def sweep(self) -> None:
        """Remove every deleted pod from podman now (one ``podman pod rm``)."""
        with self._gc_lock:
            with self._lock:
                batch, self._garbage = sorted(self._garbage), set()
            self.podman.remove_many(batch)

    def _reclaim(self, podman_name: str) -> None:
        """A new pod takes the name of a deleted one: that one goes from podman first."""
        with self._gc_lock:
            with self._lock:
                if podman_name not in self._garbage:
                    return
                self._garbage.discard(podman_name)
            self.podman.remove_many([podman_name])

    # ------------------------------------------------------------------ scripts

    def _play_script(self, pod: _Pod) -> None:
        assert pod.script is not None
        nodes, _ = self.store.list(st.NODES)
        pod.node = nodes[0]["metadata"]["name"] if nodes else "node-1"
        view = _ScriptView(self, pod)
        for step in pod.script.steps:
            if self._closed.wait(pod.script.pause) or pod.stage in ("deleting", "gone"):
                return
            step.act(view)

    # ------------------------------------------------------------------ logs

    def pod_logs(self, pod: Obj, container: str, *, follow: bool, tail: int | None,
                 timestamps: bool) -> Iterator[bytes]:
        """The log of one container (``LogSource``); ApiError 400 before it started."""
        with self._lock:
            known = self._pods.get(pod["metadata"]["uid"])
            seen = known.seen.get(container) if known else None
            script = known.script if known else None
            waiting = known.waiting if known else None
        if script is not None:
            yield script.logs.encode()
            return
        if known is None or seen is None or not (seen.state == "running" or seen.ended):
            reason = waiting[0] if waiting else "ContainerCreating"
            raise ApiError(400, "BadRequest", f'container "{container}" in pod '
                           f'"{pod["metadata"]["name"]}" is waiting to start: {reason}')
        if not seen.log_path:  # another log driver than k8s-file: podman reads it
            yield from self.podman.logs(f"{known.podman}-{container}", follow=follow,
                                        tail=tail, timestamps=timestamps)
            return
        yield from read_log(seen.log_path, follow=follow, tail=tail, timestamps=timestamps,
                            ended=lambda: self._over(known, container))

    def _over(self, pod: _Pod, container: str) -> bool:
        """Whether a container's log can grow no more (it ended, or its pod went)."""
        with self._lock:
            seen = pod.seen.get(container)
            return pod.stage in ("gone", "done") or (seen is not None and seen.ended)


    def pod_exec(self, pod: Obj, container: str, command: list[str], *,
                 tty: bool) -> subprocess.Popen[bytes]:
        """``podman exec -i`` of ``command`` in a running container (``ExecSource``).

        With ``tty`` the command gets a terminal too (``-t``, under a pseudo-terminal here).
        """
        with self._lock:
            known = self._pods.get(pod["metadata"]["uid"])
            seen = known.seen.get(container) if known else None
        if known is None or seen is None or seen.state != "running":
            raise ApiError(400, "BadRequest", f"container {container} is not running")
        return self.podman.exec(f"{known.podman}-{container}", command)

    def pod_connect(self, pod: Obj, port: int) -> socket.socket:
        """A TCP connection to ``port`` of ``pod`` (``ExecSource``): on this host's loopback,
        since every pod here runs on the host's network (its podIP is 127.0.0.1)."""
        conn = socket.create_connection(((pod.get("status") or {}).get("podIP") or
                                         "127.0.0.1", port), timeout=5)
        conn.settimeout(None)  # connected: the connection may idle as long as it likes
        return conn


class _ScriptView:
    """What a status script's steps may do to their pod (``scripts.ScriptPod``)."""

    def __init__(self, kubelet: Kubelet, pod: _Pod) -> None:
        self._kubelet, self._pod = kubelet, pod
        self.node = pod.node

    def change(self, change: Any) -> None:
        self._kubelet._update(self._pod, change)

    def remove(self) -> None:
        self._kubelet.store.remove(st.PODS, self._pod.namespace, self._pod.name)

    def stall_watches(self) -> None:
        self._kubelet.store.stall_watches()

    def wait(self, event: threading.Event) -> None:
        while not event.wait(0.1) and not self._kubelet._closed.is_set():
            pass

