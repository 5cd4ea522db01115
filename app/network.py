"""Who may use the app: this machine only, unless whoever serves it passes ``--args
--allow-remote``. ``panel serve`` without ``--address`` listens on every interface, so:

* a server reachable beyond loopback refuses: the first page and the log say why and how
  to restart, and the server stops;
* a request from another machine, for a ``Host`` that is not this machine (a DNS-rebinding
  page) or with a websocket ``Origin`` other than the page's own gets the refusal.

Pure functions of the request (covering what ``--allow-websocket-origin`` does not: the
page request, and servers without that list); :mod:`mdcore_app.main` applies them.
"""

from __future__ import annotations

import ipaddress
import socket
from urllib.parse import urlsplit

#: Host names that mean this machine.
LOOPBACK_NAMES = {"localhost", "127.0.0.1", "::1", "[::1]"}
#: The opt-in, after ``panel serve app/main.py ... --args``.
OPT_IN = "--allow-remote"
#: The restart the messages suggest.
RESTART = ("panel serve app/main.py --address 127.0.0.1 --port {port} "
           "--allow-websocket-origin 127.0.0.1:{port}")


def is_loopback(host: str | None) -> bool:
    """Whether ``host`` (a name or an IP address, IPv6 in brackets or not) is loopback."""
    if not host:
        return False
    host = host.strip().lower()
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def _host_and_port(netloc: str) -> tuple[str, int | None]:
    """``("127.0.0.1", 5006)`` from ``"127.0.0.1:5006"`` (IPv6 in brackets)."""
    parts = urlsplit(f"//{netloc}")
    try:
        return parts.hostname or "", parts.port
    except ValueError:                       # a port that is not a number
        return parts.hostname or "", None


def own_addresses() -> set[str]:
    """This machine's addresses beyond loopback, found without sending a packet: the default
    route's interface (a UDP ``connect`` only picks it) and the host name's addresses."""
    found: set[str] = set()
    for family, probe in ((socket.AF_INET, "192.0.2.1"), (socket.AF_INET6, "2001:db8::1")):
        try:
            with socket.socket(family, socket.SOCK_DGRAM) as s:
                s.connect((probe, 9))
                found.add(s.getsockname()[0])
        except OSError:
            pass
    try:
        for info in socket.getaddrinfo(socket.gethostname(), None):
            found.add(str(info[4][0]))
    except OSError:
        pass
    return {a for a in found if not is_loopback(a) and not a.startswith("fe80")}


def reachable_beyond_loopback(port: int, timeout: float = 0.5) -> str | None:
    """An address of this machine beyond loopback where ``port`` accepts TCP, or None."""
    for address in sorted(own_addresses()):
        try:
            with socket.create_connection((address, port), timeout=timeout):
                return address
        except OSError:
            continue
    return None


def how_to_restart(port: int | None) -> str:
    """The sentence every refusal ends with: the restart, and the opt-in."""
    port = port or 5006
    return (f"This app serves this machine only. Restart it with `{RESTART.format(port=port)}` "
            f"and open http://127.0.0.1:{port}; to serve your network on purpose, add "
            f"`{OPT_IN}` after `--args` (and --allow-websocket-origin for the address others "
            "use).")


def port_of(request) -> int | None:
    """The port in the ``Host`` header of a Bokeh session context's ``request``."""
    return _host_and_port(str(_headers(request).get("host", "")))[1]


def _headers(request) -> dict:
    return {k.lower(): v for k, v in dict(getattr(request, "headers", {}) or {}).items()}


def request_refusal(request) -> str | None:
    """Why the app refuses a Bokeh session context's page or websocket ``request``, or None:
    from another machine, for another host, or a websocket from another site (without a
    ``Host`` header, as a session built ahead, by where it comes from alone)."""
    headers = _headers(request)
    host, port = _host_and_port(str(headers.get("host", "")))
    remote = getattr(request, "remote_ip", None)
    if remote and not is_loopback(remote):
        return f"Refused a request from {remote}, another machine. {how_to_restart(port)}"
    if host and not is_loopback(host):          # a browser always names the host
        return (f"Refused a request for the host {host!r}, which is not this machine "
                f"(127.0.0.1 or localhost). {how_to_restart(port)}")
    origin = headers.get("origin")
    if origin and _host_and_port(urlsplit(str(origin)).netloc) != (host, port):
        return (f"Refused a websocket from the page of another site ({origin}). "
                f"{how_to_restart(port)}")
    return None


def binding_refusal(port: int | None) -> str | None:
    """Why the app refuses to run on a server answering at ``port`` beyond loopback, or None."""
    exposed = None if port is None else reachable_beyond_loopback(port)
    if exposed is None:
        return None
    return (f"This server listens beyond this machine: it answers at {exposed}:{port}, so "
            "anyone on your network could use it (panel serve without --address 127.0.0.1 "
            f"listens on every interface); it has stopped. {how_to_restart(port)}")
