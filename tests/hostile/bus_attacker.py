"""A hostile zenoh peer, run as its own process: ``python -m tests.hostile.bus_attacker ...``.

It holds no token. It reaches the router like any local process can (a TCP listener on
loopback), optionally after dropping to the ``nobody`` user (``--as-nobody``: imports first,
as root, because the interpreter lives under /root here), and then:

- ``harvest ENDPOINT SECONDS OUT``: answers every query and hears every put under the
  cluster prefix, in plain and wildcard forms (``**``, ``*/**``, ``osmo/local/*/**``), and
  writes what it heard to OUT (one JSON line per message, bytes as latin-1 text).
- ``forge ENDPOINT KEY PAYLOAD``: puts PAYLOAD on KEY (a key expression, wildcards allowed)
  a few times.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time

from osmo.transport.zenoh_link import Link, Request

_FORMS = ["**", "*/**", "osmo/local/**", "osmo/local/*/**", "osmo/*/api/*",
          "osmo/local/api/**", "osmo/local/to-worker/*"]


def _drop_privileges() -> None:
    os.setgroups([])
    os.setgid(65534)
    os.setuid(65534)


def harvest(endpoint: str, seconds: float, out: str) -> None:
    link = Link.client([endpoint], "local")
    heard: list[dict[str, str]] = []
    lock = threading.Lock()

    def note(kind: str, key: str, data: bytes, att: bytes | None) -> None:
        with lock:
            heard.append({"kind": kind, "key": key, "data": data.decode("latin-1"),
                          "att": (att or b"").decode("latin-1")})

    def answer(request: Request) -> None:
        note("query", request.key, request.payload, request.attachment)
        request.reply(b'{"ok": [{"id": "forged-1", "status": "COMPLETED"}]}',
                      request.attachment)

    for form in _FORMS:
        for declare in (lambda f: link.serve(f, answer),
                        lambda f: link.subscribe_raw(f, lambda k, d, a: note("put", k, d, a))):
            try:
                declare(form)
            except Exception:  # noqa: BLE001 - a refused declaration is the router's answer
                pass
    print("listening", flush=True)
    time.sleep(seconds)
    with lock, open(out, "w") as f:
        for entry in heard:
            f.write(json.dumps(entry) + "\n")
    link.close()


def forge(endpoint: str, key: str, payload: str) -> None:
    link = Link.client([endpoint], "local")
    for _ in range(3):
        link.put(key, payload.encode())
        time.sleep(0.1)
    link.close()


def main(argv: list[str]) -> None:
    if "--as-nobody" in argv:
        argv.remove("--as-nobody")
        _drop_privileges()
    mode, endpoint, *rest = argv
    if mode == "harvest":
        harvest(endpoint, float(rest[0]), rest[1])
    elif mode == "forge":
        forge(endpoint, rest[0], rest[1])
    else:
        raise SystemExit(f"unknown mode {mode}")


if __name__ == "__main__":
    main(sys.argv[1:])
