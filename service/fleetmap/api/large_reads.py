"""Reads of big windows (`GET /maps/{id}/region`, `/surface`, `/export`), at most a few at once.

Each read is bounded (`max_region_cells`, `max_export_cells`), but not how many run together. A
region of 16 Mi cells holds about 450 MB while it is made (the window, the probability's float64
steps, its npy bytes), then its answer (64 MB as npy, more as PNG being encoded) until the client
has read it. The routes run on the thread pool (40 workers), and a client that reads slowly keeps
its answer for up to the send timeout (60 s): eight such requests at once held 3.2 GB more, and a
script sending a few dozen could hold more memory than the machine has. So a read of more than
`LARGE_READ_CELLS` cells takes one of `ApiState.large_reads` (`ApiSettings.max_large_reads`) from
its window's check until its answer is sent, and past the limit is refused with 503 (and
`Retry-After`) before anything is read; smaller windows, as viewers and most programs ask for,
never wait for one.
"""

from __future__ import annotations

import asyncio
from types import TracebackType
from typing import Any

from fastapi import Response
from starlette.types import Receive, Scope, Send

from fleetmap.api.errors import ApiError
from fleetmap.api.state import ThreadSlots

#: Cells of a window past which a read is big (the most a JSON region may hold, 4 MiB as npy).
LARGE_READ_CELLS = 1 << 20


class LargeRead:
    """A window read, holding one of the big reads' slots when it is big (`large_read`). Used as a
    context manager around making the answer: `answer` hands the slot to the answer, which gives it
    back once sent; leaving without one (an error) gives it back at once."""

    def __init__(self, slots: ThreadSlots | None) -> None:
        self._slots = slots

    def answer(self, content: bytes | str, **kwargs: Any) -> Response:
        """The read's answer (as `Response(content, **kwargs)`), which holds the read's slot until it
        has been sent, or has failed to be."""
        slots, self._slots = self._slots, None
        return Response(content, **kwargs) if slots is None else _HeldResponse(content, slots, **kwargs)

    def __enter__(self) -> LargeRead:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        if self._slots is not None:  # no answer took it
            self._slots.release()
            self._slots = None


def large_read(reads: ThreadSlots, cells: int) -> LargeRead:
    """The read of a window of `cells` cells: one of `reads` taken if it is big (more than
    `LARGE_READ_CELLS`), else none. ApiError 503 when all are taken: nothing was read."""
    if cells <= LARGE_READ_CELLS:
        return LargeRead(None)
    if not reads.acquire():
        raise ApiError(
            503,
            f"the server already reads its limit of {reads.limit} windows of more than {LARGE_READ_CELLS} "
            "cells at once; retry later, or read smaller windows",
        )
    return LargeRead(reads)


#: Bytes of a big read's answer handed to the server at a time (`_HeldResponse`).
SEND_BYTES = 1 << 20


class _HeldResponse(Response):
    """An answer that gives back its read's slot once it has been sent, however that ended (sent,
    the client gone, the server stopping): in `__call__`, since a background task does not run when
    sending fails. It hands its body to the server a megabyte at a time: the server takes a whole
    body at once into its own buffer whatever the client reads, so a body sent whole let its slot go
    with 64 MB still held for a client that read nothing. Piece by piece, each waits for the client to
    have read most of the one before, and a client gone is noticed at the next piece. A body of at
    most a megabyte goes whole, as any answer's."""

    def __init__(self, content: bytes | str, slots: ThreadSlots, **kwargs: Any) -> None:
        super().__init__(content, **kwargs)
        self._slots = slots

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await send(
                {"type": "http.response.start", "status": self.status_code, "headers": self.raw_headers}
            )
            body = memoryview(self.body)
            for at in range(0, max(len(body), 1), SEND_BYTES):
                more = at + SEND_BYTES < len(body)
                await send(
                    {
                        "type": "http.response.body",
                        "body": bytes(body[at : at + SEND_BYTES]),
                        "more_body": more,
                    }
                )
                # The server takes a piece without waiting while its write buffer has room, and a
                # client gone (a reset) makes the socket refuse every piece at once, so the buffer
                # never fills: the answer ran on to its end without the event loop running the
                # connection's loss (after which the server drops what is sent), and asyncio logged
                # "socket.send() raised exception." for each piece past the fifth. Letting the loop
                # run between pieces has the server drop the rest.
                await asyncio.sleep(0)
        finally:
            self._slots.release()
