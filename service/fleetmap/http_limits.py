"""Connection limits of `fleetmap serve`'s HTTP server: how many connections, and how long a client
may take to send a request.

uvicorn on its own closes a connection only when it has been idle for 5 s after a response: a client
that connects and sends nothing, or sends its request head or body a byte at a time ("slowloris"),
holds its connection, and a file descriptor, for ever. About a thousand such connections used up a
service's 1024 descriptors: robots could no longer connect over Zenoh, HTTP went unanswered, and
asyncio logged every refused accept with a traceback (300 MB of log in a minute). Nobody needs a
token to do that: a connection is only checked once its request head has arrived.

`bounded_http_protocol` returns uvicorn's httptools protocol with five limits:

- at most `max_connections` HTTP connections are open at once; the next one is answered with a
  JSON 503 and closed at once, so HTTP alone can never use up the descriptors Zenoh, SQLite and the
  snapshot files need (nor Zenoh's sessions those of HTTP: `zenoh_session_limit` bounds them);
- a request's head (request line and headers) must arrive within `head_timeout` seconds of the
  connection opening, or of the request's first byte on a kept-alive connection;
- its body must then arrive within `body_timeout` seconds, or it is answered with a JSON 408 naming
  the limit (`body_too_slow`) and the connection is closed as after a refused head: a big snapshot
  upload over a slow link, cut off without a word, left its client with "empty reply from server"
  and nothing saying which option to raise;
- a client must take what its answer sends: if it reads nothing for `send_timeout` seconds while
  the answer waits on it (the connection's write buffer full), the connection is dropped (reset, so
  that the kernel does not go on holding the unsent answer for the client); and the kernel drops an
  answer its client has taken nothing of for as long once the connection is closed
  (`unsent_answer_timeout`). A client
  that asked for a snapshot download and stopped reading, connection open, held one of the 4
  download slots (and the download's file in TMPDIR) for ever: four of them refused every download;
- its head may be at most MAX_HEAD_BYTES long: past it the answer is a JSON 414 (the request line
  alone is that long) or 431 (headers), and the connection is closed (after LINGER seconds at most
  of reading and dropping what the client still sends, so that it reads the answer, not a reset).
  Neither httptools nor uvicorn has such a limit: a 10 MB header was read whole (in memory) and
  answered 200.

Requests httptools cannot parse (a URL over 64 KiB, which its URL parser cannot index, or no HTTP at
all) get uvicorn's 400, but as JSON `{"detail": ...}` like every other error of the API rather than
uvicorn's text/plain (`send_400_response`): the same bytes on the wire otherwise, and the same close.
Like every answer of the app, these answers carry `Cache-Control: no-cache` and the security headers
(`COMMON_HEADERS`).

A request that asks to switch protocols (`Upgrade: h2c`, as `curl --http2` sends over http://) and
has a body is refused too, with a JSON 400 (`UPGRADE_WITH_BODY`), before it reaches the app: the
service speaks no other protocol, and httptools takes the bytes after such a head for the other
protocol's, so uvicorn handed the app the request without its body. `curl --http2 -X PUT -d
'{"resolution": 0.1}'` created a map of the default 0.05 m, answered 201; a scan was refused as
empty. Without a body there is nothing to lose: the request is answered over HTTP/1.1, its
`Upgrade` ignored (RFC 9110, 7.8), and nothing is logged (uvicorn warned of each, advising to
install a WebSocket library the service has no use for); what the client sent after it is read as
HTTP again (uvicorn dropped it: a request pipelined behind it was never answered).

uvicorn logs a warning for each request it refuses so ("Invalid HTTP request received.", also for
the 414 and 431 of a head that arrived whole): anyone can send
them, and a client looping on bad heads wrote 10 lines a second of one sentence. The protocol's
warnings go through a `RateLimitedLog`: each sentence at most once per LOG_INTERVAL, with the count
of those held back.

Besides, `fleetmap serve` has asyncio accept at most ACCEPT_BACKLOG connections per turn of the
event loop (uvicorn's default of 2048 let one burst take 2048 descriptors before any could be
refused), and rate-limits asyncio's complaints when descriptors do run out (`quiet_accept_errors`;
Python 3.11 logs one traceback per connection still waiting, 46,000 in 8 s).

A connection past a deadline is closed (after that 408 if it was its body's). Nothing limits how
long a response takes: an event stream, or a scan waiting for its integration, runs as long as it
needs once its request has arrived, as long as its client reads what it is sent.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import resource
import socket
import struct
import sys
from typing import Any, cast

from fleetmap.rate_limited_log import RateLimitedLog

log = logging.getLogger("fleetmap.http")

#: Seconds a refused request's connection is kept to read and drop what its client still sends
#: (`_refuse`), so that the client can read the refusal instead of a reset.
LINGER = 2.0
#: Connections asyncio accepts per turn of its loop, and the listening socket's queue: each holds a
#: descriptor until the next turn refuses it.
ACCEPT_BACKLOG = 100
#: Descriptors kept for everything but HTTP connections: Zenoh's links, SQLite, snapshot and log
#: files, the event loop's own (about 60 in all), and two turns of accepted connections not yet
#: refused or not yet closed (2 x ACCEPT_BACKLOG). `max_connections` is lowered to leave them.
RESERVED_DESCRIPTORS = 384
#: Seconds a connection refused for the limit is told to wait (`Retry-After`).
RETRY_AFTER_SECONDS = 5
#: asyncio's message when accept() fails for want of descriptors or memory.
ACCEPT_ERROR = "socket.accept() out of system resource"
#: Bytes a request's head (request line and headers) may have. httptools' URL parser indexes a URL
#: with 16 bits, so longer URLs failed anyway; browsers and proxies send far less (nginx: 8 KiB per
#: header line by default).
MAX_HEAD_BYTES = 64 * 1024


#: What every answer of the app carries whatever made it, and so these too: the default
#: `Cache-Control` (`fleetmap.api.http_semantics.DEFAULT_CACHE_CONTROL`; a 414 may be stored and
#: served again by a cache unless told otherwise, RFC 9110 15.5.15) and the security headers
#: (`fleetmap.api.security_headers.EVERY_ANSWER`). Spelled out, not imported: `fleetmap serve` loads
#: this module before, and without, the REST API; tests/test_http_exhaustion.py checks they match.
COMMON_HEADERS = (
    "cache-control: no-cache\r\nx-content-type-options: nosniff\r\nx-frame-options: DENY\r\n"
    "referrer-policy: no-referrer\r\n"
)


def error_response(status: int, reason: str, detail: str, headers: str = "") -> bytes:
    """The whole HTTP answer the protocol sends itself, before any request reaches the app: the
    API's JSON error shape `{"detail": ...}` and `COMMON_HEADERS`, then close (`headers`: extra
    CRLF-ended lines)."""
    body = json.dumps({"detail": detail}).encode()
    head = (
        f"HTTP/1.1 {status} {reason}\r\ncontent-type: application/json\r\n"
        f"content-length: {len(body)}\r\n{COMMON_HEADERS}{headers}connection: close\r\n\r\n"
    )
    return head.encode() + body


#: The answer to a connection past `max_connections`.
BUSY_RESPONSE = error_response(
    503, "Service Unavailable", "the server holds too many HTTP connections; retry later",
    f"retry-after: {RETRY_AFTER_SECONDS}\r\n",
)  # fmt: skip
INVALID_REQUEST = error_response(400, "Bad Request", "invalid HTTP request: it could not be parsed")
URL_TOO_LONG = error_response(
    414, "URI Too Long", f"the request line is longer than {MAX_HEAD_BYTES} bytes: send less in the URL"
)
UPGRADE_WITH_BODY = error_response(
    400, "Bad Request",
    "the request asks to switch protocols (an Upgrade header) and has a body, which this server "
    "cannot read then: send it without Upgrade (curl: --http1.1, not --http2, for an http:// URL)",
)  # fmt: skip
HEAD_TOO_LARGE = error_response(
    431, "Request Header Fields Too Large",
    f"the request's head (request line and headers) is longer than {MAX_HEAD_BYTES} bytes",
)  # fmt: skip


def body_too_slow(body_timeout: float) -> bytes:
    """The answer to a request whose body did not arrive within `body_timeout` seconds."""
    return error_response(
        408, "Request Timeout",
        f"the request's body did not arrive within {body_timeout:g} s of its head (the server's "
        "--http-body-timeout): send it faster, or have the limit raised for big uploads over a slow link",
    )  # fmt: skip


def raise_descriptor_limit() -> int:
    """Raise this process's soft limit of open files to its hard limit (as the Go runtime does: the
    soft limit, often 1024, is a compatibility default for select()); returns the new soft limit.
    `fleetmap serve` calls it, and so do `fleetmap sim` and `demo` for their robots' sessions."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or hard > soft:
        target = hard if hard != resource.RLIM_INFINITY else max(soft, 1 << 20)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError):  # not allowed here: keep the soft limit
            pass
    return soft


def connection_limit(requested: int, descriptors: int) -> int:
    """`requested`, lowered so that HTTP connections leave RESERVED_DESCRIPTORS of `descriptors`
    (at least 16 connections). `descriptors`: what Zenoh's sessions leave (`zenoh_session_limit`)."""
    return max(16, min(requested, descriptors - RESERVED_DESCRIPTORS))


def zenoh_session_limit(descriptors: int, http_requested: int) -> int:
    """The most Zenoh sessions (robots) the service may accept with `descriptors` file descriptors:
    what RESERVED_DESCRIPTORS and `http_requested` HTTP connections leave, but at least half of
    those beyond the reserve (HTTP then gets the other half: `connection_limit` of what the sessions
    leave). Each session holds a descriptor, and Zenoh's own limit (`transport/unicast/max_sessions`,
    1000 by default) knows nothing of them: 365 robots took all of 400, and HTTP, /healthz included,
    went unanswered while they stayed."""
    beyond = descriptors - RESERVED_DESCRIPTORS
    return max(1, beyond - http_requested, beyond // 2)


class RateLimitedWarnings:
    """uvicorn's protocol logger (`logging.getLogger("uvicorn.error")`) with its warnings rate-limited
    by `limited`, one category per sentence; errors and everything else pass through. Its warnings
    are about requests it refused before the app saw them, one line per request for anyone to cause."""

    def __init__(self, logger: logging.Logger, limited: RateLimitedLog) -> None:
        self._logger = logger
        self._limited = limited

    def warning(self, msg: str, *args: object, **kwargs: Any) -> None:
        message = msg % args if args else msg
        self._limited.warning(message, message)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._logger, name)


def bounded_http_protocol(
    max_connections: int, head_timeout: float, body_timeout: float, send_timeout: float = 60.0
) -> type:
    """uvicorn's httptools protocol with the limits of the module's docstring (pass the class as
    `uvicorn.Config(http=...)`)."""
    # Imported here: `fleetmap --help` (which imports server.py, and so this module) need not load
    # uvicorn.
    from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

    # One for all connections: a flood comes over many.
    refusal_log = RateLimitedLog(logging.getLogger("uvicorn.error"))
    late_body = body_too_slow(body_timeout)

    class BoundedHttpToolsProtocol(HttpToolsProtocol):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            # uvicorn types it a Logger; the wrapper passes everything but warnings to the one it wraps.
            self.logger = cast(logging.Logger, RateLimitedWarnings(self.logger, refusal_log))
            self._deadline: asyncio.TimerHandle | None = None
            # Bytes received since the current head began (None: in a body, not in a head).
            self._head_bytes: int | None = 0
            # Whether the current head's request line has ended (a line feed arrived): what is
            # past the limit then is headers. (httptools hands a header over only when the next
            # one begins, so the headers seen so far cannot tell.)
            self._request_line_ended = False
            # The answer to a head refused by `on_headers_complete` (sent by `send_400_response`).
            self._refusal: bytes | None = None
            # A refusal was sent: what the client still sends is read and dropped (`_refuse`).
            self._lingering = False
            # The bytes `data_received` is parsing, and what of them follows a request that asked
            # to switch protocols (`_unsupported_upgrade_warning`), to be parsed next.
            self._received = b""
            self._after_upgrade = b""
            # Armed while the transport's write buffer is full (`pause_writing`): the client reads
            # nothing of its answer.
            self._send_stall: asyncio.TimerHandle | None = None

        def data_received(self, data: bytes) -> None:
            # A loop, not a call per request that asked to switch protocols: a client pipelining
            # thousands of them in one read would otherwise go past Python's recursion limit.
            while data and not self._lingering:
                self._received, self._after_upgrade = data, b""
                in_head = self._head_bytes is not None
                if in_head:
                    self._head_bytes = (self._head_bytes or 0) + len(data)
                    self._request_line_ended = self._request_line_ended or b"\n" in data
                super().data_received(data)
                # Still in the same head after all of `data`: every byte of it was head. (A head
                # that arrived whole in this chunk, at most 256 KiB, is measured by
                # `on_headers_complete`.) Unless the parser refused it meanwhile (`_lingering`): the
                # rest of `data` was its body, and a second refusal wrote after the end of the
                # stream (asyncio's "Fatal error" traceback, and a reset).
                if (
                    in_head
                    and not self._lingering
                    and (self._head_bytes or 0) > MAX_HEAD_BYTES
                    and not self.transport.is_closing()
                ):
                    self._refuse(HEAD_TOO_LARGE if self._request_line_ended else URL_TOO_LONG)
                data = self._after_upgrade

        def send_400_response(self, msg: str) -> None:
            # uvicorn's answer to what httptools cannot parse, as JSON (its msg says nothing more
            # than "Invalid HTTP request received."). A URL that arrived in one piece is only
            # refused here, by the URL parser: the same 414 as one that arrives slowly.
            too_long = len(getattr(self, "url", b"")) >= MAX_HEAD_BYTES
            self._refuse(self._refusal or (URL_TOO_LONG if too_long else INVALID_REQUEST))

        def _unsupported_upgrade_warning(self) -> None:
            """uvicorn's handling of a request that asks to switch to a protocol it does not serve
            (h2c; websocket without a WebSocket library), called while it handles httptools'
            `HttpParserUpgrade`, whose argument is where the other protocol would begin in the bytes
            received. The service speaks HTTP/1.1 only and ignores the `Upgrade` (RFC 9110, 7.8): the
            request, which has no body (`on_headers_complete` refuses one that has), is answered as
            any other, so there is nothing to warn of; and what follows it is HTTP, to be read on."""
            error = sys.exc_info()[1]
            offset = error.args[0] if error is not None and error.args else None
            if isinstance(offset, int) and 0 <= offset < len(self._received):
                self._after_upgrade = self._received[offset:]  # parsed next by `data_received`

        def _refuse(self, answer: bytes) -> None:
            """Send `answer` and end the connection, so that the client can read it. Closing at once,
            with the rest of the client's request unread, makes the kernel reset the connection,
            and a reset can destroy the answer before the client has read it (the client sees
            "connection reset" instead of the 414 of its 100 kB URL). So, as web servers do
            ("lingering close"), the answer goes out, then the end of the stream, and what the
            client still sends is read and dropped until it closes its side, at most LINGER
            seconds.

            A head refused behind an answer still being made on the same connection (an event
            stream, a download: the client pipelined its next request) ends that answer too, as if
            the client had gone: its app's later writes would come after the end of the stream,
            where the transport raises (an internal error, logged with two tracebacks, for
            anyone's malformed bytes), and the refusal is not written into the middle of its bytes,
            where the client would read it as part of the other answer."""
            cycle = self.cycle
            if cycle is not None and not cycle.response_complete:
                # What uvicorn does when the connection is lost: `send` drops what the app writes,
                # and the app's `receive` says the client went away (an event stream ends).
                cycle.disconnected = True
                cycle.message_event.set()
            if cycle is None or cycle.response_complete or not cycle.response_started:
                self.transport.write(answer)
            self._lingering = True
            if self.transport.can_write_eof():
                self.transport.write_eof()
            self._disarm()
            self._deadline = self.loop.call_later(LINGER, self._expire)

        # Narrower than asyncio's BaseTransport, as uvicorn's own override is: a TCP server's
        # protocol is always handed a Transport.
        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            unsent_answer_timeout(transport, send_timeout)
            if len(self.connections) > max_connections:
                # Refused before anything is read: the descriptor is given back at once.
                transport.write(BUSY_RESPONSE)
                transport.close()
                return
            self._arm(head_timeout)

        def connection_lost(self, exc: Exception | None) -> None:
            self._disarm()
            self._resumed()
            super().connection_lost(exc)

        def pause_writing(self) -> None:
            super().pause_writing()
            if self._send_stall is None:
                self._send_stall = self.loop.call_later(send_timeout, self._stalled)

        def resume_writing(self) -> None:
            self._resumed()
            super().resume_writing()

        def _resumed(self) -> None:
            if self._send_stall is not None:
                self._send_stall.cancel()
                self._send_stall = None

        def _stalled(self) -> None:
            """The client read nothing for `send_timeout` seconds: drop the connection (abort, not
            close, which would wait for the unread bytes to go). uvicorn then tells the app that the
            client went away, as when it closes: the answer ends, and a download gives back its slot
            and its file.

            The connection is reset, not closed (`reset_on_close`): closed, its socket left the
            process but not the kernel, which went on offering the answer's queued megabytes to a
            client whose window stayed shut (FIN-WAIT-1) for as long as that client held its end."""
            self._send_stall = None
            reset_on_close(self.transport)
            self.transport.abort()

        def on_message_begin(self) -> None:
            super().on_message_begin()
            if self._deadline is None:  # a kept-alive connection's next request
                self._arm(head_timeout)

        def on_headers_complete(self) -> None:
            self._head_bytes = None
            size = len(self.url) + sum(len(name) + len(value) + 4 for name, value in self.headers)
            if size > MAX_HEAD_BYTES:
                # Raising stops the parser: httptools raises a parser error from `data_received`,
                # whose handler (uvicorn's) answers with `send_400_response`, i.e. this refusal.
                self._refusal = URL_TOO_LONG if len(self.url) >= MAX_HEAD_BYTES else HEAD_TOO_LARGE
                raise ValueError(f"request head of {size} bytes")
            if self.parser.should_upgrade() and not self._should_upgrade() and self._has_body():
                # httptools ends the request at its head and leaves the body to the other protocol:
                # the app would get the request without it (see the module's docstring).
                self._refusal = UPGRADE_WITH_BODY
                raise ValueError("a request to switch protocols with a body")
            self._disarm()
            self._deadline = self.loop.call_later(body_timeout, self._body_late)
            super().on_headers_complete()

        def _has_body(self) -> bool:
            """Whether the current request's head announces a body (uvicorn keeps its headers'
            names in lower case)."""
            return any(
                name == b"transfer-encoding" or (name == b"content-length" and value.strip() != b"0")
                for name, value in self.headers
            )

        def on_message_complete(self) -> None:
            self._head_bytes = 0  # what follows is the next request's head
            self._request_line_ended = False
            self._disarm()  # the whole request is in: the response may take as long as it needs
            super().on_message_complete()

        def _arm(self, seconds: float) -> None:
            self._deadline = self.loop.call_later(seconds, self._expire)

        def _disarm(self) -> None:
            if self._deadline is not None:
                self._deadline.cancel()
                self._deadline = None

        def _expire(self) -> None:
            self._deadline = None
            if not self.transport.is_closing():
                self.transport.close()

        def _body_late(self) -> None:
            """The request's body missed its deadline: tell the client why (408), unless it is
            being answered already (a refusal sent before its body, which it kept sending), and
            end the connection as `_refuse` does; the app hears that its client went away."""
            self._deadline = None
            if self.transport.is_closing():
                return
            cycle = self.cycle
            if cycle is not None and cycle.response_started:
                self.transport.close()
            else:
                self._refuse(late_body)

    return BoundedHttpToolsProtocol


def unsent_answer_timeout(transport: asyncio.BaseTransport, seconds: float) -> None:
    """Have the kernel reset `transport`'s connection once bytes sent on it have waited `seconds`
    for the client to take them (TCP_USER_TIMEOUT; its window shut counts too), also after this
    process closed the socket. An answer that fitted whole in the socket's buffers, its client
    reading nothing, was still held by the kernel after the service closed the idle connection
    (keep-alive or head timeout), for as long as the client kept its end open (1.8 MB of a region
    minutes later): the service no longer counted that connection, so a client could pin the
    machine's memory a few MB a request. A client that reads, however slowly, is unaffected. No-op
    for a transport without a TCP socket."""
    sock = transport.get_extra_info("socket")
    user_timeout = getattr(socket, "TCP_USER_TIMEOUT", None)  # Linux only
    if sock is not None and user_timeout is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
        with contextlib.suppress(OSError):  # already gone: nothing to time
            sock.setsockopt(socket.IPPROTO_TCP, user_timeout, max(1, round(seconds * 1000)))


def reset_on_close(transport: asyncio.BaseTransport) -> None:
    """Make the closing of `transport`'s socket reset the connection (SO_LINGER on, 0 s) rather than
    leave the bytes still queued to the client to the kernel, which holds them, unsent, as long as
    the client neither reads nor goes away. No-op for a transport without a socket."""
    sock = transport.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):  # already gone: nothing is queued
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))


def quiet_accept_errors(loop: asyncio.AbstractEventLoop, limited: RateLimitedLog | None = None) -> None:
    """Log asyncio's failed accepts (out of descriptors) as one rate-limited warning instead of a
    traceback each: every other exception still goes to the loop's handler."""
    limited = limited or RateLimitedLog(log)
    previous = loop.get_exception_handler()

    def handler(loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        if context.get("message") == ACCEPT_ERROR:
            limited.warning(
                "accept", f"cannot accept HTTP connections: {context.get('exception')} (retrying)"
            )
            return
        if previous is not None:
            previous(loop, context)
        else:
            loop.default_exception_handler(context)

    loop.set_exception_handler(handler)
