"""Who may talk to the teleop server: a pure check of one request's Host, Origin and token.

The threat (docs/teleop.md, "Security"): the server drives a robot and writes files, and it listens on
127.0.0.1, which every web page the user opens in the same browser can reach. A foreign page can open
a WebSocket to it (browsers send WebSockets across origins) and DNS rebinding can make a foreign name
resolve to 127.0.0.1. So, like Jupyter:

- ``Host`` must name the bound address or a loopback name (``127.0.0.1``, ``localhost``, ``[::1]``),
  with the server's port: a rebound name (``evil.example``) is refused;
- a WebSocket upgrade (the only request that changes state) must carry ``Origin`` equal to the page's
  own origin ``http://HOST:PORT``; a missing Origin is refused too (non-browser clients send it);
- every request except the static assets (``/static/...``: the page's code and style, no state, no
  secrets) must carry the per-run ``token`` (``?token=...``) printed in the URL; the page keeps it;
- requests other than GET/HEAD are refused (nothing is posted to this server).

``allow_origins`` opens it on purpose: each entry is an extra origin (``http://host:port``) whose
host is accepted as ``Host`` too, and ``*`` accepts any Origin and any Host. The token stays
required either way. Every refusal is HTTP 403 with a one-line reason.
"""

from __future__ import annotations

import hmac
import secrets
from dataclasses import dataclass, field
from urllib.parse import parse_qs, urlsplit

__all__ = ["AccessPolicy", "new_token", "refusal"]

LOOPBACK_NAMES = ("127.0.0.1", "localhost", "::1")
WILDCARD = "*"


def new_token() -> str:
    """A random per-run token (128 bits, URL-safe)."""
    return secrets.token_urlsafe(16)


def _split_host(value: str) -> tuple[str, int | None] | None:
    """``host[:port]`` (IPv6 in brackets) -> (lower-case host, port or None); None if malformed."""
    value = value.strip().lower()
    if not value:
        return None
    if value.startswith("["):
        end = value.find("]")
        if end < 0:
            return None
        host, rest = value[1:end], value[end + 1:]
        if rest and not rest.startswith(":"):
            return None
        port_s = rest[1:] if rest else ""
    else:
        host, _, port_s = value.partition(":")
    if port_s:
        if not port_s.isdigit() or len(port_s) > 5:
            return None
        return host, int(port_s)
    return host, None


@dataclass(frozen=True)
class AccessPolicy:
    """What the server accepts (see the module docstring)."""

    port: int
    """The port the server listens on (Host and Origin must name it)."""
    token: str
    """The per-run token every request but the static assets carries (``?token=``)."""
    bound_host: str = "127.0.0.1"
    """The address the server is bound to; accepted as Host next to the loopback names."""
    allow_origins: tuple[str, ...] = field(default_factory=tuple)
    """Extra origins (``http://host:port``) accepted, their hosts accepted as Host; ``*``: any."""

    @property
    def open_to_all(self) -> bool:
        return WILDCARD in self.allow_origins

    def hosts(self) -> set[tuple[str, int]]:
        names = {n: self.port for n in LOOPBACK_NAMES}
        if self.bound_host not in ("0.0.0.0", "::", ""):
            names[self.bound_host.lower().strip("[]")] = self.port
        out = set(names.items())
        for o in self.allow_origins:
            if o != WILDCARD:
                u = urlsplit(o)
                if u.hostname:
                    out.add((u.hostname.lower(), u.port or (443 if u.scheme == "https" else 80)))
        return out

    def origins(self) -> set[str]:
        out = {f"http://{'[' + h + ']' if ':' in h else h}:{p}" for h, p in self.hosts()}
        return out | {o.rstrip("/").lower() for o in self.allow_origins if o != WILDCARD}


def refusal(policy: AccessPolicy, *, method: str, path: str, query: str, headers: dict[str, str],
            websocket: bool) -> str | None:
    """None when the request may proceed, else the one-line reason of a 403.

    ``headers``: lower-case names -> values; ``query``: the raw query string."""
    if not websocket and method.upper() not in ("GET", "HEAD"):
        return f"method {method} is not accepted"
    if not policy.open_to_all:
        host = _split_host(headers.get("host", ""))
        if host is None:
            return "missing or malformed Host header"
        name, port = host
        if (name, port if port is not None else 80) not in policy.hosts():
            return f"Host {headers.get('host')!r} is not this server (open the URL presim teleop printed)"
        if websocket:
            origin = headers.get("origin")
            if origin is None:
                return "WebSocket without an Origin header"
            if origin.rstrip("/").lower() not in policy.origins():
                return f"Origin {origin!r} is not this server's page (presim teleop --allow-origin opens it)"
    if path.startswith("/static/") and not websocket:
        return None
    token = parse_qs(query).get("token", [""])[0]
    if not hmac.compare_digest(token.encode(), policy.token.encode()):
        return "missing or wrong token (open the URL presim teleop printed, with its ?token=...)"
    return None
