"""A local stand-in for ``python:3.12-slim``, so the chart's Dockerfile can be built here.

No image registry is reachable from these machines or CI (``FACTS.md``), but Debian's mirror
is. The stand-in is made as the official image is: a Debian bookworm root filesystem
(``mmdebstrap --variant=minbase``, with the slim images' dpkg excludes of docs, man pages and
locales), ``ca-certificates``, ``netbase``, ``tzdata`` and the shared libraries CPython's
extension modules load (the official image keeps the same ones), plus CPython 3.12 under
``/usr/local`` with ``pip`` and ``venv``. The interpreter is this machine's own 3.12 (the
tests' ``sys.base_prefix``), copied without its test suite, tkinter, caches or other
site-packages; ``ldconfig`` then finds ``libpython3.12.so`` in ``/usr/local/lib`` as in the
official image. Everything is built in a folder the caller owns; only podman's image store
keeps the result (:func:`build` returns its id, the caller removes it).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path

PY = f"{sys.version_info.major}.{sys.version_info.minor}"
MIRROR = "http://deb.debian.org/debian"
# Debian's runtime libraries for CPython's extension modules, as the official image keeps them
# (_ssl, _hashlib, _ctypes, _sqlite3, _curses, readline, _uuid, nis, _bz2, _lzma, zlib), and
# the three packages the official image installs first.
PACKAGES = ("ca-certificates", "netbase", "tzdata", "libffi8", "libncursesw6", "libnsl2",
            "libsqlite3-0", "libssl3", "libuuid1", "libreadline8", "libbz2-1.0", "liblzma5",
            "zlib1g")
# debian:bookworm-slim's dpkg excludes (debuerreotype), which python:3.12-slim is built on.
SLIM_EXCLUDES = ("path-exclude=/usr/share/doc/*", "path-include=/usr/share/doc/*/copyright",
                 "path-exclude=/usr/share/man/*", "path-exclude=/usr/share/info/*",
                 "path-exclude=/usr/share/locale/*", "path-exclude=/usr/share/groff/*",
                 "path-exclude=/usr/share/linda/*", "path-exclude=/usr/share/lintian/*")
_SKIP = {"test", "tests", "idle_test", "idlelib", "tkinter", "turtledemo", "__pycache__"}
_PATH = "/usr/local/bin:/usr/local/sbin:/usr/sbin:/usr/bin:/sbin:/bin"


def rootfs(folder: Path) -> Path:
    """Make the stand-in's root filesystem under ``folder``; return its path.

    Raises ``RuntimeError`` (with mmdebstrap's output) when the tool or the mirror is missing.
    """
    tool = shutil.which("mmdebstrap")
    if tool is None:
        raise RuntimeError("the Dockerfile build test needs mmdebstrap: apt-get install mmdebstrap"
                           " (./dev installs it)")
    root = folder / "rootfs"
    argv = [tool, "--variant=minbase", "--include=" + ",".join(PACKAGES),
            *(f"--dpkgopt={rule}" for rule in SLIM_EXCLUDES), "bookworm", str(root), MIRROR]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=900)
    if done.returncode != 0:
        raise RuntimeError(f"mmdebstrap failed ({done.returncode}), is {MIRROR} reachable?\n"
                           f"{done.stderr[-4000:]}")
    _python(Path(sys.base_prefix), root / "usr/local")
    subprocess.run(["ldconfig", "-r", str(root)], check=True, capture_output=True)
    return root


def _python(prefix: Path, local: Path) -> None:
    """Copy this interpreter (3.12 under ``prefix``) to ``local`` as the official image has it."""
    stdlib = prefix / "lib" / f"python{PY}"

    def ignore(folder: str, names: list[str]) -> set[str]:
        skip = {n for n in names if n in _SKIP or n.endswith(".a") or n.startswith("_tkinter")}
        if Path(folder) == stdlib / "site-packages":
            skip |= {n for n in names if not n.startswith("pip")}  # pip only, as upstream
        return skip

    shutil.copytree(stdlib, local / "lib" / f"python{PY}", symlinks=True, ignore=ignore)
    for lib in (prefix / "lib").glob("libpython*.so*"):
        shutil.copy2(lib, local / "lib" / lib.name, follow_symlinks=False)
    bin_ = local / "bin"
    bin_.mkdir(parents=True, exist_ok=True)
    shutil.copy2(prefix / "bin" / f"python{PY}", bin_ / f"python{PY}")
    for name in ("python3", "python"):
        (bin_ / name).symlink_to(f"python{PY}")
    script = (f"#!/usr/local/bin/python{PY}\nimport sys\nfrom pip._internal.cli.main import main\n"
              "sys.exit(main())\n")
    for name in ("pip", "pip3", f"pip{PY}"):
        (bin_ / name).write_text(script)
        os.chmod(bin_ / name, 0o755)


def build(folder: Path, name: str, env: Mapping[str, str]) -> str:
    """Make the stand-in in ``folder``, ``podman import`` it as ``name``; return its image id."""
    root = rootfs(folder)
    tar = folder / "rootfs.tar"
    subprocess.run(["tar", "--numeric-owner", "-C", str(root), "-cf", str(tar), "."], check=True,
                   capture_output=True)
    shutil.rmtree(root)
    done = subprocess.run(
        ["podman", "import", f"--change=ENV=PATH={_PATH}", "--change=ENV=LANG=C.UTF-8",
         f"--change=ENV=PYTHON_VERSION={sys.version.split()[0]}", '--change=CMD=["python3"]',
         str(tar), name], capture_output=True, text=True, env=dict(env), timeout=600)
    tar.unlink()
    if done.returncode != 0:
        raise RuntimeError(f"podman import failed: {done.stderr.strip()}")
    return done.stdout.strip().splitlines()[-1]
