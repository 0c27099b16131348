"""Ingest before reads: new HTTP requests wait while scans wait.

The service is one Python process. Integration workers plan and apply scans in compiled code, but
they need the GIL between those calls, and every HTTP request served needs it (and a core) too. Under
heavy read load (thousands of cached tiles per second, large cell queries) the workers fell so far
behind that the per-robot queues overflowed and scans were dropped (docs/benchmark-history.md, "Why
reads starved ingest, and what fixed it").

`IngestPriority` is a pure ASGI middleware in front of the app. When a request arrives while the
oldest scan waiting for integration has waited longer than `IngestGate.threshold` seconds, the
request waits before anything of it is read or run: the event loop sleeps (it holds no GIL and uses
no CPU), and the workers catch up. One watcher task checks the backlog every `poll` seconds while
requests wait and lets all of them through, in arrival order, as soon as the backlog is back under
the threshold; a request never waits longer than `max_wait` seconds, after which it is served anyway
(counted as a timeout). Requests already being served are not interrupted, and an idle or keeping-up
service never delays anything: the check is one short look at the ingest queue.

Never delayed: `GET /healthz` and `GET /metrics` (monitoring must see a backlog, not wait for it),
`POST /maps/{id}/scans` (ingest itself), and non-HTTP scopes (lifespan).
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable

from starlette.types import ASGIApp, Receive, Scope, Send

from fleetmap.route_path import route_path

#: Seconds between two looks at the backlog while requests wait.
POLL_SECONDS = 0.002

#: Paths never delayed.
EXEMPT_PATHS = frozenset({"/healthz", "/metrics"})


class IngestGate:
    """When requests may go on: the threshold, the waiting requests and the counters (for /metrics).

    `backlog()` returns the seconds the oldest scan waiting for integration has waited (0 when none
    waits); it is called on the event loop, so it must be quick and must not block. A `threshold` of
    0 or less switches the gate off. Used from one event loop only."""

    def __init__(
        self,
        backlog: Callable[[], float],
        threshold: float,
        max_wait: float,
        poll: float = POLL_SECONDS,
    ) -> None:
        self.backlog = backlog
        self.threshold = threshold
        self.max_wait = max_wait
        self.poll = poll
        #: Requests that waited, their total wait in seconds, and those let through by `max_wait`.
        self.delayed = 0
        self.delay_seconds = 0.0
        self.timeouts = 0
        # (deadline, future) in arrival order; the deadlines are in the same order (one max_wait).
        self._waiting: deque[tuple[float, asyncio.Future[bool]]] = deque()
        self._watcher: asyncio.Task[None] | None = None

    @property
    def enabled(self) -> bool:
        return self.threshold > 0

    @property
    def waiting(self) -> int:
        """Requests waiting now."""
        return len(self._waiting)

    async def admit(self) -> float:
        """Return at once unless scans are backed up (or requests already wait: no overtaking);
        else wait until the backlog is under the threshold or `max_wait` has passed. Returns the
        seconds waited."""
        if not self.enabled or (not self._waiting and self.backlog() <= self.threshold):
            return 0.0
        loop = asyncio.get_running_loop()
        started = loop.time()
        future: asyncio.Future[bool] = loop.create_future()
        self._waiting.append((started + self.max_wait, future))
        if self._watcher is None or self._watcher.done():
            self._watcher = loop.create_task(self._watch())
        timed_out = await future
        waited = loop.time() - started
        self.delayed += 1
        self.delay_seconds += waited
        if timed_out:
            self.timeouts += 1
        return waited

    async def _watch(self) -> None:
        loop = asyncio.get_running_loop()
        while self._waiting:
            await asyncio.sleep(self.poll)
            if self.backlog() <= self.threshold:
                while self._waiting:
                    _release(self._waiting.popleft()[1], False)
                return
            now = loop.time()
            while self._waiting and self._waiting[0][0] <= now:
                _release(self._waiting.popleft()[1], True)


def _release(future: asyncio.Future[bool], timed_out: bool) -> None:
    if not future.done():  # a request cancelled while it waited
        future.set_result(timed_out)


def is_exempt(scope: Scope) -> bool:
    """Requests the gate never delays: health, metrics and scans posted over HTTP."""
    path = route_path(scope)
    if path in EXEMPT_PATHS:
        return True
    return scope.get("method") == "POST" and path.startswith("/maps/") and path.endswith("/scans")


class IngestPriority:
    """ASGI middleware: HTTP requests pass `gate.admit()` first (see the module's docstring)."""

    def __init__(self, app: ASGIApp, gate: IngestGate) -> None:
        self.app = app
        self.gate = gate

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and self.gate.enabled and not is_exempt(scope):
            await self.gate.admit()
        await self.app(scope, receive, send)
