"""Failed sign-ins, limited per client address: `POST /session` with a wrong token (or none) is a
guess at a token, and nothing slowed guessing down.

After `max_failures` failed sign-ins (401) from one client address within `window` seconds of the
first of them, every sign-in from that address is answered 429, with `Retry-After` and the usual
JSON `{"detail": ...}`, until the window has passed; the count then starts again. A blocked request
never reaches the token check: were a right token let through, 200 against 429 would tell a
guesser which guess was right, so a user who mistyped their token too often waits too. A
successful sign-in neither counts nor clears the failures: a client holding one token must not use
it to keep guessing another (an admin's, say).

The client address is the connection's, or, behind a reverse proxy the service trusts
(`--forwarded-allow-ips`), the one the proxy names in `X-Forwarded-For` (uvicorn applies it). Behind
a proxy that is not trusted, every client has the proxy's address and shares one count. With
`--forwarded-allow-ips '*'` uvicorn takes the first address of `X-Forwarded-For`, which a client
behind a proxy that appends to it writes itself: a fresh count per guess (docs/security.md says to
name the proxies instead). An IPv6
client counts by its /64 network: one host commonly holds a whole /64, and would otherwise have a
fresh count for each of its addresses.

Memory is bounded: at most `max_clients` addresses are tracked; past that, the address that failed
least recently is forgotten (an attacker with that many addresses gains a fresh count on some of
them, which the window would have given it soon anyway). An address whose window has passed is
dropped when it is next looked at, or, when another address fails for the first time, if it is
among the least recently failed.
"""

from __future__ import annotations

import ipaddress
import math

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from fleetmap.api.errors import error_answer
from fleetmap.auth import SESSION_PATH
from fleetmap.failed_signins import SignInLimiter
from fleetmap.route_path import route_path

#: The prefix length by which IPv6 clients are counted.
IPV6_PREFIX = 64


def client_address(scope: Scope) -> str:
    """The client address failures are counted by: the request's (uvicorn's: the proxy's
    `X-Forwarded-For` for a trusted proxy), an IPv6 one as its /64 network."""
    client = scope.get("client")
    if not client:
        return "(unknown)"
    host = str(client[0])
    try:
        address = ipaddress.ip_address(host)
    except ValueError:  # not an address (a Unix socket's path, say): counted as it is
        return host
    if isinstance(address, ipaddress.IPv6Address):
        if address.ipv4_mapped is not None:  # an IPv4 client of a dual-stack socket
            return str(address.ipv4_mapped)
        return str(ipaddress.IPv6Network((address, IPV6_PREFIX), strict=False))
    return str(address)


class SignInLimit:
    """ASGI middleware: `POST /session` from an address that failed too often is answered 429 without
    running the sign-in; a 401 answer to it counts as a failure (see the module's docstring), as
    soon as the answer starts, not once it has been sent. Placed just outside the auth middleware,
    whose 401 is most failures: nothing waits between this check and its decision, so sign-ins from
    one address are checked and counted one after the other, however many arrive at once."""

    def __init__(self, app: ASGIApp, limiter: SignInLimiter) -> None:
        self.app = app
        self.limiter = limiter

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "POST" or route_path(scope) != SESSION_PATH:
            await self.app(scope, receive, send)
            return
        address = client_address(scope)
        wait = self.limiter.retry_after(address)
        if wait is not None:
            seconds = max(1, math.ceil(wait))
            detail = (
                f"too many failed sign-ins from this address ({self.limiter.max_failures} within "
                f"{self.limiter.window:g} s): try again in {seconds} s"
            )
            await error_answer(429, detail, headers={"Retry-After": str(seconds)})(scope, receive, send)
            return

        async def watched(message: Message) -> None:
            # Counted as the refusal starts, before it is passed on: sending waits while the client
            # reads nothing (its connection's write buffer full, as behind a large answer it asked
            # for first on that connection), and a failure counted once the answer was sent let
            # every sign-in that arrived meanwhile past the check above, each a guess answered:
            # 25 connections got 25 guesses through a limit of 10.
            if message["type"] == "http.response.start" and message["status"] == 401:
                self.limiter.failed(address)
            await send(message)

        await self.app(scope, receive, watched)
