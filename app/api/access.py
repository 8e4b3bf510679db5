"""Who may drive the dashboard: the Host, Origin and token checks of both servers (the FastAPI API and viser's
page and WebSocket).

A browser lets any page it shows send requests to 127.0.0.1: a WebSocket to any origin, and "simple" POSTs
(no body, or text/plain) without asking. So every request is checked here before either server acts on it:

- Host must name this machine (a loopback name, or an address the servers are bound to): a DNS-rebinding page,
  whose requests carry its own host name, is refused (421).
- State-changing requests (any method but GET, HEAD and OPTIONS) and the viser WebSocket, when they carry an
  Origin (every browser sends one), must come from the dashboard's own origins, the page's and the API's (403).
  Requests without an Origin come from programs (curl, httpx), which no page can make.
- With a token (always when bound beyond loopback, or with `gsmn serve --token`), every API request and the
  WebSocket must carry it (401 without, 403 when wrong): as `Authorization: Bearer TOKEN`, an `X-GSMN-Token`
  header, a `token` query parameter, or the cookie that a first request with `?token=` sets (the page's URL
  printed at start-up carries it, and the cookie carries it on to the page's WebSocket). viser's page itself
  (static HTML, no data) is served to the right Host without one.

viser (1.1) has no hook of its own for this: its server calls `websockets.asyncio.server.serve` with a
`process_request` callback (its static-file server). `guard_viser` hands viser's module a `serve` that wraps
that callback with these checks, for the port each dashboard registers; a port not registered is refused, so a
change in viser's internals fails closed.
"""

from __future__ import annotations

import hmac
import http
import ipaddress
import os
import secrets
import socket
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from http.cookies import CookieError, SimpleCookie
from urllib.parse import parse_qs, urlsplit

from fastapi.responses import JSONResponse

TOKEN_ENV = "GSMN_TOKEN"
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")
WILDCARDS = ("0.0.0.0", "::", "")


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def resolve_token(given: str | None, host: str) -> str | None:
    """The token requests must carry: `given` ("" asks for a fresh one), else $GSMN_TOKEN, else a fresh one when
    bound beyond loopback; None on loopback without either."""
    if given is None:
        given = os.environ.get(TOKEN_ENV) or None
    if given == "" or (given is None and not is_loopback(host)):
        return secrets.token_urlsafe(24)
    return given


def machine_addresses(host: str) -> list[str]:
    """The addresses a server bound to `host` answers on: `host` itself, or for a wildcard, loopback and this
    machine's own addresses (those of its host name, and the one its default route leaves from)."""
    if host not in WILDCARDS:
        return [host]
    v6 = ":" in host
    found = ["::1" if v6 else "127.0.0.1"]
    family = socket.AF_INET6 if v6 else socket.AF_INET
    for name in {socket.gethostname(), socket.getfqdn()}:
        try:
            found += [a[4][0] for a in socket.getaddrinfo(name, None, family, socket.SOCK_STREAM)]
        except OSError:
            pass
    try:  # no packet is sent: connect() on a UDP socket only picks the route
        with socket.socket(family, socket.SOCK_DGRAM) as s:
            s.connect(("2001:db8::1" if v6 else "192.0.2.1", 9))
            found.append(s.getsockname()[0])
    except OSError:
        pass
    out: list[str] = []
    for a in found:
        a = a.split("%", 1)[0]  # an IPv6 zone id
        if a not in out:
            out.append(a)
    return out


def url(host: str, port: int, path: str = "") -> str:
    return f"http://[{host}]:{port}{path}" if ":" in host else f"http://{host}:{port}{path}"


def _hostname(value: str | None) -> str | None:
    """The host name of a Host header or an Origin's netloc, lower case and without brackets; None if malformed."""
    if not value:
        return None
    try:
        parts = urlsplit("//" + value)
        _ = parts.port  # raises on a malformed port
    except ValueError:
        return None
    return parts.hostname


@dataclass(frozen=True)
class Access:
    """The checks of one dashboard: the host names it answers to, its two ports, and its token (None: none)."""

    hosts: frozenset[str]
    ports: tuple[int, ...]
    token: str | None = None

    @classmethod
    def for_bind(cls, host: str, ports: tuple[int, ...], token: str | None) -> Access:
        names = set(LOOPBACK_NAMES) | {h.lower() for h in machine_addresses(host)}
        if host in WILDCARDS:
            names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
        return cls(frozenset(names), tuple(ports), token)

    @property
    def cookie(self) -> str:
        """Cookies are per host, not per port: each dashboard names its own by its page's port."""
        return f"gsmn_token_{self.ports[0]}"

    def origins(self) -> set[str]:
        return {url(h, p) for h in self.hosts for p in self.ports}

    def refusal(self, method: str, headers: Mapping[str, str], query: str, *, needs_token: bool = True,
                origin_always: bool = False) -> tuple[int, str] | None:
        """(status, why) when a request may not go on, else None. `headers` by lower-case name."""
        host = _hostname(headers.get("host"))
        if host is None or host not in self.hosts:
            return 421, (f"this dashboard does not answer to the host {headers.get('host')!r}: open it as "
                         "http://127.0.0.1 (or an address it was bound to)")
        origin = headers.get("origin")
        if origin is not None and (origin_always or method.upper() not in SAFE_METHODS):
            if origin.rstrip("/").lower() not in self.origins():
                return 403, (f"requests from the origin {origin!r} are refused: only the dashboard's own page "
                             "may change its state")
        if self.token is not None and needs_token:
            given = self.given_token(headers, query)
            if given is None:
                return 401, ("this dashboard needs its token (printed by `gsmn serve`): open the page's URL with "
                             "?token=..., or send the header 'Authorization: Bearer TOKEN'")
            if not hmac.compare_digest(given.encode("utf-8", "replace"), self.token.encode()):
                return 403, "wrong token"
        return None

    def given_token(self, headers: Mapping[str, str], query: str) -> str | None:
        auth = headers.get("authorization", "")
        if auth[:7].lower() == "bearer ":
            return auth[7:].strip()
        if headers.get("x-gsmn-token"):
            return headers["x-gsmn-token"]
        if (q := self.query_token(query)) is not None:
            return q
        try:
            jar = SimpleCookie(headers.get("cookie", ""))
        except CookieError:
            return None
        return jar[self.cookie].value if self.cookie in jar else None

    @staticmethod
    def query_token(query: str) -> str | None:
        values = parse_qs(query).get("token") if query else None
        return values[-1] if values else None

    def set_cookie(self, query: str) -> str | None:
        """The Set-Cookie value for a request whose ?token= is right (so the page's WebSocket carries it)."""
        q = self.query_token(query)
        if self.token is None or q is None or not hmac.compare_digest(q.encode("utf-8", "replace"),
                                                                      self.token.encode()):
            return None
        return f"{self.cookie}={self.token}; Path=/; HttpOnly; SameSite=Strict"


# -- the API: an ASGI middleware --------------------------------------------------------------------------------
class AccessMiddleware:
    """Refuses requests that fail `Access.refusal` with {"detail": why}; sets the token cookie after a right
    ?token=."""

    def __init__(self, app, access: Access):
        self.app, self.access = app, access

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        query = scope.get("query_string", b"").decode("latin-1")
        refused = self.access.refusal(scope["method"], headers, query)
        if refused is not None:
            status, why = refused
            return await JSONResponse({"detail": why}, status_code=status)(scope, receive, send)
        cookie = self.access.set_cookie(query)
        if cookie is None:
            return await self.app(scope, receive, send)

        async def send_with_cookie(message):
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", []),
                                                  (b"set-cookie", cookie.encode("latin-1"))]}
            await send(message)

        return await self.app(scope, receive, send_with_cookie)


# -- viser: its WebSocket handshake and static files --------------------------------------------------------------
_guards: dict[int, Access] = {}
_guard_lock = threading.Lock()


def guard_viser(port: int, access: Access) -> None:
    """Check every request to the viser server on `port` with `access` (see the module docstring)."""
    install_viser_guard()
    with _guard_lock:
        _guards[port] = access


def unguard_viser(port: int) -> None:
    with _guard_lock:
        _guards.pop(port, None)


def install_viser_guard() -> None:
    """Give viser's server module a `serve` whose `process_request` checks each request first. Once per process;
    before any ViserServer starts (a server started before it is refused nothing and must not be used)."""
    import websockets.asyncio.server as ws_server
    from viser.infra import _infra

    if isinstance(_infra.websockets, _Namespace):
        return
    real_serve = ws_server.serve

    def serve(handler, *args, process_request=None, **kwargs):
        return real_serve(handler, *args, process_request=_checked(process_request), **kwargs)

    _infra.websockets = _Namespace(_infra.websockets, asyncio=_Namespace(
        _infra.websockets.asyncio, server=_Namespace(ws_server, serve=serve)))


class _Namespace:
    """A module with some attributes replaced: viser's own view of `websockets`, the rest of the process keeps its."""

    def __init__(self, target, **replaced):
        self._target, self._replaced = target, replaced

    def __getattr__(self, name):
        return self._replaced[name] if name in self._replaced else getattr(self._target, name)


def _checked(process_request: Callable | None) -> Callable:
    def check(connection, request):
        port = connection.transport.get_extra_info("sockname")[1]
        with _guard_lock:
            access = _guards.get(port)
        if access is None:
            return connection.respond(http.HTTPStatus.SERVICE_UNAVAILABLE, "not ready\n")
        headers = {k.lower(): v for k, v in request.headers.raw_items()}
        websocket = headers.get("upgrade", "").lower() == "websocket"
        query = urlsplit(request.path).query
        refused = access.refusal("GET", headers, query, needs_token=websocket, origin_always=websocket)
        if refused is not None:
            return connection.respond(http.HTTPStatus(refused[0]), refused[1] + "\n")
        response = process_request(connection, request) if process_request is not None else None
        cookie = access.set_cookie(query)
        if response is not None and cookie is not None:
            response.headers["Set-Cookie"] = cookie
        return response

    return check
