"""The node's hands: Pod manifests run under ``podman kube play``, watched, logged, removed.

The only module of the stand-in that runs podman. What podman 4.3 needs, found by trying:

- **Names.** Every stand-in's pods get a prefix of their own (``podman_name``): podman's pod
  and container names are global on the machine and other test sessions share them.
  Containers are ``<podman pod>-<container>``; the pod's hostname stays its Kubernetes name.
  A label (``LABEL=<prefix>``) on every pod and container lets :meth:`PodmanPods.leftovers`
  find what is left.
- **The host's network** (``kube play --network host``): every pod shares it, as a pod with
  ``hostNetwork: true`` does, so its podIP is the host's (127.0.0.1) and it reaches services
  on the host's loopback. A network namespace per pod is what podman 4.3 handles badly here:
  with several pods starting and stopping at once it unmounts namespaces it still uses
  (after which ``podman ps`` fails for every user of the machine until the pod is removed)
  and leaves their files in ``/run/netns``. Ports are therefore shared between pods, and no
  cluster DNS resolves Service or pod names.
- **Init containers** run inside ``kube play`` (it returns after they finished, or fails with
  ``init container ... exited with code N``). The annotation
  ``io.podman.annotations.init.container.type: always`` keeps them, so their exit codes can
  be read.
  **Native sidecars** (an init container with ``restartPolicy: Always``) would block ``kube
  play`` for ever: they become ordinary containers, and the kubelet stops them when the
  regular containers have exited.
- **Secrets.** podman reads ``secretKeyRef`` env from a podman secret holding a JSON map of
  base64 values, but a Secret *volume* gets the base64 text undecoded and ``items`` ignored.
  So :func:`translate` resolves both itself: env becomes literal values, a Secret volume a
  read-only ``hostPath`` folder of decoded files (0700, under the node's private folder).
  ``fieldRef`` env for the pod's name, namespace, uid, node and host IP is resolved too.
- **subPath** is ignored by podman 4.3 for an ``emptyDir`` (the whole volume is mounted), and
  a ``hostPath`` must exist when the manifest is read. So an ``emptyDir`` that some
  container mounts with a ``subPath`` becomes a ``hostPath`` folder (0777, as the kubelet
  makes it) under the node's private folder, and each ``subPath`` mount a ``hostPath`` of
  its own folder in it, made when missing just before the regular containers are played,
  as the kubelet makes a missing subPath. A
  ``subPath`` naming a *file* that an init container writes cannot be had this way (podman
  reads the manifest before init containers run). So a pod with such volumes has its init
  containers run first, one by one, as plain ``podman run`` containers named as podman
  names a pod's (``<pod>-<container>``, with the same mounts, environment and user), and
  only its regular containers are played once they all succeeded (``PodmanPods.run_inits``).
- **Fields podman ignores or cannot honour** are removed (``nodeName``, ``nodeSelector``,
  ``tolerations``, ``affinity``, ``schedulerName``, ``priorityClassName``,
  ``imagePullSecrets``, service account fields); ``resources`` stay (memory and cpu limits are
  enforced). An ``emptyDir`` with ``medium: Memory`` is a plain folder (no size limit).
- **Exits.** ``podman inspect`` by name gives states, exit codes and ``OOMKilled``,
  which podman does not set on hybrid cgroups (these machines), so an exit of
  137 of a container with a memory limit that the node did not stop counts as OOMKilled.
  When to look is told by one ``podman events`` stream filtered by the node's label
  (:meth:`PodmanPods.events`): a container's start, death or OOM, as the kubelet's evented
  PLEG learns them from the runtime, rather than a ``podman inspect`` every round.
- **Logs.** podman's ``k8s-file`` log driver (the default here) writes the CRI log format a
  kubelet reads (``TIME STREAM P|F TEXT`` lines, in the file ``HostConfig.LogConfig.Path``
  names): :func:`read_log` serves them from that file as the kubelet does, with no process
  per read; ``podman logs`` only for another driver.
- **Removal** of many pods is one ``podman pod rm`` (:meth:`PodmanPods.remove_many`).
"""

from __future__ import annotations

import copy
import json
import os
import shutil
import subprocess
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["LABEL", "ContainerState", "MissingSecret", "PodmanPods", "read_log", "translate"]

LABEL = "osmo.k8s-standin"
INIT_TYPE = "io.podman.annotations.init.container.type"
DROPPED_SPEC = ("nodeName", "nodeSelector", "tolerations", "affinity", "schedulerName",
                "priorityClassName", "priority", "preemptionPolicy", "imagePullSecrets",
                "serviceAccountName", "serviceAccount", "automountServiceAccountToken",
                "topologySpreadConstraints", "schedulingGates", "enableServiceLinks",
                "runtimeClassName", "overhead", "readinessGates")
EVENTS = frozenset({"start", "died", "oom"})  # container events that change what a pod shows
LOG_WAIT = 0.1  # seconds between two reads of a followed log that had nothing new
PULL_FAILURES = ("Trying to pull", "initializing source", "pinging container registry",
                 "manifest unknown", "unable to pull", "image not known", "name unknown",
                 "requested access to the resource is denied")

Obj = dict[str, Any]
SecretLookup = Callable[[str], "Mapping[str, bytes] | None"]


@dataclass(frozen=True)
class ContainerState:
    """One container as ``podman inspect`` last showed it."""

    name: str  # the Kubernetes container name
    state: str  # podman's: created, running, exited, stopped, ...
    exit_code: int
    started: str  # RFC 3339, seconds ("" : never)
    finished: str
    oom_killed: bool
    container_id: str
    image_id: str
    log_path: str = ""  # its CRI-format log file (podman's k8s-file driver), if it has one

    @property
    def ended(self) -> bool:
        """Whether it ran and stopped."""
        return self.state in ("exited", "stopped") and bool(self.started)


class MissingSecret(Exception):
    """A Secret the pod needs does not exist (yet)."""

    def __init__(self, name: str, key: str | None, for_env: bool) -> None:
        where = f'key "{key}" in ' if key else ""
        super().__init__(f'{where}secret "{name}" not found')
        self.name, self.for_env = name, for_env


def translate(pod: Obj, podman_name: str, prefix: str, folder: Path, secrets: SecretLookup,
              node_name: str) -> tuple[Obj, list[str]]:
    """The manifest podman plays for ``pod``, and the names of its native sidecars.

    Secret volumes are written under ``folder``; a Secret that is missing raises
    :class:`MissingSecret` before anything is written.
    """
    meta, spec = pod["metadata"], copy.deepcopy(pod["spec"])
    for key in DROPPED_SPEC:
        spec.pop(key, None)
    spec.setdefault("hostname", meta["name"][:63].rstrip("-."))
    sidecars = [c for c in spec.get("initContainers") or [] if c.get("restartPolicy") == "Always"]
    spec["initContainers"] = [c for c in spec.get("initContainers") or [] if c not in sidecars]
    spec["containers"] = list(spec["containers"]) + sidecars
    if not spec["initContainers"]:
        del spec["initContainers"]
    fields = {"metadata.name": meta["name"], "metadata.namespace": meta.get("namespace", ""),
              "metadata.uid": meta.get("uid", ""), "spec.nodeName": node_name,
              "status.hostIP": "127.0.0.1", "status.podIP": "127.0.0.1",
              "spec.serviceAccountName":
              pod["spec"].get("serviceAccountName", "default")}
    for container in spec["containers"] + spec.get("initContainers", []):
        container.pop("restartPolicy", None)
        container["env"] = _env(container, secrets, fields, meta)
        container.pop("envFrom", None)
    volumes = []
    for volume in spec.get("volumes") or []:
        if "secret" in volume:
            path = _secret_volume(volume, folder / volume["name"], secrets)
            if path is None:
                continue  # optional and missing: the mount is dropped with it
            volume = {"name": volume["name"], "hostPath": {"path": str(path),
                                                           "type": "Directory"}}
            _read_only(spec, volume["name"])
        volumes.append(volume)
    spec["volumes"] = volumes + _sub_paths(spec, volumes, folder)
    names = {v["name"] for v in spec["volumes"]}
    for container in spec["containers"] + spec.get("initContainers", []):
        container["volumeMounts"] = [m for m in container.get("volumeMounts") or []
                                     if m.get("name") in names]
    if any("-sub" in v["name"] for v in spec["volumes"]) and spec.get("initContainers"):
        spec["osmo-standin-inits"] = spec.pop("initContainers")  # run_inits runs them first
    annotations = {k: str(v) for k, v in (meta.get("annotations") or {}).items()}
    annotations[INIT_TYPE] = "always"
    manifest = {"apiVersion": "v1", "kind": "Pod", "spec": spec,
                "metadata": {"name": podman_name, "annotations": annotations,
                             "labels": {**(meta.get("labels") or {}), LABEL: prefix}}}
    return manifest, [c["name"] for c in sidecars]


def _env(container: Obj, secrets: SecretLookup, fields: Mapping[str, str],
         meta: Obj) -> list[Obj]:
    out: list[Obj] = []
    for source in container.get("envFrom") or []:
        ref = source.get("secretRef")
        if ref is None:
            continue  # configMapRef: not served by the stand-in
        data = secrets(ref["name"])
        if data is None:
            if ref.get("optional"):
                continue
            raise MissingSecret(ref["name"], None, for_env=True)
        out += [{"name": source.get("prefix", "") + k, "value": v.decode(errors="replace")}
                for k, v in data.items()]
    for var in container.get("env") or []:
        found = var.get("valueFrom") or {}
        if "secretKeyRef" in found:
            ref = found["secretKeyRef"]
            data = secrets(ref["name"])
            if data is None or ref["key"] not in data:
                if ref.get("optional"):
                    continue
                raise MissingSecret(ref["name"], ref["key"] if data else None, for_env=True)
            var = {"name": var["name"], "value": data[ref["key"]].decode(errors="replace")}
        elif "fieldRef" in found:
            path = found["fieldRef"].get("fieldPath", "")
            value = fields.get(path)
            if path.startswith(("metadata.labels['", "metadata.annotations['")):
                group, key = path.split("['", 1)
                value = (meta.get(group.split(".")[1]) or {}).get(key.rstrip("']"), "")
            if value is not None:
                var = {"name": var["name"], "value": value}
        out.append(var)
    return out


def _secret_volume(volume: Obj, folder: Path, secrets: SecretLookup) -> Path | None:
    source = volume["secret"]
    data = secrets(source.get("secretName", ""))
    if data is None:
        if source.get("optional"):
            return None
        raise MissingSecret(source.get("secretName", ""), None, for_env=False)
    items = source.get("items") or [{"key": k, "path": k} for k in data]
    mode = int(source.get("defaultMode", 0o644))
    folder.mkdir(parents=True, exist_ok=True)
    folder.chmod(0o755)  # the pod's user may be anyone; the node's folder above is private
    for item in items:
        if item["key"] not in data:
            if source.get("optional"):
                continue
            raise MissingSecret(source.get("secretName", ""), item["key"], for_env=False)
        target = (folder / item["path"]).resolve()
        if not target.is_relative_to(folder.resolve()):
            continue  # the API refuses such paths; never write outside the folder
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data[item["key"]])
        target.chmod(int(item.get("mode", mode)))
    return folder


def _sub_paths(spec: Obj, volumes: list[Obj], folder: Path) -> list[Obj]:
    """Turn ``emptyDir`` volumes mounted with a ``subPath`` into host folders (module doc);
    return the volumes their subPath mounts now name."""
    containers = spec["containers"] + spec.get("initContainers", [])
    wanted = {m["name"] for c in containers for m in c.get("volumeMounts") or []
              if m.get("subPath")}
    roots: dict[str, Path] = {}
    for index, volume in enumerate(volumes):
        if "emptyDir" in volume and volume["name"] in wanted:
            root = folder / "emptydir" / volume["name"]
            root.mkdir(parents=True, exist_ok=True)
            root.chmod(0o777)
            roots[volume["name"]] = root
            volumes[index] = {"name": volume["name"],
                              "hostPath": {"path": str(root), "type": "Directory"}}
    added: list[Obj] = []
    for container in containers:
        for mount in container.get("volumeMounts") or []:
            root = roots.get(mount.get("name", ""))
            if root is None or not mount.get("subPath"):
                continue
            sub = mount.pop("subPath")
            path = (root / sub).resolve()
            if not path.is_relative_to(root.resolve()):
                raise ValueError(f"subPath {sub!r} leaves its volume")
            spec.setdefault("osmo-standin-subpaths", []).append([str(root), str(path)])
            mount["name"] = f"{mount['name']}-sub{len(added)}"
            added.append({"name": mount["name"], "hostPath": {"path": str(path),
                                                             "type": "Directory"}})
    return added


def _read_only(spec: Obj, volume: str) -> None:
    for container in spec["containers"] + spec.get("initContainers", []):
        for mount in container.get("volumeMounts") or []:
            if mount.get("name") == volume:
                mount["readOnly"] = True


class PodmanPods:
    """podman for one stand-in node: its network, its pods, their containers and logs.

    Args:
        env: the environment podman runs with (``CONTAINERS_CONF`` on these machines).
        prefix: what every podman pod name of this node starts with (unique per node).
        folder: a private folder for manifests and Secret files.
    """

    def __init__(self, env: Mapping[str, str], prefix: str, folder: Path) -> None:
        self.env = dict(env)
        self.prefix = prefix
        self.folder = folder
        self.played: dict[str, list[str]] = {}  # podman pod → its containers, ever played
        self.run_alone: set[str] = set()  # podman pods whose init containers run_inits runs

    def podman_name(self, namespace: str, name: str) -> str:
        """The podman pod name for a Kubernetes pod."""
        return f"{self.prefix}-{namespace}-{name}"

    def run(self, *args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
        """``podman ARGS`` (output captured; the caller reads the return code)."""
        return subprocess.run(["podman", *args], capture_output=True, text=True,
                              env=self.env, timeout=timeout)

    def write(self, podman_name: str, manifest: Obj) -> Path:
        """Write a manifest (JSON is YAML) into the node's folder; return its path."""
        path = self.folder / f"{podman_name}.json"
        spec = manifest["spec"]
        self.played[podman_name] = [c["name"] for c in spec.get("initContainers", [])
                                    + spec.get("osmo-standin-inits", []) + spec["containers"]]
        if spec.get("osmo-standin-inits"):
            self.run_alone.add(podman_name)
        played = {**manifest, "spec": {k: v for k, v in spec.items()
                                       if not k.startswith("osmo-standin-")}}
        path.write_text(json.dumps(played))
        return path

    def play(self, manifest: Path) -> subprocess.Popen[str]:
        """Start ``podman kube play`` of ``manifest`` (it returns once init containers ran).

        In the node's folder: conmon, which podman starts there, writes a file ``oom`` into
        its working folder when a container of it is killed for memory.
        """
        return subprocess.Popen(["podman", "kube", "play", "--network", "host", str(manifest)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env=self.env, cwd=self.folder)

    def states(self, pods: Mapping[str, Sequence[str]]) -> dict[str, dict[str, ContainerState]]:
        """The containers of ``pods`` ({podman pod: container names}) that exist now.

        One ``podman inspect`` by name: unlike ``podman ps``, it never looks at other users'
        containers (one of them in a bad state makes ``podman ps`` fail for everyone).
        """
        names = {f"{pod}-{name}": (pod, name) for pod, names in pods.items() for name in names}
        if not names:
            return {}
        done = self.run("inspect", "--type", "container", "--format", "json", *names)
        try:
            found = json.loads(done.stdout or "[]") or []
        except ValueError:
            found = []  # podman printed nothing usable: nothing is known this time
        out: dict[str, dict[str, ContainerState]] = {}
        for entry in found:
            if entry.get("Name") not in names:
                continue
            pod, name = names[entry["Name"]]
            state = entry.get("State") or {}
            out.setdefault(pod, {})[name] = ContainerState(
                name, state.get("Status", ""), int(state.get("ExitCode") or 0),
                _seconds(state.get("StartedAt")), _seconds(state.get("FinishedAt")),
                bool(state.get("OOMKilled")), entry.get("Id", ""), entry.get("Image", ""),
                _log_file(entry))
        return out

    def events(self, seen: Callable[[str], None]) -> subprocess.Popen[str]:
        """Start ``podman events`` for this node's containers; a thread calls ``seen`` with
        the container's name for each start, death or OOM. The caller ends it
        (``terminate`` and ``wait`` on what this returns)."""
        proc = subprocess.Popen(["podman", "events", "--format", "json", "--filter",
                                 f"label={LABEL}={self.prefix}"], stdout=subprocess.PIPE,
                                stderr=subprocess.DEVNULL, text=True, env=self.env)

        def read() -> None:
            assert proc.stdout is not None
            for line in proc.stdout:
                try:
                    event = json.loads(line)
                except ValueError:
                    continue
                if event.get("Type") == "container" and event.get("Status") in EVENTS:
                    seen(str(event.get("Name", "")))
            proc.stdout.close()
        threading.Thread(target=read, name="k8s-podman-events", daemon=True).start()
        return proc

    @staticmethod
    def make_sub_paths(manifest: Obj) -> None:
        """Make the subPath folders that do not exist (as the kubelet does), just before the
        regular containers are played."""
        for root, sub in manifest["spec"].get("osmo-standin-subpaths", []):
            path = Path(sub)
            if path.exists():
                continue
            path.mkdir(parents=True, exist_ok=True)
            for made in [path, *path.parents]:
                if made == Path(root):
                    break
                made.chmod(0o777)

    def run_inits(self, podman_name: str, manifest: Obj) -> str:
        """Run the init containers ``translate`` set apart, in order; "" or podman's error.

        Each is ``podman run`` with the pod's host paths, environment, user and working
        folder, named ``<pod>-<container>`` (so :meth:`states` reads it) and labelled as the
        node's; it stays (stopped) until :meth:`remove`.
        """
        spec = manifest["spec"]
        paths = {v["name"]: v["hostPath"]["path"] for v in spec["volumes"] if "hostPath" in v}
        for container in spec.pop("osmo-standin-inits", []):
            args = ["run", "--name", f"{podman_name}-{container['name']}", "--network", "host",
                    "--pull=never", "--label", f"{LABEL}={self.prefix}"]
            for mount in container.get("volumeMounts") or []:
                ro = ":ro" if mount.get("readOnly") else ""
                args += ["-v", f"{paths[mount['name']]}:{mount['mountPath']}{ro}"]
            for var in container.get("env") or []:
                args += ["--env", f"{var['name']}={var.get('value', '')}"]
            security = container.get("securityContext") or {}
            if "runAsUser" in security:
                args += ["--user", f"{security['runAsUser']}:{security.get('runAsGroup', 0)}"]
            if container.get("workingDir"):
                args += ["--workdir", container["workingDir"]]
            command = [*container.get("command", []), *container.get("args", [])]
            if command:
                args += ["--entrypoint", json.dumps(command[:1])]
            args += [container["image"], *command[1:]]
            done = self.run(*args, timeout=600)
            if done.returncode != 0:
                return f"init container {container['name']} exited with code {done.returncode}"
        return ""

    def stop(self, podman_name: str, grace: int) -> None:
        """Stop a pod: SIGTERM, and SIGKILL after ``grace`` seconds."""
        self.run("pod", "stop", "-t", str(max(grace, 0)), podman_name, timeout=grace + 60)

    def stop_containers(self, names: Sequence[str], grace: int) -> None:
        """Stop some containers of a pod (its sidecars)."""
        if names:
            self.run("stop", "-t", str(max(grace, 0)), *names, timeout=grace + 60)

    def remove(self, podman_name: str) -> None:
        """Remove a pod and its containers (stopping them at once), and its files."""
        for _ in range(5):  # under load podman now and then refuses; a pod must not stay
            done = self.run("pod", "rm", "-f", "-t", "0", podman_name)
            if done.returncode == 0 or self.run("pod", "exists", podman_name).returncode:
                break
            print(f"k8s stand-in: podman pod rm {podman_name}: {done.stderr.strip()}")
            time.sleep(0.5)
        self.run("rm", "-f", "--ignore", *[f"{podman_name}-{c}" for c in
                                           self.played.get(podman_name, [])])
        shutil.rmtree(self.folder / podman_name, ignore_errors=True)
        (self.folder / f"{podman_name}.json").unlink(missing_ok=True)

    def remove_many(self, podman_names: Sequence[str]) -> None:
        """Remove several pods at once (one ``podman pod rm``), each alone if that fails."""
        if not podman_names:
            return
        done = self.run("pod", "rm", "-f", "--ignore", "-t", "0", *podman_names)
        if done.returncode != 0:
            for name in podman_names:
                self.remove(name)
            return
        standalone = [f"{pod}-{c}" for pod in podman_names for c in self.played.get(pod, [])
                      if pod in self.run_alone]
        if standalone:  # run_inits' containers are not the pod's: they go on their own
            self.run("rm", "-f", "--ignore", *standalone)
        for name in podman_names:
            shutil.rmtree(self.folder / name, ignore_errors=True)
            (self.folder / f"{name}.json").unlink(missing_ok=True)

    def logs(self, container: str, *, follow: bool, tail: int | None,
             timestamps: bool) -> Iterator[bytes]:
        """The output of a container (stdout and stderr together) by ``podman logs``, for a
        log driver whose file :func:`read_log` cannot read."""
        args = ["podman", "logs"]
        if follow:
            args.append("--follow")
        if tail is not None:
            args += ["--tail", str(tail)]
        if timestamps:
            args.append("--timestamps")
        proc = subprocess.Popen([*args, container], stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, env=self.env)
        assert proc.stdout is not None
        try:
            while chunk := os.read(proc.stdout.fileno(), 65536):
                yield chunk
        finally:
            if proc.poll() is None:
                proc.kill()
            proc.wait()
            proc.stdout.close()

    def exec(self, container: str, command: Sequence[str]) -> subprocess.Popen[bytes]:
        """``podman exec -i CONTAINER COMMAND`` with its three streams piped."""
        return subprocess.Popen(["podman", "exec", "-i", container, *command],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, env=self.env)

    def leftovers(self) -> tuple[list[str], list[str]]:
        """(pods, containers) this node played that still exist, and any other pod carrying
        its label."""
        found = self.run("pod", "ps", "--filter", f"label={LABEL}={self.prefix}",
                         "--format", "{{.Name}}").stdout.split()
        left = self.run("pod", "inspect", "--format", "{{.Name}}", *self.played).stdout.split() \
            if self.played else []
        states = self.states(self.played)
        containers = [f"{pod}-{name}" for pod, names in states.items() for name in names]
        return sorted(set(found) | set(left)), sorted(containers)


def read_log(path: str, *, follow: bool, tail: int | None, timestamps: bool,
             ended: Callable[[], bool]) -> Iterator[bytes]:
    """A container's output from its CRI-format log file, as the kubelet serves it.

    Each ``TIME STREAM TAG TEXT`` line gives its text, with a newline unless its tag is
    ``P`` (a partial line), prefixed with its time when ``timestamps``. ``tail``: only the
    last lines. ``follow``: more as it comes, until ``ended()`` and the file has no more.
    """
    try:
        handle = open(path, "rb")  # noqa: SIM115 - held across the generator's yields
    except FileNotFoundError:
        return
    with handle:
        pending = b""
        lines = handle.read().splitlines(keepends=True)
        if lines and not lines[-1].endswith(b"\n"):
            pending = lines.pop()
        if tail is not None:
            lines = lines[-tail:] if tail > 0 else []
        out = b"".join(_cri_text(line, timestamps) for line in lines)
        if out:
            yield out
        while follow:
            over = ended()  # asked before the read: what was written before its end is read
            more = handle.read()
            if more:
                lines = (pending + more).splitlines(keepends=True)
                pending = lines.pop() if not lines[-1].endswith(b"\n") else b""
                out = b"".join(_cri_text(line, timestamps) for line in lines)
                if out:
                    yield out
            elif over:
                return
            else:
                time.sleep(LOG_WAIT)


def _cri_text(line: bytes, timestamps: bool) -> bytes:
    """The text of one CRI log line (``TIME STREAM TAG TEXT``)."""
    parts = line.rstrip(b"\n").split(b" ", 3)
    if len(parts) < 3:
        return b""
    text = parts[3] if len(parts) == 4 else b""
    if parts[2] != b"P":
        text += b"\n"
    if timestamps:
        stamp = parts[0].replace(b"+00:00", b"Z")
        text = stamp + b" " + text
    return text


def _log_file(entry: Mapping[str, Any]) -> str:
    """The k8s-file log path ``podman inspect`` gave, "" for another log driver."""
    config = (entry.get("HostConfig") or {}).get("LogConfig") or {}
    return str(config.get("Path") or "") if config.get("Type") == "k8s-file" else ""


def _seconds(stamp: str | None) -> str:
    """podman's RFC 3339 time with nanoseconds as the API writes it ("" for never)."""
    if not stamp or stamp.startswith("0001-"):
        return ""
    return stamp[:19] + "Z"
