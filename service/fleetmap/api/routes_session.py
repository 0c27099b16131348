"""Browser sessions: `POST /session` signs a browser in with an API token, `DELETE /session` out.

A browser's `<img>` tiles and `EventSource` cannot send an `Authorization` header, so the web viewer
of a service that requires a read token trades the token for a session cookie once, and the browser
sends the cookie with every request after. What the cookie holds, and why it unlocks reads only, is
`fleetmap.auth`'s (which also checks the token before `POST /session` runs).
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request, Response

from fleetmap.api.errors import ApiError
from fleetmap.api.state import State
from fleetmap.api.strict_requests import StrictRoute
from fleetmap.api_models import ErrorResponse, Session
from fleetmap.auth import (
    SESSION_COOKIE,
    SESSION_PATH,
    bearer_token,
    cleared_session_cookie,
    session_cookie,
    session_value,
)
from fleetmap.route_path import root_path

router = APIRouter(route_class=StrictRoute)

#: Answers that set the cookie: no cache keeps them, not even the browser's.
_CACHE_CONTROL = "no-store"


def _set_cookie_spec(cookie: str) -> dict[str, Any]:
    """The spec of a `Set-Cookie` header setting `cookie` (`auth.session_cookie`'s attributes)."""
    return {
        "description": f"`{cookie}; HttpOnly; SameSite=Strict; Path=/` (the path the service is served "
        "under: `--root-path`'s behind a proxy), and `Secure` when the request came over https",
        "schema": {"type": "string"},
    }


def _cookie_path(request: Request) -> str:
    """The cookie's `Path`: the path the service is served under (`--root-path`), `/` at the root."""
    return root_path(request.scope) or "/"


def _over_https(request: Request) -> bool:
    """Whether the request came over https: its own scheme, or a trusted proxy's `X-Forwarded-Proto`
    (uvicorn applies it for the proxies $FORWARDED_ALLOW_IPS names, by default loopback)."""
    return request.scope.get("scheme") == "https"


@router.post(
    SESSION_PATH,
    tags=["session"],
    summary="Sign a browser in: a session cookie that stands for the token on reads",
    response_model=Session,
    responses={
        200: {
            "description": "Signed in; the cookie is set",
            "headers": {"Set-Cookie": _set_cookie_spec(f"{SESSION_COOKIE}=<hex SHA-256 of the token>")},
        },
        401: {"model": ErrorResponse, "description": "No token, or an unknown one"},
        404: {"model": ErrorResponse, "description": "The service runs without API tokens: no sign-in"},
        429: {
            "model": ErrorResponse,
            "description": "Too many failed sign-ins from this client address: try again after Retry-After",
            "headers": {"Retry-After": {"description": "seconds to wait", "schema": {"type": "integer"}}},
        },
    },
    openapi_extra={"security": [{"bearerToken": []}]},
)
async def sign_in(request: Request, response: Response, state: State) -> Session:
    """Send `Authorization: Bearer <token>` (a token of any role, whether reading needs one or not);
    the answer sets the session cookie `fleetmap_session`, which the browser then sends with every
    request. It stands for the token on reads only (every GET, `POST .../cells` and `.../raycast`),
    never on writes, and an `Authorization: Bearer` header, when sent, wins over it. It holds the token's
    SHA-256 digest, not the token, and ends when its token is revoked (token file and SIGHUP), or
    when the browser closes. This is how the web viewer reads from a service that requires a read
    token (`--require-read-token`): its `<img>` tiles and `EventSource` cannot send a header.

    401 without a token or with an unknown one (and no cookie is set); 404 when the service runs
    without API tokens, as there is nothing to sign in to. 429, with `Retry-After`, after too many
    failed sign-ins from the client's address (10 within 60 s by default, from the first of them:
    `--max-failed-sign-ins`, `--failed-sign-in-window`), for every sign-in from it, a right token's
    too, until that window has passed; a successful sign-in is never counted."""
    tokens = state.settings.tokens
    if tokens is None:
        raise ApiError(
            404, "this service runs without API tokens: there is nothing to sign in to (reads need no token)"
        )
    # The auth middleware let the request in only with a valid token; the route reads it again for
    # the cookie (and stays safe in an app built without that middleware).
    token = bearer_token(request.scope["headers"])
    role = tokens.role_of(token) if token is not None else None
    if token is None or role is None:
        raise ApiError(401, "signing in needs a valid token: send 'Authorization: Bearer <token>'")
    cookie = session_cookie(session_value(token), secure=_over_https(request), path=_cookie_path(request))
    response.headers.append("Set-Cookie", cookie)
    response.headers["Cache-Control"] = _CACHE_CONTROL
    return Session(role=role)


@router.delete(
    SESSION_PATH,
    tags=["session"],
    summary="Sign a browser out: clear its session cookie",
    status_code=204,
    response_class=Response,
    responses={
        204: {
            "description": "Signed out; the cookie is cleared",
            "headers": {"Set-Cookie": _set_cookie_spec(f"{SESSION_COOKIE}=; Max-Age=0")},
        }
    },
)
async def sign_out(request: Request) -> Response:
    """Clears the session cookie (`fleetmap_session`). Needs no token: it only makes the browser
    forget its cookie, and must work once the token is revoked too. To end a session for every
    browser that holds it, revoke its token (token file and SIGHUP)."""
    headers = {
        "Set-Cookie": cleared_session_cookie(secure=_over_https(request), path=_cookie_path(request)),
        "Cache-Control": _CACHE_CONTROL,
    }
    return Response(status_code=204, headers=headers)
