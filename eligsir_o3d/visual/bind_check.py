"""Checks made before a viewer starts serving: viser binds in a background thread, so a port
out of range, a host that does not resolve or an address this machine does not have would otherwise print a thread
traceback and hang. Each is a ValueError here, one line (``eligsir view`` exits 2).

- :func:`check_bind`: the port is 0..65535; the host resolves; a socket can be bound to it (a port in use is fine:
  the viewer takes the next free one).
- :func:`served_urls`: the URLs a browser can use; for ``0.0.0.0`` / ``::`` (every interface) this machine's own
  addresses, with :data:`NETWORK_WARNING`.
"""

from __future__ import annotations

import errno
import socket

NETWORK_WARNING = ("warning: --host {host} serves the map to every network this machine is on (anyone who can "
                   "reach it can look at the map); use --host 127.0.0.1 to keep it on this machine")
WILDCARD = ("0.0.0.0", "", "::")  # the usual spellings; :func:`is_wildcard` also knows "0", "::0", "0.0", ...


def is_wildcard(host: str) -> bool:
    """Whether ``host`` means every interface (an unspecified address however it is spelled: ``0``, ``::0``,
    ``0x0``, ``0000::``), so that the network warning and the URLs never depend on the spelling."""
    import ipaddress

    if host in WILDCARD:
        return True
    try:
        infos = socket.getaddrinfo(host, None, flags=socket.AI_NUMERICHOST)
    except (socket.gaierror, UnicodeError, ValueError):
        return False
    return any(ipaddress.ip_address(info[4][0].split("%")[0]).is_unspecified for info in infos)


def check_bind(host: str, port: int) -> None:
    if not isinstance(port, int) or not 0 <= port <= 65535:
        raise ValueError(f"--port {port}: not a port number (0-65535; 0: any free port)")
    try:
        infos = socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError, ValueError) as e:
        raise ValueError(f"--host {host}: not an address or a name that resolves ({e})") from None
    family, _, _, _, addr = infos[0]
    s = socket.socket(family, socket.SOCK_STREAM)
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(addr)
    except OSError as e:
        if e.errno == errno.EADDRINUSE:
            return  # taken: the viewer moves on to the next free port
        if e.errno == errno.EADDRNOTAVAIL:
            raise ValueError(f"--host {host}: not an address of this machine (cannot listen there)") from None
        if e.errno == errno.EACCES:
            raise ValueError(f"--port {port}: permission denied (ports below 1024 need root); choose another "
                             f"--port") from None
        raise ValueError(f"--host {host} --port {port}: cannot listen there ({e.strerror or e})") from None
    finally:
        s.close()


def _own_addresses() -> list[str]:
    found = []
    try:
        found += socket.gethostbyname_ex(socket.gethostname())[2]
    except OSError:
        pass
    try:  # the address of the default route's interface (no packet is sent)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect(("192.0.2.1", 9))
            found.append(s.getsockname()[0])
    except OSError:
        pass
    return sorted({a for a in found if not a.startswith("127.")})


def served_urls(host: str, port: int) -> list[str]:
    """The URLs of a viewer on ``host:port``: loopback first, then this machine's addresses for a wildcard."""
    if is_wildcard(host):
        return [f"http://127.0.0.1:{port}"] + [f"http://{a}:{port}" for a in _own_addresses()]
    return [f"http://[{host}]:{port}" if ":" in host else f"http://{host}:{port}"]
