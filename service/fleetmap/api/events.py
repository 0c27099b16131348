"""`GET /maps/{map_id}/events`: server-sent events of a map's changed tiles and robots, for live clients.

Each stream polls the map's change feed and robots every `ApiSettings.events_period` (100 ms), so
whatever the ingest rate, a client gets at most one `tiles` and one `robots` event per period, each
covering everything since the previous one. Polling a version number is cheap, and it keeps the
integration workers free of any per-client work.

Format (text/event-stream):

    retry: 1000

    id: 41

    id: 42
    event: tiles
    data: {"version": 42, "tiles": [[0, 0, 256, 256], [256, 0, 512, 256]]}

    event: robots
    data: {"robots": {"r1": {"online": true, "pose": [1.0, 2.0, 0.5], "trail": [[0.9, 2.0], ...],
           "scans_integrated": 17}}}

    event: robots_delta                       (only with ?robots=delta)
    data: {"trail_length": 100, "robots": {"r1": {"online": true, "pose": [1.1, 2.0, 0.5],
           "trail": [[1.0, 2.0]], "scans_integrated": 18}}, "removed": ["r7"]}

    : keepalive

- `id:` alone, once when the stream opens: the change version it starts from (the `since` it
  resumes after, else the map's version now), which an EventSource keeps as its last event id
  without dispatching anything, so a client that loses the stream before any `tiles` event still
  resumes from there (`Last-Event-ID`) instead of from its reconnection, missing what changed.
- `tiles`: cell windows `[i0, j0, i1, j1]` of the storage tiles changed since the last event (refetch
  the web tiles that overlap them; the streams of a map share their events, `tiles_event`, so one
  may name a few tiles the previous one did too), or `{"version": v, "reset": true}`: too much
  changed to list, reload everything. Its `id` is the map's change version: a reconnecting
  EventSource sends it back as `Last-Event-ID` (or pass `?since=`) and gets the changes it missed.
  An id from an earlier map of the id, or from before the service restarted, is outside the map's
  versions (`ChangeFeed`): reset.
- `robots`: every robot of the map with its last 100 trail points, sent when anything in it changed
  (and once on connect).
- `robots_delta`, only on a stream opened with `?robots=delta`: after that stream's first `robots`
  event (on connect, and after each `replaced`), what changed since its previous robots event: the
  robots created or changed (all their fields as now, but in `trail` only the points appended
  since) and the ids of the robots forgotten (`removed`, applied first). Appended to the trail and
  cut to its last `trail_length` points, they give what a `robots` event would have said
  (`RobotsEvent.apply`). 100 robots moving at 2 Hz with full trails make the full event ~150 kB,
  ten times a second per viewer; their deltas are ~3 kB (docs/benchmarks.md, "Web viewer").

  Why opt-in, and why another event name: a client that does not know deltas (an older viewer, a
  script reading `robots`) must keep getting full events, and it does: without the parameter the
  stream is as it was. A new event name (sent to every stream besides the full `robots`) would keep
  old clients right too, but then every stream would carry both, costing more, not less. And a
  client that asked for deltas never mistakes one for the full list (which would remove every
  robot it omits), because a delta is never called `robots`.
- `replaced`: `{"id": map_id, "version": v}`, with `id: v`: the map was replaced under its id by
  `PUT /maps/{map_id}/snapshot` or `PUT /maps/{map_id}/import` (new configuration, cells and
  robots; change versions start again). Reload the map's metadata and every tile. The stream goes
  on with the new map's events (a `robots` event follows at once), and `v` is its change version,
  so a reconnect resumes from it.
- `deleted`: the map was deleted; the stream ends. (Also when it was deleted and created again
  between two polls: it is another map, which a client must select anew.)
- `: keepalive` comment lines after 15 s without anything sent (`ApiSettings.keepalive`, `fleetmap
  serve --events-keepalive`) keep proxies from closing an idle stream, and tell a client that a
  stream silent for several such periods is dead (a half-open connection): the Python client
  resumes it after 45 s of silence. A browser's EventSource never shows comments to the page, so a
  stream opened with `?keepalive=event` gets `keepalive` events instead (`{"interval": 15.0}`), and
  one at once when it opens: the web viewer reopens a stream that sent nothing for three intervals.
- `: the server is shutting down`, the last line of every open stream when the service stops
  (`EventStreamSlots.close_all`); the response then ends cleanly.
- `: the token of this stream was revoked`, the last line of a stream opened with a token (its
  `Authorization: Bearer` header, or a browser's session cookie standing for it) once that token is
  revoked, or demoted below the role reading needs (token file and SIGHUP): the stream ends within
  one poll, as a new request with the token would be refused (`fleetmap.auth.Grant`). An EventSource
  then reconnects, gets 401, and the web viewer asks for a token again. Only streams a token let in
  end: where reading is open (no `--require-read-token`), no token is checked, and none is revoked.

Streams are capped (`ApiSettings.max_event_streams`, 256 by default; `fleetmap serve
--max-event-streams`): each open stream holds a task, its buffers and a poll every 100 ms, so without
a cap anyone who can read could open thousands (9,000 held a whole core and 1 GB, and made ingest 30
times slower). Past the cap a new stream is refused with 503 and `Retry-After`. The web viewer tries
again by itself; a plain EventSource does not (a browser closes it for good on an answer other than
200): reopen it after `Retry-After`.
"""

from __future__ import annotations

import asyncio
import json
import time
import weakref
from collections.abc import AsyncIterator
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Header, Query, Request
from fastapi.responses import StreamingResponse
from starlette.types import Receive, Scope, Send

from fleetmap.api.errors import ApiError, error_responses
from fleetmap.api.robots_feed import RobotsFeed
from fleetmap.api.state import ApiState, EventStreamSlots, MapId, State
from fleetmap.api.strict_requests import StrictRoute
from fleetmap.api_models import KeepaliveEvent, ReplacedEvent, TilesEvent, tile_windows
from fleetmap.auth import GRANT_SCOPE_KEY, Grant
from fleetmap.change_feed import ChangeFeed
from fleetmap.map_entry import MapEntry

router = APIRouter(route_class=StrictRoute)

#: Seconds a client refused for the stream cap is told to wait (`Retry-After`).
RETRY_AFTER_SECONDS = 5


class _SlotStreamingResponse(StreamingResponse):
    """A StreamingResponse that gives its stream's slot back when the response ends, however it ends
    (the client went away, the map was deleted, the server shuts down). Released here rather than in
    the generator: a generator cancelled before its first step never runs its `finally`."""

    def __init__(self, slots: EventStreamSlots, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._slots = slots

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self._slots.release()


def _event(kind: str, data: str, event_id: int | None = None) -> str:
    head = f"id: {event_id}\n" if event_id is not None else ""
    return f"{head}event: {kind}\ndata: {data}\n\n"


def _successor(maps: dict[str, MapEntry], entry: MapEntry) -> MapEntry | None:
    """What became of `entry` (call under the registry lock): itself while it is the map; the map
    that replaced it, however many replacements ago, while that is the map; None once it is gone
    (deleted, or deleted and created again: a new map, not a replacement)."""
    current = maps.get(entry.id)
    follow: MapEntry | None = entry
    while follow is not None and follow is not current:
        follow = follow.replaced_by
    return follow


#: Per change feed, the last `tiles` event a stream made of it for the others to share: (from version,
#: to version, its data, when it was made: `time.monotonic()`). Only the event loop reads and writes
#: it, and `_fronts`.
_last_tiles: weakref.WeakKeyDictionary[ChangeFeed, tuple[int, int, str, float]] = weakref.WeakKeyDictionary()
#: Per change feed, the newest version one of its streams stands at (it sent everything up to it, or
#: started from it): no stream of the map is ahead of it.
_fronts: weakref.WeakKeyDictionary[ChangeFeed, int] = weakref.WeakKeyDictionary()

#: Seconds for which the last shared event shows where the streams in step stand. They poll every
#: `ApiSettings.events_period` (0.1 s), and each change makes one; an older one dates from before a
#: quiet spell, or from before the map's viewers last left, and says nothing of the streams now.
SHARED_EVENT_CURRENT_FOR = 1.0


def tiles_event(feed: ChangeFeed, version: int, tile_size: int) -> tuple[int, str | None]:
    """`(new version, the data of the tiles event to send or None)` for a stream of `feed` that has
    sent everything up to `version`.

    The streams of a map share their events: a stream whose version lies within the last event any
    stream made (from `a` to `b`, a <= version < b) sends that one and goes on from `b`. It may name
    tiles it was told of already (those changed in `(a, version]`): a viewer then asks for them again
    and gets 304s. Each stream made its own before, the same work once per viewer: 100 streams of a
    map that 200 robots change took 73 ms of the event loop per 100 ms poll. A stream behind or ahead
    of that event makes its own, which the others then share: streams fall into step within a poll.
    A version bump that changed no tile is not news (None).

    An event is left for sharing only when it starts where the streams in step could be: at or past
    every stream's version (`_fronts`), or, while the last shared event is current (made within
    `SHARED_EVENT_CURRENT_FOR`), no earlier than its start. Else it is its stream's alone: made by a
    stream resuming from an old version, shared, it told every stream in step of everything changed
    since that version, and every viewer of the map asked again for every one of those tiles."""
    last = _last_tiles.get(feed)
    if last is not None and last[0] <= version < last[1]:
        return last[1], last[2]
    front = _fronts.get(feed, version)  # (a feed's first stream stands at the front)
    batch = feed.since(version)
    _fronts[feed] = max(front, batch.version)
    if batch.version == version:
        return version, None
    if batch.reset:
        return batch.version, TilesEvent(version=batch.version, reset=True).model_dump_json(exclude_none=True)
    if not batch.tiles:
        return batch.version, None
    data = TilesEvent(version=batch.version, tiles=tile_windows(batch.tiles, tile_size)).model_dump_json(
        exclude_none=True
    )
    now = time.monotonic()
    # Behind the front, the shared event's start tells whether this stream is nearly in step: streams
    # that poll in step but a scan apart share the next one, and so fall into step. Not once it is
    # old: a viewer resuming with a `Last-Event-ID` from the evening found the evening's shared event
    # there, started after it, and its event of the night's changes went to a viewer opened in the
    # morning, in step, which had loaded those tiles fresh.
    current = last is not None and now - last[3] <= SHARED_EVENT_CURRENT_FOR and version >= last[0]
    if version >= front or current:
        _last_tiles[feed] = (version, batch.version, data, now)
    return batch.version, data


#: The last line of a stream whose token was revoked.
REVOKED = ": the token of this stream was revoked\n\n"


async def event_stream(
    state: ApiState,
    entry: MapEntry,
    since: int | None,
    robot_deltas: bool = False,
    grant: Grant | None = None,
    keepalive_events: bool = False,
) -> AsyncIterator[str]:
    """The events of one client until it disconnects (Starlette then cancels this generator), the
    map is deleted, or the token that let the stream in (`grant`; None: no token was needed) is no
    longer valid. A map replaced under its id is followed: `replaced`, then the new map's events.
    `robot_deltas` (`?robots=delta`): after the first `robots` event of a map, `robots_delta` events.
    `keepalive_events` (`?keepalive=event`): keepalives as `keepalive` events, one at once, instead of
    comments."""
    registry, settings = state.registry, state.settings
    keepalive = (
        _event("keepalive", KeepaliveEvent(interval=settings.keepalive).model_dump_json())
        if keepalive_events
        else ": keepalive\n\n"
    )
    feed = entry.changes
    tile_size = entry.config.tile_size
    robots_feed = RobotsFeed(entry, registry.lock)
    successor: MapEntry | None = entry
    try:
        yield "retry: 1000\n\n"  # EventSource reconnects after 1 s
        if keepalive_events:
            # At once: the client learns the interval, and so when a silence means a dead stream.
            yield keepalive
        version = feed.version if since is None else since
        if since is not None and since > feed.version:
            # A version this map never had (the id is from a deleted or replaced map of the same name):
            # start over.
            yield _event(
                "tiles",
                TilesEvent(version=feed.version, reset=True).model_dump_json(exclude_none=True),
                feed.version,
            )
            version = feed.version
        else:
            # Where this stream starts, as an id without data (an EventSource takes it as its last
            # event id and dispatches nothing): a client whose connection drops before the first
            # `tiles` event resumes from here. Ids came only with `tiles` events, so one that left a
            # quiet map reconnected without `Last-Event-ID`, started from then, and never heard of
            # the tiles changed while it was away.
            yield f"id: {version}\n\n"
        last_sent = time.monotonic()
        while not state.event_streams.closing:
            if grant is not None and not grant.still_valid():
                # Revoked (token file and SIGHUP): the client could not open this stream now, so it
                # may not keep it either. Its reconnection gets the 401 that says why.
                yield REVOKED
                return
            with registry.lock:
                successor = _successor(registry.maps, entry)
            if successor is None:
                yield _event("deleted", json.dumps({"id": entry.id}))
                return
            if successor is not entry:
                # Replaced: the client reloads everything, so the new map's history is not news; its
                # version becomes the event id, so a reconnecting EventSource resumes in the new feed.
                entry, feed, tile_size = successor, successor.changes, successor.config.tile_size
                version = feed.version
                yield _event(
                    "replaced", ReplacedEvent(id=entry.id, version=version).model_dump_json(), version
                )
                robots_feed = RobotsFeed(entry, registry.lock)  # all the new map's robots, at once
                last_sent = time.monotonic()
            version, tiles = tiles_event(feed, version, tile_size)
            if tiles is not None:
                yield _event("tiles", tiles, version)
                last_sent = time.monotonic()
            # A feed that sent nothing yet sends every robot: a delta needs a base.
            if robot_deltas and robots_feed.version >= 0:
                delta = robots_feed.delta_json()
                if delta is not None:
                    yield _event("robots_delta", delta)
                    last_sent = time.monotonic()
            else:
                robots = robots_feed.full_json()
                if robots is not None:
                    yield _event("robots", robots)
                    last_sent = time.monotonic()
            if time.monotonic() - last_sent >= settings.keepalive:
                yield keepalive
                last_sent = time.monotonic()
            await asyncio.sleep(settings.events_period)
        # The server is shutting down (`EventStreamSlots.close_all`): end the stream, so that the
        # server need not wait for it. An EventSource reconnects by itself once the server is back.
        yield ": the server is shutting down\n\n"
    finally:
        # A stream that ends because its client went away is cancelled, and the CancelledError's
        # traceback keeps this generator's frame, locals included, in a reference cycle that only a
        # full garbage collection frees: of an idle service, none came within minutes. A deleted
        # map's tiles (its memory, and its share of --max-memory) stayed held while a viewer had
        # shown it. Unbound here, before the frame ends, they go with the map.
        del entry, feed, robots_feed, successor


#: Digits of the longest change version (an int64: microseconds since 1970, counted up).
_VERSION_DIGITS = 19


def last_event_version(header: str) -> int | None:
    """The change version a reconnecting EventSource sends back as `Last-Event-ID`, or None for a
    header that is no number (not an id this service sent: the stream starts from now).

    Only ASCII digits count: `str.isdigit` also accepts `²` (latin-1 byte 0xB2 of a header), which
    `int` refuses. A number longer than any version (`int` refuses more than 4300 digits) stands
    for one past them all, so the stream starts with a reset, as for any version the map never had.
    """
    text = header.strip()
    if not (text.isascii() and text.isdigit()):
        return None
    return int(text) if len(text) <= _VERSION_DIGITS else 10**_VERSION_DIGITS


@router.get(
    "/maps/{map_id}/events",
    tags=["events"],
    summary="Live changes of a map (server-sent events)",
    response_class=StreamingResponse,
    responses={
        200: {
            "content": {"text/event-stream": {"schema": {"type": "string"}}},
            "description": "An endless text/event-stream; see the description for the events",
        },
        **error_responses(404, 422, 503),
    },
)
async def get_events(
    request: Request,
    map_id: MapId,
    state: State,
    since: Annotated[int | None, Query(ge=0, description="resume after this change version")] = None,
    last_event_id: Annotated[str | None, Header(description="set by a reconnecting EventSource")] = None,
    robots: Annotated[
        Literal["full", "delta"],
        Query(description="`delta`: after a first full `robots` event, send what changed as `robots_delta`"),
    ] = "full",
    keepalive: Annotated[
        Literal["comment", "event"],
        Query(
            description="`event`: send keepalives as `keepalive` events (one at once, with the interval), "
            "which an EventSource shows to the page, instead of comments"
        ),
    ] = "comment",
) -> StreamingResponse:
    """Server-sent events, at most one `tiles` and one `robots` event per 100 ms:

    - `id: <version>` alone (no data), first: the change version the stream starts from, which an
      EventSource keeps as its last event id, so a client that loses the stream before any `tiles`
      event resumes from there;
    - `event: tiles`, `id: <version>`, data `{"version": int, "tiles": [[i0, j0, i1, j1], ...]}`: the
      cell windows of the storage tiles changed since the previous event (refetch the overlapping web
      tiles), or `{"version": int, "reset": true}`: reload everything;
    - `event: robots`, data `{"robots": {"<robot_id>": {"online", "pose": [x, y, theta] | null,
      "trail": [[x, y], ...], "scans_integrated"}}}`: sent on connect and whenever a robot changed;
    - with `?robots=delta`, after the first `robots` event (and the one after `replaced`):
      `event: robots_delta`, data `{"trail_length": int, "robots": {"<robot_id>": {...}},
      "removed": ["<robot_id>", ...]}`: the robots changed since the previous robots event, with only
      the trail points appended since, and the robots forgotten (see `RobotsDeltaEvent`);
    - `event: replaced`, `id: <version>`, data `{"id": map_id, "version": int}`: the map was replaced
      by `PUT /maps/{map_id}/snapshot` or `PUT /maps/{map_id}/import`; reload its metadata and
      every tile. The stream goes on with the new map's events (change versions start again at
      `version`);
    - `event: deleted`, data `{"id": map_id}`: the map was deleted, the stream ends;
    - `: keepalive` comments after 15 s without anything sent (`ApiSettings.keepalive`); with
      `?keepalive=event`, `event: keepalive`, data `{"interval": float}` instead, and one at once when
      the stream opens: a page (whose EventSource hides comments) that hears nothing for a few
      intervals knows the connection died silently, and reconnects;
    - `: the server is shutting down`: the service is stopping; the stream ends cleanly after it;
    - `: the token of this stream was revoked`: the token (bearer or session cookie) that opened the
      stream was revoked, or demoted below the role reading needs; the stream ends after it.

    A reconnecting EventSource sends `Last-Event-ID` (the last version it got) and receives what
    changed since; `?since=` does the same by hand (a `Last-Event-ID` that is a version wins over it:
    an EventSource opened with `?since=` sends both on a reconnect, the header being the later).
    Robots always start with a full `robots` event.

    503 (with `Retry-After`) when the server already holds its limit of open streams (256 by
    default) or is shutting down. A browser's EventSource closes for good on a 503 (it reconnects by
    itself only after a stream that ended): reopen it after `Retry-After`, as the web viewer does."""
    entry = state.entry(map_id)
    # `Last-Event-ID` wins over `?since=`: an EventSource opened with `?since=` sends that URL again on
    # every reconnect, with the id of the last event it got, which is later. Reading `since` first
    # replayed everything from it on each reconnect: a reset (reload every tile) once the map's log
    # no longer reached back to it, as it soon does on a busy map.
    resumed = None if last_event_id is None else last_event_version(last_event_id)
    if resumed is not None:
        since = resumed
    slots = state.event_streams
    if slots.closing or not slots.acquire():  # (no slot is taken while closing)
        why = (
            "is shutting down"
            if slots.closing
            else f"already holds its limit of {slots.limit} open event streams"
        )
        raise ApiError(
            503, f"the server {why}; retry later", headers={"Retry-After": str(RETRY_AFTER_SECONDS)}
        )
    return _SlotStreamingResponse(
        slots,
        # The token that let the stream in, if one had to (the auth middleware left it here).
        event_stream(
            state,
            entry,
            since,
            robot_deltas=robots == "delta",
            grant=request.scope.get(GRANT_SCOPE_KEY),
            keepalive_events=keepalive == "event",
        ),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
