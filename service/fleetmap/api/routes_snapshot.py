"""A map as one file: download it for backup, upload it to restore or to move a map between servers."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from collections.abc import AsyncIterator, Callable
from typing import IO, Any

from fastapi import APIRouter, Request, Response
from fastapi.responses import StreamingResponse
from starlette.types import Receive, Scope, Send

from fleetmap.api.conditional import Conditions, Preconditions, tag_map
from fleetmap.api.errors import CLIENT_CLOSED_REQUEST, ApiError, error_responses, validation_detail
from fleetmap.api.http_semantics import created_status, is_head
from fleetmap.api.revocation import refuse_if_revoked
from fleetmap.api.state import MapId, Slots, State
from fleetmap.api.strict_requests import StrictRoute
from fleetmap.api_models import MapInfo, map_info
from fleetmap.config import MapConfig
from fleetmap.grid_map import GridMap
from fleetmap.map_entry import MapEntry
from fleetmap.memory_budget import UploadReservation
from fleetmap.registry import MapNotFound
from fleetmap.storage_format import (
    SNAPSHOT_FORMAT,
    SnapshotError,
    map_from_snapshot_file,
    write_snapshot_file,
)
from fleetmap.upload_spool import UploadStopped, check_stop, close_spool, spooled_file

router = APIRouter(tags=["maps"], route_class=StrictRoute)
log = logging.getLogger("fleetmap.api")

MEDIA_TYPE = "application/zip"


#: The request body of an upload of a zip file (OpenAPI), and the answer of an upload that replaced a
#: map: `PUT .../snapshot` and `PUT .../import`.
ZIP_UPLOAD = {
    "requestBody": {
        "required": True,
        "content": {MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}},
    }
}
REPLACED: dict[int | str, dict[str, Any]] = {
    200: {"model": MapInfo, "description": "Replaced the map that had this id"}
}
#: The errors of an upload: those of `install_upload`, and a 503 and a 507 that also say what the
#: temporary directory may do to the upload (`spooled_body`, `fleetmap.upload_spool.SpoolFailed`).
UPLOAD_ERRORS = error_responses(
    412, 413, 415, 422, 503, 507,
    described={
        503: "The server already holds its limit of uploads in progress, its temporary directory "
        "(TMPDIR) failed to write or read the upload (an I/O error of its disk), or the map was "
        "installed but could not be stored: retry later",
        507: "The service's memory budget for map tiles (--max-memory) is used up, or its temporary "
        "directory (TMPDIR) has no room for the upload",
    },
)  # fmt: skip

#: A snapshot upload's 415: its body is read as the snapshot whatever its Content-Type.
SNAPSHOT_UNSUPPORTED_MEDIA = (
    "The body was sent with a Content-Encoding (gzip, ...): send the file as it is. Its Content-Type "
    "is not checked (application/zip is its type): the body is read as a snapshot file either way"
)

#: Bytes of body gathered before they are written to the spool in one call on a worker thread (and
#: of a download read from its spool at a time).
_WRITE_BATCH = 1 << 20
#: Seconds between two looks at whether a download's client went away while its file is written.
_DISCONNECT_POLL_S = 0.2
#: Seconds an upload refused for the limit of uploads in progress is told to wait (`Retry-After`):
#: uploads take seconds (a big one a minute), so the default second would only make clients resend.
UPLOAD_RETRY_AFTER_SECONDS = 5


def _take_slot(slots: Slots, busy: str) -> None:
    """Take one of `slots` for a transfer, or refuse it with 503 and `Retry-After` ("the server
    already <busy>; retry later") when all are taken."""
    if not slots.acquire():
        raise ApiError(
            503,
            f"the server already {busy}; retry later",
            headers={"Retry-After": str(UPLOAD_RETRY_AFTER_SECONDS)},
        )


@contextlib.asynccontextmanager
async def spooled_body(request: Request, uploads: Slots) -> AsyncIterator[IO[bytes]]:
    """The request's body as a binary file (at its start; readable, seekable), which is not held in
    memory: streamed to a spool (`fleetmap.upload_spool`: in memory up to 16 MiB, then a file of the
    temporary directory). On leaving, whatever happened (an answer, a refusal, the client gone, the
    body's deadline, a cancelled task), the spool is closed and so its file removed. The body limit
    (`BodyLimitMiddleware`) applies as the body arrives: it counts what `receive` hands over, so a
    body past it raises `BodyTooLarge` (413) from here with no more of it read. `SpoolFailed` (507,
    or 503) if the temporary directory cannot take the body, or (from the reader) give it back.

    The upload takes one of `uploads` (`ApiSettings.max_uploads`) before a byte of its body is read,
    and gives it back with its spool: with none free it is refused with 503 and `Retry-After`, its
    body unread (a client that sent `Expect: 100-continue` has not sent it). The memory, disk and
    worker threads that uploads hold are so bounded by that limit, not by the HTTP connections.

    The writes run on a worker thread, a megabyte at a time: a write goes to the page cache and is
    quick, but once the disk falls behind (a 4 GiB upload from a fast network to a slow disk) the
    kernel holds the writer until writeback catches up, for up to hundreds of milliseconds a call,
    and on the event loop that would stall every other request and the ingest of scans meanwhile.
    Batching keeps the thread hops few (4096 for 4 GiB) and the memory held at a megabyte."""
    _take_slot(
        uploads, f"holds its limit of {uploads.limit} uploads in progress (snapshots and nav2 imports)"
    )
    spool = spooled_file()
    writing: asyncio.Future[int] | None = None  # a write of the spool, on a worker thread

    def done() -> None:
        close_spool(spool)
        uploads.release()

    try:
        pending: list[bytes] = []
        held = 0
        async for chunk in request.stream():
            pending.append(chunk)
            held += len(chunk)
            if held >= _WRITE_BATCH:
                # Off the loop: the spool's first write past its memory makes its file and copies
                # what it held there, and any write may wait on the disk.
                writing = asyncio.ensure_future(asyncio.to_thread(spool.write, b"".join(pending)))
                # Shielded: a cancelled request must not close the spool under a write still running
                # on its thread (the `finally` below waits for it instead).
                await asyncio.shield(writing)
                pending, held = [], 0
        if pending:
            writing = asyncio.ensure_future(asyncio.to_thread(spool.write, b"".join(pending)))
            await asyncio.shield(writing)
        spool.seek(0)
        yield spool
    finally:
        # A reader on a worker thread that outlives a cancelled request (the shutdown cutoff) finds
        # the spool closed: its next read raises ValueError there, its result is dropped anyway.
        if writing is not None and not writing.done():
            writing.add_done_callback(lambda _: done())
        else:
            done()


@router.get(
    "/maps/{map_id}/snapshot",
    summary="Download a map as one file",
    response_class=Response,
    responses={
        200: {
            "content": {MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}},
            "description": f"a {SNAPSHOT_FORMAT} zip: map.json (configuration) and tiles.npz (every layer)",
        },
        **error_responses(
            404,
            422,
            503,
            507,
            described={
                503: "The server already sends its limit of snapshot downloads, or its temporary "
                "directory (TMPDIR) failed to write or read the download (an I/O error of its disk): "
                "retry later",
                507: "The service's temporary directory (TMPDIR) has no room for the download",
            },
        ),
    },  # fmt: skip
)
async def get_snapshot(map_id: MapId, state: State, request: Request) -> Response:
    """The whole map (configuration and every tile of every layer) as one zip file, consistent: it
    is taken under the map's lock, between two scans. `PUT` it to this or another server to restore.
    The file is written to the service's temporary directory, then sent: 507 if that has no room for
    it, 503 if its disk fails; 503 (`Retry-After: 5`) if the server already sends its limit of
    downloads (4 by default). Nothing changes either way. A HEAD answers the headers without writing
    the file, so without its `Content-Length`, and takes no download slot."""
    entry = state.entry(map_id)
    disposition = f'attachment; filename="{map_id}.fleetmap.zip"'
    if is_head(request):
        # The file is made only to be sent: a HEAD (a script checking that the map is there, a
        # download manager's probe) wrote all of it (half a minute for a 4.46 GB map) and held one
        # of the download slots, to send nothing.
        head = Response(media_type=MEDIA_TYPE, headers={"Content-Disposition": disposition})
        del head.headers["Content-Length"]  # unknown until written: not the empty body's 0
        return head
    downloads = state.downloads
    _take_slot(downloads, f"sends its limit of {downloads.limit} snapshot downloads at once")
    spool = spooled_file("download")
    stop = threading.Event()
    writer = asyncio.ensure_future(asyncio.to_thread(_write_download, map_id, entry.gmap, spool, stop))

    def written(_: asyncio.Future[int]) -> None:
        if not writer.cancelled():
            writer.exception()  # retrieved: it is answered (or its client gone) already
        close_spool(spool)
        downloads.release()

    try:
        # A client that goes away while its file is written stops the writing at its next write: it
        # ran to the end (half a minute for a 4.46 GB map), holding the slot and a copy of the map,
        # so a client dropping 4 downloads as often as they were written kept the others at 503.
        while not (await asyncio.wait({writer}, timeout=_DISCONNECT_POLL_S))[0]:
            if await request.is_disconnected():
                stop.set()
        size = writer.result()
    except BaseException as exc:
        stop.set()  # cancelled too (the server stopping): the writer stops at its next write
        if writer.done():
            # It failed (no room: 507): closed now, before the answer. As a done callback it ran a
            # loop turn later, and a client reading the 507 could still find the file held open.
            written(writer)
        else:
            writer.add_done_callback(written)  # the spool is closed once the writer let go of it
        if isinstance(exc, UploadStopped):
            log.info(
                "the download of map %s stopped as it was written: its client went away", map_id,
                extra={"map_id": map_id},
            )  # fmt: skip
            raise ApiError(CLIENT_CLOSED_REQUEST, "the client went away") from None
        raise
    return _SpoolResponse(
        spool, downloads, media_type=MEDIA_TYPE,
        headers={"Content-Disposition": disposition, "Content-Length": str(size)},
    )  # fmt: skip


def _write_download(map_id: str, gmap: GridMap, spool: IO[bytes], stop: threading.Event) -> int:
    """The map's snapshot file written to `spool`, which is left at its start; its size. Raises
    `UploadStopped` at the first write after `stop` is set."""
    write_snapshot_file(map_id, gmap, _StoppableWrites(spool, stop))  # type: ignore[arg-type]
    size = spool.tell()
    spool.seek(0)
    return size


class _StoppableWrites:
    """A binary file whose writes raise `UploadStopped` once `stop` is set; anything else is the
    file's own."""

    def __init__(self, file: IO[bytes], stop: threading.Event) -> None:
        self._file, self._stop = file, stop

    def write(self, data: bytes) -> int:
        check_stop(self._stop)
        return self._file.write(data)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._file, name)


class _SpoolResponse(StreamingResponse):
    """A download sent from its spool, a megabyte at a time, each read on a worker thread (the spool
    may be on a slow disk). When the response ends, however it ends (sent, the client gone, the
    server stopping), the spool is closed, its file's room given back, and the download's slot
    released: here rather than in the generator, since a generator cancelled before its first step
    never runs its `finally`."""

    def __init__(self, spool: IO[bytes], slots: Slots, **kwargs: Any) -> None:
        async def chunks() -> AsyncIterator[bytes]:
            while chunk := await asyncio.to_thread(spool.read, _WRITE_BATCH):
                yield chunk

        super().__init__(chunks(), **kwargs)
        self._spool, self._slots = spool, slots

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            close_spool(self._spool)
            self._slots.release()


@router.put(
    "/maps/{map_id}/snapshot",
    summary="Restore a map from a snapshot file",
    response_model=MapInfo,
    status_code=201,
    openapi_extra=ZIP_UPLOAD,
    responses={
        **REPLACED,
        **UPLOAD_ERRORS,
        # Its own: the shared sentence says a zip must come as application/zip, as an import's must,
        # but a snapshot is read from its bytes whatever its Content-Type (`curl -T` sends none).
        **error_responses(415, described={415: SNAPSHOT_UNSUPPORTED_MEDIA}),
    },
)
async def put_snapshot(
    map_id: MapId, request: Request, response: Response, state: State, conditions: Conditions
) -> MapInfo:
    """Replace map `map_id` (201 with its `Location` when it did not exist, else 200) with the map in
    the uploaded snapshot file, durably: the answer comes once it is stored. Its robots' statistics
    start afresh; scans queued for the old map are dropped. 422 if the body is not a fleetmap
    snapshot, or holds a tile or a cell value the service could not have made; 413 if a part of it
    decompresses to more than its limit (see the docs); 507 if its tiles need more memory than the
    budget (`--max-memory`) leaves, or if the service's temporary directory has no room for the
    upload (it is kept there, not in memory, while it is read); 503 naming that directory if its
    disk fails to write or read the upload (an I/O error: the server's fault, logged, never the
    body's); 503 (`Retry-After: 5`), before the body is read, if the server already holds its limit
    of uploads in progress (4 by default); none changes anything. 503 if the map was installed but
    could not be stored. `If-Match` / `If-None-Match: *` as for `PUT /maps/{map_id}` (412, nothing
    changed; before the body is read)."""

    def read(
        body: IO[bytes],
        _config: MapConfig | None,
        reservation: UploadReservation | None,
        stop: threading.Event,
    ) -> GridMap:
        return map_from_snapshot_file(
            body, max_bytes=state.snapshot_tile_bytes, reservation=reservation, stop=stop
        )

    try:
        return await install_upload(state, map_id, request, response, read, conditions)
    except SnapshotError as exc:
        if not exc.errors:
            raise ApiError(exc.status, str(exc)) from None
        detail, items = validation_detail(exc.errors)  # one line per problem, as for PUT /maps
        raise ApiError(exc.status, f"snapshot {detail}", errors=items) from None


async def install_upload(
    state: State,
    map_id: str,
    request: Request,
    response: Response,
    read: Callable[[IO[bytes], MapConfig | None, UploadReservation | None, threading.Event], GridMap],
    conditions: Preconditions,
    *,
    reads_config: bool = False,
) -> MapInfo:
    """Install the map an upload holds as map `map_id`, replacing any map of that id, durably: what
    `PUT .../snapshot` and `PUT .../import` share. The request's body goes to a spool
    (`spooled_body`, one of the uploads in progress); `read(body, config, reservation, stop)` makes
    the map from it on a worker thread, with the configuration of the map it replaces (None for a
    new id), charging it to the upload's room in the memory budget (`MapRegistry.upload_reservation`;
    None without a budget) before it allocates the tiles, and stopping (`spool.UploadStopped`) soon
    after `stop` is set, which it is when the request ends before the reader does; whatever it
    raises for a bad upload (a 507 when the budget has no room) propagates with nothing changed,
    and the room is given back. `reads_config`: the map `read` makes depends on that configuration
    (a nav2 import's does), so it is installed only where it is what reading it for the map there
    then makes: over a map of its configuration, or over none if it was read for none; else 409,
    nothing changed (the map deleted, created or replaced by another meanwhile).
    Sets 201 (with `Location`) for a new map, else 200; NotDurable (503) if the map was installed
    but could not be stored. `conditions` (the request's If-Match / If-None-Match) are checked
    before the body is read, sparing a doomed upload its transfer (gigabytes, for a big map) and
    its spool, again once it is in, and last where the map is installed, under the registry's
    lock, so that of two uploads sent with the same ETag one is installed and the other gets 412.
    401, nothing changed, if the request's token was revoked (or demoted) while the upload was read
    (`refuse_if_revoked`)."""

    def current() -> MapEntry | None:
        with contextlib.suppress(MapNotFound):
            return state.registry.get(map_id)
        return None

    conditions.check(map_id, current())
    async with spooled_body(request, state.uploads) as body:
        # Again: the map may have changed while the body came (minutes, for a big one); the reader
        # takes the configuration of the map there now, and its bytes are the ones lent.
        replaced = current()
        conditions.check(map_id, replaced)
        config = None if replaced is None else replaced.gmap.config
        # Held from the reader's check of the map's size until it is installed, so that uploads
        # read together (and scans meanwhile) cannot each take the same free bytes; given back on
        # every other way out, a cancelled request's too.
        with state.registry.upload_reservation(replaced) as reservation:
            stop = threading.Event()
            try:
                gmap = await asyncio.to_thread(read, body, config, reservation, stop)
            finally:
                # A request cancelled while its reader runs (the shutdown's cutoff) does not wait for
                # it: the reader stops at its next chunk rather than decompress on to 4 GiB into the
                # temporary directory, for the process's exit to wait for (asyncio joins its threads).
                stop.set()
            refuse_if_revoked(request.scope)
            read_with = config if reads_config else ANY_CONFIG
            return await _install(state, map_id, request, response, gmap, conditions, reservation, read_with)


#: `_install`'s `read_with` for an upload that holds its own configuration (a snapshot): it replaces
#: whatever map is there when it is installed.
ANY_CONFIG = object()


def read_for_the_map_there(
    read_with: MapConfig | None | object, there: MapConfig | None, made: MapConfig
) -> bool:
    """Whether a map `made` from an upload read for the configuration `read_with` (None: for no map;
    `ANY_CONFIG`: an upload of its own configuration) is what reading it for the map there now
    (of configuration `there`, None: none) would make: read for none and none there, or a map of
    the same configuration there (`MapConfig.same_map_as`: its layers in any order, a preset as its
    values; compared with `!=`, a map replaced meanwhile by one of its very configuration, its
    layers listed in another order, had the import refused 409)."""
    if read_with is ANY_CONFIG:
        return True
    if there is None:
        return read_with is None
    return there.same_map_as(made)


async def _install(
    state: State,
    map_id: str,
    request: Request,
    response: Response,
    gmap: GridMap,
    conditions: Preconditions,
    reservation: UploadReservation | None,
    read_with: MapConfig | None | object,
) -> MapInfo:
    """`install_upload`'s last step: replace map `map_id` with the upload's map `gmap`, durably. Unless
    `read_with` is `ANY_CONFIG`, `gmap` was read for that configuration of the map there (None: no
    map), and is installed only over a map of its own configuration, or over none if read for none
    (else 409): what reading it again for the map there now would make."""
    # Whether a map was replaced is known only where it is, under the registry's lock: the map
    # looked up before the upload was read (seconds, for a big one), may have been created,
    # deleted or replaced by another writer since, and a 201 Created for an upload that replaced
    # another writer's map (or a 200 for one that found none) misinformed the client.
    check = conditions.expectation(map_id)
    found: list[MapEntry | None] = []

    def expect(old: MapEntry | None) -> None:
        if check is not None:
            check(old)
        # A nav2 import is read with the configuration of the map there when its body was in: a
        # map made or replaced by another writer since (at another resolution, say) was replaced
        # by a map of a configuration no longer there, a 200 where the import, sent after that
        # writer, would have been refused (another resolution) or made with that map's.
        if not read_for_the_map_there(read_with, None if old is None else old.gmap.config, gmap.config):
            raise ApiError(
                409,
                f"map {map_id!r} was deleted, created or replaced while the upload was read (with the "
                "configuration of the map there before): nothing changed; send it again",
            )
        found.append(old)

    # On a worker thread: storing a big map's tiles takes seconds (the event loop serves on).
    try:
        entry = await asyncio.to_thread(
            state.registry.replace, map_id, gmap, wait=True, expect=expect, reservation=reservation
        )
    except ApiError:  # a precondition failed: the old map is untouched, its tiles still good
        raise
    except BaseException:  # also when it could not be stored: the old map's tiles are gone all the same
        state.tiles.drop_map(map_id)
        raise
    state.tiles.drop_map(map_id)
    created_status(request, response, map_id, created=found[-1] is None)
    tag_map(response, entry)
    return map_info(entry, state.registry.lock)
