"""DNS rebinding: a service without tokens answers only requests that name this machine.

Without API tokens `fleetmap serve` listens on loopback only, so that only this machine can change
the maps (docs/security.md). A web page can still reach it through its visitor's browser: a page of
`http://attacker.example:8000` whose name the attacker's DNS then points at `127.0.0.1` ("DNS
rebinding") is, to the browser, the same origin as the service. Its script could list, read, delete
and overwrite every map, with no CORS or cross-site check in the way (`Sec-Fetch-Site` says
`same-origin`). What gives such a request away is its `Host` header, which names the attacker's host.

`LoopbackHostOnly` answers a JSON 403 to any request whose `Host` is not a name of this machine:
`localhost` or a loopback address (`127.0.0.1`, any of `127.0.0.0/8`, `[::1]`), with any port. An
attacker's DNS name can never be one of those, and an address cannot be rebound. `fleetmap serve`
installs it when it serves without tokens and without `--insecure` (then its socket is on loopback);
`--insecure` accepts requests for any host, as it accepts any address (a reverse proxy that passes
its clients' `Host` on to a service without tokens exposes the service as binding to all interfaces
would). A request without `Host` (HTTP/1.0; no browser sends one) is let through.
"""

from __future__ import annotations

import ipaddress

from starlette.datastructures import Headers
from starlette.types import ASGIApp, Receive, Scope, Send

from fleetmap.api.errors import error_answer

#: The most of a refused `Host` header quoted in the answer (a header may be 64 KiB long).
_QUOTED_HOST_CHARS = 100


def host_name(host: str) -> str:
    """The name or address of a `Host` header's value, without its port, IPv6 brackets or a final
    dot, in lower case: `[::1]:8000` -> `::1`, `LocalHost.:80` -> `localhost`."""
    host = host.strip().lower()
    if host.startswith("["):
        return host[1:].partition("]")[0]
    return host.rpartition(":")[0].rstrip(".") if ":" in host else host.rstrip(".")


def is_loopback_name(name: str) -> bool:
    """Whether `name` (`host_name`'s) names this machine: `localhost` or a loopback address."""
    if name == "localhost":
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


class LoopbackHostOnly:
    """ASGI middleware refusing (403) requests whose `Host` names no loopback host (see the module's
    docstring)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        host = Headers(scope=scope).get("host")
        if host is not None and not is_loopback_name(host_name(host)):
            quoted = host if len(host) <= _QUOTED_HOST_CHARS else host[:_QUOTED_HOST_CHARS] + "..."
            detail = (
                f"this service runs without API tokens and answers only requests for this machine "
                f"(Host localhost, 127.0.0.1 or [::1]), not for {quoted!r}: a web page whose name "
                "was pointed at this machine (DNS rebinding) could otherwise change the maps. Behind "
                "a reverse proxy that passes its own Host on, give the service API tokens (or "
                "--insecure to accept that anyone who reaches the proxy may change the maps)"
            )
            await error_answer(403, detail)(scope, receive, send)
            return
        await self.app(scope, receive, send)
