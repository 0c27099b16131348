"""CORS (`fleetmap serve --cors-origin ORIGIN ...`): which pages served elsewhere may call the API from
a browser, as docs/security.md says. Starlette's `CORSMiddleware` does the work; `JsonCORS` only
makes its refusal of a preflight an error answer like every other, JSON with a `detail` naming what
was refused. Starlette answered it with the plain text `Disallowed CORS origin`, the one error of
the API that was not JSON (docs/api.md, "Errors": every error answer is JSON with a `detail`).
"""

from __future__ import annotations

from fastapi.middleware.cors import CORSMiddleware
from starlette.datastructures import Headers
from starlette.responses import Response

from fleetmap.api.errors import error_answer


class JsonCORS(CORSMiddleware):
    """Starlette's CORS middleware whose refused preflight (400) is the API's JSON error: `{"detail":
    "CORS preflight refused: ..."}`, naming the origin, method, headers or private-network access
    refused, with the headers Starlette gave it (`Vary`, the allowed methods, ...)."""

    def preflight_response(self, request_headers: Headers) -> Response:
        answer = super().preflight_response(request_headers)
        if answer.status_code != 400:
            return answer
        detail = "CORS preflight refused: " + "; ".join(self._refusals(request_headers))
        headers = {
            name: value
            for name, value in answer.headers.items()
            # error_answer sets its own body's length and type.
            if name not in ("content-length", "content-type")
        }
        return error_answer(400, detail, headers=headers)

    def _refusals(self, request_headers: Headers) -> list[str]:
        """What of the preflight is not allowed, each as a sentence, in the order Starlette checks."""
        refusals = []
        origin = request_headers["origin"]
        if not self.is_allowed_origin(origin=origin):
            refusals.append(f"the origin {origin!r} is not allowed (fleetmap serve --cors-origin)")
        method = request_headers["access-control-request-method"]
        if method not in self.allow_methods:
            refusals.append(f"the method {method!r} is not allowed (only {', '.join(self.allow_methods)})")
        requested = request_headers.get("access-control-request-headers")
        if requested is not None and not self.allow_all_headers:
            names = [name.strip() for name in requested.lower().split(",")]
            refused = [name for name in names if name not in self.allow_headers]
            if refused:
                refusals.append(f"the headers {', '.join(refused)} are not allowed")
        private = request_headers.get("access-control-request-private-network") is not None
        if private and not self.allow_private_network:
            refusals.append("access from a public page to a private network is not allowed")
        return refusals or ["not allowed"]
