"""The one module that runs a container engine's CLI (``podman``, else ``docker``).

What it owns:

- **engines** — :func:`detect_engine` finds ``podman`` (first) or ``docker`` (or the one
  named) and its version; none usable is :class:`EngineNotFound`, naming the package.
- **images, networks, clean-up** — :class:`ContainerEngine`: an image's id (pulling a missing
  image, progress lines to a callback as the engine prints them, registry credentials in a
  0600 auth file of a private folder that is deleted after the pull), group networks, and
  containers/networks found and removed by label (orphans after a ``kill -9``).

The runs themselves are described, and turned into argv, by ``osmo.runtime.container.run``
(pure); ``osmo.runtime.container.runs`` spawns them; ``osmo.runtime.container.pull`` runs
a pull.

Decisions, checked with podman 4.3 and the docker 28 CLI (``tests/containers``):

- An image is identified by its **id** (``{{.Id}}``, the digest of its config, which names
  every layer): every image has one in both engines, unlike ``.Digest``/``RepoDigests`` (a
  registry's manifest digest: none for a locally built image in docker, and it changes with
  compression). The repo digests are returned too, for lineage.
- Short names pull from Docker Hub (``pull_reference``), as docker and Kubernetes read them.

Secrets (variables, registry passwords) never appear in argv, a log or a message.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from osmo.runtime.container.pull import ImageError, pull_image
from osmo.runtime.container.run import ContainerError, EngineInfo, RegistryAuth

__all__ = ["ENGINES", "ContainerEngine", "EngineNotFound", "ImageInfo", "detect_engine"]

ENGINES = ("podman", "docker")
"""The engines, in the order ``detect_engine`` tries them."""
_INSTALL = ("install podman (Debian/Ubuntu: `apt-get install podman runc`) or docker, "
            "or run tasks as processes (--runtime process)")
_MISSING = ("image not known", "no such image", "no such object")
_NO_CONTAINER = ("no such container", "no container with")


class EngineNotFound(ContainerError):
    """No usable container engine on this machine (the message names what to install)."""


@dataclass(frozen=True)
class ImageInfo:
    """A local image: ``id`` (``sha256:<hex>``) and its registry digests (maybe none)."""

    id: str
    repo_digests: tuple[str, ...] = ()


def detect_engine(name: str | None = None, *, env: Mapping[str, str] | None = None) -> EngineInfo:
    """The first usable engine of ``podman``, ``docker`` (or only ``name``).

    Raises:
        EngineNotFound: none is installed and answering; the message says why for each.
    """
    if name is not None and name not in ENGINES:
        raise EngineNotFound(f"unknown container engine {name!r}: choose podman or docker")
    env = dict(os.environ if env is None else env)
    problems = []
    for candidate in [name] if name else ENGINES:
        path = shutil.which(candidate, path=env.get("PATH"))
        if path is None:
            problems.append(f"{candidate}: not installed")
            continue
        try:
            return _probe(candidate, path, env)
        except ContainerError as exc:
            problems.append(f"{candidate}: {exc}")
    raise EngineNotFound(f"no usable container engine ({'; '.join(problems)}); {_INSTALL}")


def _probe(name: str, path: str, env: Mapping[str, str]) -> EngineInfo:
    if name == "podman":  # podman run by a non-root user is rootless
        version = _call([path, "version", "--format", "{{.Client.Version}}"], env)
        return EngineInfo(name, path, version.strip(), rootless=os.geteuid() != 0)
    # `docker info` needs the daemon: the CLI alone cannot run anything
    out = _call([path, "info", "--format", "{{.ServerVersion}}|{{json .SecurityOptions}}"], env)
    version, _, security = out.strip().partition("|")
    return EngineInfo(name, path, version, rootless="rootless" in security)


def _call(argv: Sequence[str], env: Mapping[str, str], *, timeout: float = 60,
          stdin: bytes | None = None) -> str:
    """Run an engine command and return its stdout.

    Raises:
        ContainerError: it failed (its last stderr line) or did not finish in time.
    """
    try:
        done = subprocess.run(list(argv), input=stdin if stdin is not None else b"",
                              capture_output=True, env=dict(env), timeout=timeout)
    except subprocess.TimeoutExpired:
        raise ContainerError(f"`{Path(argv[0]).name} {argv[1]}` did not finish in "
                             f"{timeout:g} s") from None
    except OSError as exc:
        raise ContainerError(f"cannot run {argv[0]}: {exc.strerror or exc}") from exc
    if done.returncode != 0:
        raise ContainerError(_last_line(done.stderr) or f"exit code {done.returncode}")
    return done.stdout.decode(errors="replace")


def _last_line(data: bytes) -> str:
    lines = [ln.strip() for ln in data.decode(errors="replace").splitlines() if ln.strip()]
    return lines[-1].removeprefix("Error: ") if lines else ""


class ContainerEngine:
    """Engine commands other than ``run``: images, networks, and clean-up by label.

    Args:
        engine: the engine to drive (``detect_engine``).
        env: the CLI's environment (default: this process's, read at each call), e.g. with
            ``CONTAINERS_CONF``.
    """

    def __init__(self, engine: EngineInfo, *, env: Mapping[str, str] | None = None) -> None:
        self.engine = engine
        self._env = None if env is None else dict(env)
        self._store_file: Path | None | bool = False  # False: not looked for yet

    @property
    def env(self) -> dict[str, str]:
        """The environment engine commands run with."""
        return dict(os.environ) if self._env is None else dict(self._env)

    def call(self, *args: str, timeout: float = 60, stdin: bytes | None = None) -> str:
        """``<engine> ARGS...``'s stdout. Raises ContainerError."""
        return _call([self.engine.path, *args], self.env, timeout=timeout, stdin=stdin)

    # -------------------------------------------------------------- images

    def image(self, image: str) -> ImageInfo | None:
        """The local image ``image`` names (short names resolve as the engine does), or None.

        Raises:
            ContainerError: the engine failed for another reason.
        """
        try:
            out = self.call("image", "inspect", "--format",
                            "{{.Id}} {{range .RepoDigests}}{{.}} {{end}}", "--", image)
        except ContainerError as exc:
            if any(m in str(exc).lower() for m in _MISSING):
                return None
            raise
        ident, *digests = out.split()
        return ImageInfo(ident if ident.startswith("sha256:") else f"sha256:{ident}",
                         tuple(digests))

    def image_environment(self, image: str) -> dict[str, str]:
        """The variables image ``image`` sets (its ``ENV``).

        Raises:
            ContainerError: the engine cannot inspect it.
        """
        out = self.call("image", "inspect", "--format",
                        "{{range .Config.Env}}{{println .}}{{end}}", "--", image)
        return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)

    def store_stamp(self) -> tuple[int, int, int] | None:
        """A fingerprint of the local image store that changes with every image change.

        podman replaces its store's ``images.json`` (a new inode) on each pull, tag,
        untag and removal, and leaves it alone when containers run: its inode, mtime and
        size are the stamp, read with one ``stat``. None when there is none to read
        (docker's daemon owns its store; an engine that cannot say where its store is).
        """
        if self._store_file is False:
            self._store_file = self._find_store_file()
        if not isinstance(self._store_file, Path):
            return None
        try:
            found = os.stat(self._store_file)
        except OSError:
            return None
        return found.st_ino, found.st_mtime_ns, found.st_size

    def _find_store_file(self) -> Path | None:
        if self.engine.name != "podman":
            return None
        try:
            root, _, driver = self.call("info", "--format",
                                        "{{.Store.GraphRoot}}\t{{.Store.GraphDriverName}}"
                                        ).strip().partition("\t")
        except ContainerError:
            return None
        path = Path(root) / f"{driver}-images" / "images.json"
        return path if root and driver and path.is_file() else None

    def resolve(self, image: str, *, pull: bool = True,
                progress: Callable[[str], None] | None = None,
                auth: RegistryAuth | None = None) -> ImageInfo:
        """``image``'s local id, pulling it first if it is missing and ``pull`` allows.

        Raises:
            ImageError: ``image 'x' not found: <why>`` (not present, pull failed).
        """
        try:
            found = self.image(image)
            if found is None and pull:
                self.pull(image, progress=progress, auth=auth)
                found = self.image(image)
        except ImageError:
            raise
        except ContainerError as exc:
            raise ImageError(f"image '{image}' not found: {exc}") from exc
        if found is None:
            why = "pulled, yet not found" if pull else "not on this node (pulling is off)"
            raise ImageError(f"image '{image}' not found: {why}")
        return found

    def pull(self, image: str, *, progress: Callable[[str], None] | None = None,
             auth: RegistryAuth | None = None) -> None:
        """Pull ``image``; each progress line goes to ``progress`` as it comes.

        With ``auth``, the pull reads it from an auth file (0600) in a private folder that
        is deleted when the pull ends.

        Raises:
            ImageError: the pull failed (the engine's reason; never a password).
        """
        pull_image(self.engine, self.env, image, progress=progress, auth=auth)

    # -------------------------------------------------------------- networks

    def create_network(self, name: str, labels: Mapping[str, str]) -> None:
        """Create network ``name`` (containers on it find each other by name and alias)."""
        try:
            self.call("network", "create", *_label_args(labels), "--", name)
        except ContainerError as exc:
            if "already" not in str(exc).lower():  # a retry of the same group reuses it
                raise

    def remove_network(self, name: str) -> None:
        """Remove network ``name`` (gone already is fine)."""
        try:
            self.call("network", "rm", "--", name)
        except ContainerError as exc:
            if not any(m in str(exc).lower() for m in ("not found", "no such network")):
                raise

    def networks(self, labels: Mapping[str, str]) -> list[str]:
        """Names of the networks that carry every one of ``labels``."""
        out = self.call("network", "ls", *_filters(labels), "--format", "{{.Name}}")
        return out.split()

    # -------------------------------------------------------------- containers

    def containers(self, labels: Mapping[str, str]) -> list[str]:
        """Ids of the containers (any state) that carry every one of ``labels``."""
        return self.call("ps", "-a", "--no-trunc", *_filters(labels),
                         "--format", "{{.ID}}").split()

    def running(self, labels: Mapping[str, str]) -> list[str]:
        """Ids of the running containers that carry every one of ``labels``."""
        return self.call("ps", "--no-trunc", *_filters(labels), "--filter=status=running",
                         "--format", "{{.ID}}").split()

    def wait_started(self, label: tuple[str, str], where: tuple[str, str], *, since: float,
                     timeout: float) -> bool:
        """Wait for a container labelled ``label`` whose label ``where`` holds to start.

        A start at or after ``since`` (epoch seconds) counts, also one before this call:
        the engine's event stream (``events --since``) is read, nothing is polled.

        Returns:
            True once one started; False when ``timeout`` seconds passed first.

        Raises:
            ContainerError: the engine has no event stream here (it ended by itself, e.g.
                a journald event log this user cannot read).
        """
        key, want = where
        attributes = ".Attributes" if self.engine.name == "podman" else ".Actor.Attributes"
        # the engines OR label filters: filter by one, read the other from each event
        argv = [self.engine.path, "events", f"--since={since:.3f}", *_filters(dict([label])),
                "--filter=event=start", "--format", f'{{{{index {attributes} "{key}"}}}}']
        try:
            proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                    stderr=subprocess.DEVNULL, env=self.env)
        except OSError as exc:
            raise ContainerError(f"cannot run {argv[0]}: {exc.strerror or exc}") from exc
        timer = threading.Timer(timeout, proc.kill)  # ends the stream: readline sees EOF
        timer.start()
        assert proc.stdout is not None
        try:
            if any(line.decode(errors="replace").strip() == want for line in proc.stdout):
                return True
        finally:
            timer.cancel()
            proc.kill()
            code = proc.wait()
            proc.stdout.close()
        if code >= 0:  # it ended by itself, not by the timer's kill
            raise ContainerError(f"`{self.engine.name} events` ended with exit code {code}")
        return False

    def kill(self, container: str, signal: str = "TERM") -> bool:
        """Send ``signal`` to a running container; False when it is not running (yet)."""
        try:
            self.call("kill", f"--signal={signal}", "--", container)
        except ContainerError:
            return False
        return True

    def stop(self, container: str, grace: float) -> None:
        """SIGTERM, then SIGKILL after ``grace`` seconds (the engine waits)."""
        self.call("stop", f"--time={max(0, round(grace))}", "--", container,
                  timeout=grace + 60)

    def remove(self, *containers: str) -> bool:
        """Kill (SIGKILL) and remove ``containers``; False if none of them existed."""
        if not containers:
            return False
        force = ["-f", "--time=0"] if self.engine.name == "podman" else ["-f"]
        try:  # both print what they removed; podman is silent about a missing one
            return bool(self.call("rm", *force, "--", *containers).strip())
        except ContainerError as exc:
            if not any(m in str(exc).lower() for m in _NO_CONTAINER):
                raise
            return False

    def address(self, container: str) -> str | None:
        """The container's IP address on its network (``inspect``); None if it has none.

        Raises:
            ContainerError: the engine cannot inspect it.
        """
        out = self.call("inspect", "--format",
                        "{{range .NetworkSettings.Networks}}{{.IPAddress}} {{end}}"
                        "{{.NetworkSettings.IPAddress}}", container, timeout=15)
        found = [word for word in out.split() if word]
        return found[0] if found else None

    def remove_labelled(self, labels: Mapping[str, str]) -> tuple[list[str], list[str]]:
        """Remove every container, then every network, carrying ``labels`` (orphan clean-up).

        Returns:
            ``(container ids, network names)`` removed.
        """
        ids = self.containers(labels)
        for ident in ids:
            self.remove(ident)
        names = self.networks(labels)
        for name in names:
            self.remove_network(name)
        return ids, names


def _label_args(labels: Mapping[str, str]) -> list[str]:
    return [f"--label={key}={value}" for key, value in sorted(labels.items())]


def _filters(labels: Mapping[str, str]) -> list[str]:
    if not labels:  # no filter would match every container on the machine
        raise ContainerError("refusing to list containers without a label filter")
    return [f"--filter=label={key}={value}" for key, value in sorted(labels.items())]
