"""A request's path as the service's routes name it, and the prefix the service is served under.

Behind a reverse proxy that serves the service under a path (`fleetmap serve --root-path /fleetmap`
for https://host/fleetmap/, the proxy stripping the prefix), uvicorn puts the prefix back before each
request's path, as ASGI says (its `root_path`, the path's start): a request for `/maps/a` arrives as
`/fleetmap/maps/a` with root path `/fleetmap`. Starlette's routes match the path without the root
path; everything else that looks at a request's path (the middlewares: roles, viewer files, event
streams, HEAD, metrics) does it with `route_path`, and everything that names a URL of the service to
a client (a 201's `Location`, the session cookie's `Path`) puts `root_path` before it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the REST client imports `auth`, which uses this module, and loads no Starlette
    from starlette.types import Scope


def root_path(scope: Scope) -> str:
    """The path the service is served under (`--root-path`), without a trailing `/`: `""` at the root.
    The app's own, also in the scope of a mount (the viewer's files), whose `root_path` ends with the
    mount's prefix."""
    root: str = scope.get("app_root_path", scope.get("root_path", ""))
    return root.rstrip("/")


def route_path(scope: Scope) -> str:
    """The request's path as the routes name it (`/maps/a`): its path without the root path, or as it
    is when it does not start with it (an app called without uvicorn's root path)."""
    path: str = scope["path"]
    below = path_below(path, root_path(scope))
    return path if below is None else below


def path_below(path: str, root: str) -> str | None:
    """`path` without its start `root` (`/fleetmap/maps` below `/fleetmap`: `/maps`; `/fleetmap`:
    `/`), or None when it does not start with that path (`/fleetmapx`) or `root` is `""`."""
    if root and (path == root or path.startswith(root + "/")):
        return path[len(root) :] or "/"
    return None
