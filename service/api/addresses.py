"""Who is at the other end: the client's address and scheme, derived in one place from the
connection and the proxies the operator trusts (`POLYDDA_TRUSTED_PROXIES`).

Ownership without keys, the rate limits, the wrong-key throttle and the access log all read
the address this derives (the middleware puts it in the request's scope). `X-Forwarded-For`
and `X-Forwarded-Proto` count only when the connection comes from a trusted proxy; from
anyone else they are ignored. The app does not rely on its launcher for this: a server that
rewrote the client's address from the header itself (uvicorn does from 127.0.0.1 unless
started with `--no-proxy-headers`; `polydda serve` starts it so) leaves a client address
that is one of the header's entries, and such a request is refused (400) unless it came
through a proxy the operator named.
"""

from __future__ import annotations

import ipaddress
import json
from collections.abc import Iterable, MutableMapping
from typing import Any

from service.api.middleware import ASGI, Receive, Send

Network = ipaddress.IPv4Network | ipaddress.IPv6Network

#: the schemes a trusted proxy may say the browser used
_SCHEMES = frozenset({"http", "https"})


class ForwardedError(ValueError):
    """A request whose address cannot be trusted: the reason, for a 400."""


def parse_networks(values: Iterable[str]) -> tuple[Network, ...]:
    """Addresses and networks (`10.0.0.0/8`, `127.0.0.1`, `::1`) as networks; ValueError
    naming the first that is neither."""
    out = []
    for value in values:
        try:
            out.append(ipaddress.ip_network(value.strip(), strict=False))
        except ValueError:
            raise ValueError(f"{value!r} is not an IP address or network "
                             "(e.g. 10.0.0.5, 10.0.0.0/8, ::1)") from None
    return tuple(out)


def parse_host(entry: str) -> str | None:
    """The address of one X-Forwarded-For entry (`1.2.3.4`, `1.2.3.4:5678`, `::1`,
    `[::1]:5678`), normalized; None when it is no IP address."""
    entry = entry.strip()
    if entry.startswith("["):
        entry = entry[1:].split("]", 1)[0]
    elif entry.count(":") == 1:  # IPv4 with a port
        entry = entry.split(":", 1)[0]
    try:
        return str(ipaddress.ip_address(entry))
    except ValueError:
        return None


def is_trusted(host: str | None, trusted: tuple[Network, ...]) -> bool:
    """True if `host` is an IP address inside one of the trusted networks."""
    if host is None or not trusted:
        return False
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return False
    return any(address in net for net in trusted)


def _entries(headers: Iterable[tuple[bytes, bytes]], name: bytes) -> list[str]:
    """Every comma-separated entry of every header `name`, in order."""
    return [e.strip() for k, v in headers if k.lower() == name
            for e in v.decode("latin-1").split(",") if e.strip()]


def derive_client(peer: str | None, headers: Iterable[tuple[bytes, bytes]], scheme: str,
                  trusted: tuple[Network, ...]) -> tuple[str, str]:
    """`(address, scheme)` of the client behind a connection from `peer`.

    From a trusted proxy: the right-most X-Forwarded-For entry that is not itself a trusted
    proxy (each proxy appends the address it saw; entries left of it are what the client
    claimed), and X-Forwarded-Proto's scheme. From anyone else: the peer and the
    connection's scheme, the headers ignored; ForwardedError when the peer is one of the
    header's entries (the launching server took the address from the header).
    """
    headers = list(headers)
    forwarded = _entries(headers, b"x-forwarded-for")
    if not is_trusted(peer, trusted):
        if forwarded and peer is not None and \
                (parse_host(peer) or peer) in {parse_host(e) for e in forwarded}:
            raise ForwardedError(
                "the server that launched this service took the client's address from "
                "X-Forwarded-For, and this service trusts no proxy at that address: start "
                "uvicorn with --no-proxy-headers (polydda serve does) and name the proxies "
                "in POLYDDA_TRUSTED_PROXIES")
        return peer or "unknown", scheme
    address = peer
    for entry in reversed(forwarded):
        host = parse_host(entry)
        if host is None:
            raise ForwardedError("a trusted proxy sent an X-Forwarded-For entry that is no "
                                 f"IP address ({entry[:40]!r})")
        address = host
        if not is_trusted(host, trusted):
            break
    proto = _entries(headers, b"x-forwarded-proto")
    if proto and proto[0].lower() in _SCHEMES:
        scheme = proto[0].lower()
    return address or "unknown", scheme


class ClientAddress:
    """Puts the derived client address and scheme (:func:`derive_client`) in the scope of
    every HTTP request, where the routes, the limits and the access log read them; a
    request whose address cannot be trusted is answered 400 (a problem document)."""

    def __init__(self, app: ASGI, trusted: tuple[Network, ...]) -> None:
        self.app, self.trusted = app, trusted

    async def __call__(self, scope: MutableMapping[str, Any], receive: Receive,
                       send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        client = scope.get("client")
        peer = client[0] if client else None
        try:
            address, scheme = derive_client(peer, scope.get("headers", ()),
                                            scope.get("scheme", "http"), self.trusted)
        except ForwardedError as exc:
            body = json.dumps({"type": "/problems/untrusted-forwarding",
                               "title": "Untrusted forwarded address", "status": 400,
                               "detail": str(exc), "instance": scope.get("path", "")}).encode()
            await send({"type": "http.response.start", "status": 400, "headers": [
                (b"content-type", b"application/problem+json"),
                (b"content-length", str(len(body)).encode())]})
            await send({"type": "http.response.body", "body": body})
            return
        # in place: the server's access log reads the same scope
        scope["client"] = (address, client[1] if client and address == peer else 0)
        scope["scheme"] = scheme
        await self.app(scope, receive, send)
