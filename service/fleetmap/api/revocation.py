"""Writes whose body arrives after their token was revoked: refused, nothing changed.

A request is let in by the tokens in force when its head arrives (`fleetmap.auth.AuthMiddleware`),
but its body may take up to `--http-body-timeout` (60 s) to follow, and a snapshot upload minutes.
A token revoked meanwhile (token file and SIGHUP) let the write be made all the same, by a token no
longer in force. Each write route calls `refuse_if_revoked` once its body is in, before it changes
anything.
"""

from __future__ import annotations

from starlette.types import Scope

from fleetmap.api.errors import ApiError
from fleetmap.auth import CHALLENGE, revoked_during


def refuse_if_revoked(scope: Scope) -> None:
    """Raise a 401 (`WWW-Authenticate` as every 401's) if the request's token was revoked, or lost
    the role the request needed, since it was let in (`fleetmap.auth.revoked_during`); nothing
    otherwise, nor for a request let in without a token."""
    revoked = revoked_during(scope)
    if revoked is not None:
        raise ApiError(401, revoked, headers={"WWW-Authenticate": CHALLENGE})
