"""Offline test images: root filesystems built from host binaries and ``podman import``-ed.

No registry is reachable from CI or these machines (``FACTS.md``), so the container tests
build the images OSMO's tutorials name, from what the host has:

- ``alpine:3.18`` — Debian's static busybox as ``/bin/busybox`` and a symlink per applet
  (``sh``, ``nc``, ``sleep``, ``wc``, ``hostname`` ...), like the real alpine;
- ``ubuntu:22.04``, ``ubuntu:24.04`` — the same plus the host's ``bash`` and the libraries it
  loads (the tutorials run ``bash -c`` with ``{1..10}``, which busybox ``sh`` leaves as is);
- ``python:X.Y-slim`` and ``localhost/osmo-test/python:X.Y``, only when asked for
  (``KINDS_PYTHON``) — this interpreter (``sys.base_prefix``, at the same absolute path, so
  it finds its standard library) with the standard library minus tests, caches, tkinter and
  site-packages, and the shared libraries its extension modules load: about 30 MB, a few
  seconds to build. Typed tasks inside containers will need it; the tutorials do not.
- ``localhost/osmo-test/osmo:<key>`` (tagged ``localhost/osmo:test``), only when asked for
  (``KINDS_OSMO``) — the python image plus this checkout's ``osmo`` package and its core
  dependencies as installed in this venv (the closure of ``pyproject.toml``'s requirements
  without extras, from their installed files), so pods of the Kubernetes stand-in run osmo's own
  init and collector containers (``osmo.runtime.kubernetes.podside``) as the chart's image
  would. ``/root`` is world-readable in it: the interpreter lives under pyenv's ``/root``
  here, and those containers run as the task's non-root uid.

Each image has the label ``osmo.test-image=<kind>`` and is built once per *recipe key* (the
sha256 of this recipe's version and its input files' paths, sizes and mtimes) under
``localhost/osmo-test/<kind>:<key>``; the tutorial names are tags of it. Calling
:func:`ensure_images` again costs one ``podman images`` listing. A tutorial name that
already names another image without that label (a real alpine pulled on a workstation) is
left alone: the tutorials run in the real image too. Builds are serialised across
processes with a lock file, since every test session shares podman's image store.

Podman needs two settings on these machines (no CAP_SYS_RESOURCE, hybrid cgroups):
:func:`write_containers_conf` writes them; tests hand the file over as ``CONTAINERS_CONF``.
It is a test fixture, never a product default.
"""

from __future__ import annotations

import fcntl
import hashlib
import io
import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tarfile
import tempfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

__all__ = ["CONTAINERS_CONF", "KINDS_OSMO", "KINDS_PYTHON", "KINDS_TUTORIALS", "OSMO_IMAGE", "TEST_IMAGE_LABEL",
           "ensure_images", "podman", "write_containers_conf"]

CONTAINERS_CONF = '[containers]\ndefault_ulimits = []\n\n[engine]\nruntime = "runc"\n'
TEST_IMAGE_LABEL = "osmo.test-image"
KINDS_TUTORIALS = ("busybox", "bash")
KINDS_PYTHON = ("python",)
KINDS_OSMO = ("osmo",)
OSMO_IMAGE = "localhost/osmo:test"
"""The tag of the osmo image (``KINDS_OSMO``)."""
_RECIPE = "1"  # bump when a builder changes what it puts in an image
_PY = f"{sys.version_info.major}.{sys.version_info.minor}"
NAMES = {
    "busybox": ("alpine:3.18",),
    "bash": ("ubuntu:22.04", "ubuntu:24.04"),
    "python": (f"python:{_PY}-slim",),
    "osmo": ("localhost/osmo:test",),
}
_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
_LOCK = Path(tempfile.gettempdir()) / "osmo-test-images.lock"
_PY_SKIP = {"test", "tests", "idlelib", "tkinter", "turtledemo", "ensurepip", "lib2to3",
            "site-packages", "dist-packages", "__pycache__"}


def write_containers_conf(folder: Path) -> Path:
    """Write the two podman settings these machines need; return the file's path."""
    path = folder / "containers.conf"
    path.write_text(CONTAINERS_CONF)
    return path


def podman(*args: str, env: Mapping[str, str], stdin: bytes | None = None) -> str:
    """Run ``podman ARGS`` and return its stdout; a failure raises with its stderr."""
    done = subprocess.run(["podman", *args], input=stdin, capture_output=True,
                          env=dict(env), timeout=600)
    if done.returncode != 0:
        raise RuntimeError(f"podman {' '.join(args)} failed ({done.returncode}): "
                           f"{done.stderr.decode(errors='replace').strip()}")
    return done.stdout.decode()


def ensure_images(env: Mapping[str, str], kinds: Iterable[str] = KINDS_TUTORIALS
                  ) -> dict[str, str]:
    """Make sure the images of ``kinds`` exist; map each image name to its id.

    Names are returned as written in the tutorials (``alpine:3.18``) and as
    ``localhost/osmo-test/<kind>:<key>``.
    """
    _LOCK.touch(exist_ok=True)
    with open(_LOCK) as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        present = _listing(env)
        out: dict[str, str] = {}
        for kind in kinds:
            recipe = _Recipe.of(kind)
            base = f"localhost/osmo-test/{kind}:{recipe.key[:16]}"
            if base not in present:
                _build(recipe, base, env)
                present = _listing(env)
            ident = present[base].id
            out[base] = ident
            for name in NAMES[kind]:
                full = _qualified(name)
                found = present.get(full)
                if found is None or (found.id != ident and TEST_IMAGE_LABEL in found.labels):
                    podman("tag", base, full, env=env)
                    found = _Image(ident, {TEST_IMAGE_LABEL: kind})
                out[name] = found.id
        return out


@dataclass(frozen=True)
class _Image:
    id: str
    labels: Mapping[str, str]


def _listing(env: Mapping[str, str]) -> dict[str, _Image]:
    images: dict[str, _Image] = {}
    for entry in json.loads(podman("images", "--format", "json", env=env) or "[]"):
        image = _Image("sha256:" + entry["Id"].removeprefix("sha256:"), entry.get("Labels") or {})
        for name in entry.get("Names") or []:
            images[name] = image
    return images


def _qualified(name: str) -> str:
    first, sep, _ = name.partition("/")
    if sep and ("." in first or ":" in first or first == "localhost"):
        return name
    return f"docker.io/{name}" if sep else f"docker.io/library/{name}"


# ---------------------------------------------------------------- recipes


@dataclass(frozen=True)
class _Recipe:
    """What goes into an image of one kind: host files (source → path in the image)."""

    kind: str
    files: tuple[tuple[Path, str], ...]
    links: tuple[tuple[str, str], ...]
    cmd: str

    @classmethod
    def of(cls, kind: str) -> _Recipe:
        busybox = _static_busybox()
        applets = subprocess.run([str(busybox), "--list"], capture_output=True, text=True,
                                 check=True).stdout.split()
        files = [(busybox, "/bin/busybox")]
        links = [(f"/bin/{a}", "busybox") for a in applets if a not in ("busybox", "bash")]
        cmd = "/bin/sh"
        if kind == "bash":
            bash = Path(shutil.which("bash") or "/bin/bash").resolve()
            files += [(bash, "/bin/bash"), *_libraries([bash])]
        elif kind in ("python", "osmo"):
            files += _python_files()
            if kind == "osmo":
                have = {target for _, target in files}
                files += [f for f in dict((t, (s, t)) for s, t in _osmo_files()).values()
                          if f[1] not in have]
            exe = _python_executable().as_posix()
            links += [(p, exe) for p in ("/usr/local/bin/python3", "/usr/local/bin/python",
                                         f"/usr/bin/python{_PY}", "/usr/bin/python3") if p != exe]
            cmd = "python3"
        elif kind != "busybox":
            raise ValueError(f"unknown test image kind {kind!r}")
        return cls(kind, tuple(files), tuple(links), cmd)

    @property
    def key(self) -> str:
        digest = hashlib.sha256(f"{_RECIPE}\0{self.kind}\0{self.cmd}".encode())
        for source, target in self.files:
            st = source.stat()
            digest.update(f"{source}\0{target}\0{st.st_size}\0{st.st_mtime_ns}\0".encode())
        for path, target in self.links:
            digest.update(f"{path}\0{target}\0".encode())
        return digest.hexdigest()


def _static_busybox() -> Path:
    found = shutil.which("busybox")
    if found is None or subprocess.run(["ldd", found], capture_output=True).returncode == 0:
        raise RuntimeError("the test images need a static busybox: apt-get install busybox-static")
    return Path(found).resolve()


def _libraries(binaries: Iterable[Path]) -> list[tuple[Path, str]]:
    """The shared libraries ``binaries`` load (``ldd``), at their absolute paths."""
    found: dict[str, Path] = {}
    for binary in binaries:
        out = subprocess.run(["ldd", str(binary)], capture_output=True, text=True).stdout
        for match in re.finditer(r"(?:=>\s*)?(/\S+)\s+\(0x", out):
            path = match.group(1)
            found.setdefault(path, Path(path).resolve())
    return [(source, path) for path, source in sorted(found.items())]


def _python_executable() -> Path:
    return Path(sys.base_prefix) / "bin" / f"python{_PY}"


def _python_files() -> list[tuple[Path, str]]:
    exe = _python_executable()
    stdlib = Path(sysconfig.get_paths(vars={"base": sys.base_prefix,
                                            "platbase": sys.base_prefix})["stdlib"])
    files = [(exe.resolve(), exe.as_posix())]
    for folder, dirs, names in os.walk(stdlib):
        dirs[:] = sorted(d for d in dirs if d not in _PY_SKIP and not d.startswith("config-"))
        files += [(Path(folder, n), str(Path(folder, n))) for n in sorted(names)
                  if not os.path.islink(Path(folder, n))]
    shared = [Path(s) for s, _ in files if s.suffix == ".so" or ".so." in s.name]
    return files + [f for f in _libraries([exe.resolve(), *shared]) if f[1] != exe.as_posix()]


def _osmo_files() -> list[tuple[Path, str]]:
    """This checkout's ``osmo`` and the installed files of its core dependencies, placed in
    the image's ``site-packages`` (the interpreter's own), with the libraries they load."""
    import importlib.metadata as metadata
    import tomllib

    from packaging.requirements import Requirement

    target = Path(sysconfig.get_paths(vars={"base": sys.base_prefix,
                                            "platbase": sys.base_prefix})["purelib"])
    package = Path(__file__).resolve().parents[2] / "osmo"
    files = [(Path(folder, n), str(target / Path(folder, n).relative_to(package.parent)))
             for folder, dirs, names in os.walk(package)
             for n in sorted(names) if n.endswith(".py") or n == "py.typed"
             if "__pycache__" not in folder]
    seen: set[str] = set()
    # the checkout's own requirements: the venv's record of them may be older
    project = tomllib.loads((package.parent / "pyproject.toml").read_text())["project"]
    todo = list(project["dependencies"])
    while todo:
        req = Requirement(todo.pop())
        name = req.name.lower().replace("_", "-")
        if name in seen or (req.marker is not None and not req.marker.evaluate({"extra": ""})):
            continue
        seen.add(name)
        dist = metadata.distribution(req.name)
        for entry in dist.files or []:
            if entry.parts[:1] == ("..",):
                continue  # a script outside site-packages: not needed
            source = Path(str(dist.locate_file(entry))).resolve()
            if source.is_file() and "__pycache__" not in entry.parts:
                files.append((source, str(target / entry)))
        todo += dist.requires or []
    shared = [s for s, _ in files if s.suffix == ".so" or ".so." in s.name]
    return files + _libraries(shared)


# ---------------------------------------------------------------- build


def _build(recipe: _Recipe, name: str, env: Mapping[str, str]) -> None:
    with tempfile.TemporaryDirectory(prefix="osmo-test-image-") as folder:
        tar_path = Path(folder) / "rootfs.tar"
        with tarfile.open(tar_path, "w") as tar:
            _rootfs(tar, recipe)
        cmd = json.dumps([recipe.cmd])
        podman("import", f"--change=LABEL={TEST_IMAGE_LABEL}={recipe.kind}",
               f"--change=ENV=PATH={_PATH}", f"--change=CMD={cmd}", str(tar_path), name,
               env=env)


def _rootfs(tar: tarfile.TarFile, recipe: _Recipe) -> None:
    made: set[str] = set()

    def folder(path: str, mode: int = 0o755) -> None:
        parts = path.strip("/").split("/")
        for i in range(1, len(parts) + 1):
            sub = "/".join(parts[:i])
            if sub not in made:
                made.add(sub)
                tar.addfile(_info(sub, tarfile.DIRTYPE, mode if i == len(parts) else 0o755))

    for path, mode in [("bin", 0o755), ("sbin", 0o755), ("usr/bin", 0o755),
                       ("usr/sbin", 0o755), ("usr/local/bin", 0o755), ("etc", 0o755),
                       ("root", 0o755 if recipe.kind == "osmo" else 0o700), ("home", 0o755), ("tmp", 0o1777), ("var/tmp", 0o1777),
                       ("proc", 0o555), ("sys", 0o555), ("dev", 0o755), ("run", 0o755)]:
        folder(path, mode)
    for name, text in [("etc/passwd", "root:x:0:0:root:/root:/bin/sh\n"
                                      "nobody:x:65534:65534:nobody:/:/bin/false\n"),
                       ("etc/group", "root:x:0:\nnogroup:x:65534:\n")]:
        data = text.encode()
        info = _info(name, tarfile.REGTYPE, 0o644)
        info.size = len(data)
        tar.addfile(info, fileobj=io.BytesIO(data))
    for source, target in recipe.files:
        folder(os.path.dirname(target.lstrip("/")))
        info = _info(target.lstrip("/"), tarfile.REGTYPE, source.stat().st_mode & 0o7777)
        info.size = source.stat().st_size
        with open(source, "rb") as f:
            tar.addfile(info, fileobj=f)
    for path, target in recipe.links:
        folder(os.path.dirname(path.lstrip("/")))
        info = _info(path.lstrip("/"), tarfile.SYMTYPE, 0o777)
        info.linkname = target
        tar.addfile(info)


def _info(name: str, kind: bytes, mode: int) -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.type, info.mode, info.uid, info.gid = kind, mode, 0, 0
    info.uname = info.gname = "root"
    return info
