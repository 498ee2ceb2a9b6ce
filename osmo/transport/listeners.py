"""Which zenoh endpoints other machines could reach, and refusing them without authentication.

A server listens on its home's Unix socket and on what ``--listen`` adds; a listener other
machines can reach (:func:`network_listeners`) needs zenoh authentication (user/password or
mutual TLS in ``--zenoh-config``) unless the user says ``--insecure`` (:func:`check_listeners`).
Both the server and the SDK (before it starts a local server) check this.
"""

from __future__ import annotations

import ipaddress
import logging

from osmo.errors import UsageError
from osmo.transport.zenoh_link import authenticates

__all__ = ["check_listeners", "network_listeners"]

_LOCAL_PROTOCOLS = ("unixsock-stream", "unixpipe")


def network_listeners(listen: tuple[str, ...] | list[str]) -> list[str]:
    """The endpoints of ``listen`` that other machines could reach (not loopback or a socket).

    Loopback is a loopback IP address (``127.0.0.0/8``, ``::1``) or the exact name
    ``localhost``; any other name (``127.example.com`` too) may resolve anywhere.
    """
    return [endpoint for endpoint in listen if not _is_local(endpoint)]


def _is_local(endpoint: str) -> bool:
    proto, _, rest = endpoint.partition("/")
    if proto in _LOCAL_PROTOCOLS:
        return True
    address = rest.split("?", 1)[0].split("#", 1)[0]  # zenoh's endpoint config and metadata
    host = address.rpartition(":")[0]
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_listeners(listen: tuple[str, ...] | list[str], zenoh_config: str | None, *,
                    insecure: bool) -> None:
    """Refuse a network listener without zenoh authentication, unless ``insecure``.

    Authentication means user/password (``transport.auth.usrpwd``) or mutual TLS
    (``transport.link.tls.enable_mtls``) in the zenoh config. With ``insecure``, a warning is
    logged at every start (stderr and ``server.log``).

    Raises:
        UsageError: a network listener, no authentication, no ``--insecure``.
    """
    exposed = network_listeners(listen)
    if not exposed or authenticates(zenoh_config):
        return
    what = ", ".join(exposed)
    if insecure:
        logging.getLogger("osmo.server").warning(
            "INSECURE: listening on %s without zenoh authentication (--insecure): anyone who "
            "can reach it can connect, and API tokens travel in clear over plain TCP", what)
        return
    raise UsageError(
        f"refusing to listen on {what} without authentication: anyone who can reach it "
        "could connect, and API tokens would travel in clear over plain TCP. Give a "
        "--zenoh-config with TLS and mutual TLS (enable_mtls) or user/password (usrpwd); "
        "see docs/how-to/secure-listener.md. To accept the risk (a trusted network only), add "
        "--insecure")
