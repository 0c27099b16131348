"""`fleetmap serve`'s HTTP side: the listening socket, bound before anything else starts
(`bind_http`), and the uvicorn server that serves the REST API on it (`make_server`): fleetmap's
connection limits and request timeouts (`http_limits`), its log, the ready line printed once it
accepts connections, and a graceful shutdown that ends the event streams first and is not cut short
by a second signal."""

from __future__ import annotations

import argparse
import asyncio
import errno
import logging
import socket
from collections.abc import Callable, Sequence
from typing import Any

from fleetmap.cli import CliError, discard_stdout
from fleetmap.http_limits import (
    ACCEPT_BACKLOG,
    bounded_http_protocol,
    connection_limit,
    quiet_accept_errors,
)
from fleetmap.log_format import UVICORN_LOG_CONFIG, plain_line

#: The `serve` command's logger, whichever of its modules writes the line (`fleetmap.server`).
log = logging.getLogger("fleetmap.server")

#: Seconds uvicorn waits at shutdown for the requests in flight (event streams end at once).
GRACEFUL_HTTP_SECONDS = 3  # uvicorn takes whole seconds (int)


def bind_http(host: str, port: int) -> socket.socket:
    """A listening TCP socket on (host, port), bound before anything else starts so that an address
    in use is reported at once. Raises CliError with a readable reason."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise CliError(f"cannot listen on HTTP {host}:{port}: {exc.strerror}") from None
    family, socktype, proto, _, address = infos[0]
    sock = socket.socket(family, socktype, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if family == socket.AF_INET6:
            sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
        sock.bind(address)
        sock.listen(ACCEPT_BACKLOG)
    except OSError as exc:
        sock.close()
        reason = "address already in use" if exc.errno == errno.EADDRINUSE else exc.strerror or str(exc)
        raise CliError(f"cannot listen on HTTP {host}:{port}: {reason}") from None
    sock.setblocking(False)
    return sock


def url_host(host: str) -> str:
    """`host` as a URL names it: an IPv6 address in brackets."""
    return f"[{host}]" if ":" in host else host


def _trusted_proxies(addresses: list[str] | None) -> list[str] | str | None:
    """uvicorn's `forwarded_allow_ips` for `--forwarded-allow-ips ADDRESS ...`
    (`serve_options._proxy_address`): None, uvicorn's own default ($FORWARDED_ALLOW_IPS, else
    127.0.0.1 and ::1), when not given; `*` when one of them is `*` (uvicorn trusts every client only for `*`
    alone: in a list, `*` was ignored)."""
    if addresses is not None and "*" in addresses:
        return "*"
    return addresses


def make_server(
    args: argparse.Namespace, app: Any, url: str, zenoh_endpoints: Sequence[str], descriptors: int
) -> Any:
    """The uvicorn server of `app` with fleetmap's connection limits and log, its ready line set;
    logs the HTTP limits and address. `descriptors`: the process's file descriptors that Zenoh's
    sessions leave (`http_limits.zenoh_session_limit`)."""
    import uvicorn

    max_connections = connection_limit(args.max_http_connections, descriptors)
    log.info(
        "HTTP: at most %d connections; request heads within %g s, bodies within %g s; clients that "
        "read nothing of an answer for %g s dropped",
        max_connections, args.http_head_timeout, args.http_body_timeout, args.http_send_timeout,
    )  # fmt: skip
    # httptools (a dependency; C) rather than h11 (pure Python) parses HTTP: about a quarter
    # less CPU, and GIL time the integration workers do not wait for, per cached tile. Its
    # protocol gets the connection limits of fleetmap.http_limits.
    config = uvicorn.Config(
        app,
        log_config=UVICORN_LOG_CONFIG,
        log_level="warning",  # not uvicorn's start-up lines: fleetmap's say more
        access_log=args.access_log,
        timeout_graceful_shutdown=GRACEFUL_HTTP_SECONDS,
        lifespan="auto",
        http=bounded_http_protocol(
            max_connections, args.http_head_timeout, args.http_body_timeout, args.http_send_timeout
        ),
        backlog=ACCEPT_BACKLOG,
        forwarded_allow_ips=_trusted_proxies(args.forwarded_allow_ips),
        # ASGI's root_path: uvicorn puts it before each request's path, as a proxy that strips it
        # would have received it, and the app names its URLs under it (`route_path.root_path`).
        root_path=args.root_path,
    )
    if args.access_log:  # (log_level above set its level too)
        logging.getLogger("uvicorn.access").setLevel(logging.INFO)
    server = _ready_server_class()(config)
    # Event streams never end by themselves: end them first, so that the graceful shutdown waits
    # only for the requests that do.
    server.before_shutdown = app.state.fleetmap.event_streams.close_all
    connections = server.server_state.connections
    app.state.fleetmap.metrics.watch_http_connections(lambda: len(connections), max_connections)
    server.ready_line = plain_line(
        f"fleetmap serving {url}  zenoh: {' '.join(zenoh_endpoints)}",
        args.log_format,
        url=url,
        zenoh=list(zenoh_endpoints),
    )
    log.info("HTTP (REST API, viewer, /metrics, /healthz) on %s", url)
    return server


def print_ready_line(line: str) -> None:
    """Print `line` (the ready line) on stdout; if stdout cannot take it, log that (on stderr, with
    the line) instead, and point stdout at /dev/null. Never raises.

    Why: a stdout whose reader is gone (`fleetmap serve | some-filter` that exited, a `tee` that was
    killed) or that cannot be written (redirected to a file on a full disk) raised out of uvicorn's
    start-up: a service that had started, restored its maps and opened Zenoh stopped again, with a
    traceback and exit 1. The ready line is all the service writes to stdout, so it serves on. The
    line stays in stdout's buffer (unless PYTHONUNBUFFERED is set): left pointing at the broken
    stream, the interpreter's flush at exit failed again, and a clean stop exited 120, not 0."""
    try:
        print(line, flush=True)
    except OSError as exc:
        discard_stdout()
        log.warning("cannot print the ready line on stdout (%s); serving on: %s", exc.strerror, line)


def _ready_server_class() -> type:
    import uvicorn

    class ReadyServer(uvicorn.Server):
        """uvicorn's server, printing the ready line once it accepts connections and calling
        `before_shutdown` when it starts to shut down."""

        ready_line = ""
        before_shutdown: Callable[[], None] | None = None

        async def startup(self, sockets: list[socket.socket] | None = None) -> None:
            quiet_accept_errors(asyncio.get_running_loop())
            await super().startup(sockets=sockets)
            if self.started and not self.should_exit:
                print_ready_line(self.ready_line)

        async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
            if self.before_shutdown is not None:
                self.before_shutdown()
            await super().shutdown(sockets=sockets)

        def handle_exit(self, sig: int, frame: Any) -> None:
            """Start the shutdown on the first SIGINT / SIGTERM; ignore those that follow. uvicorn
            takes a second SIGINT (a double Ctrl-C, or Ctrl-C after SIGTERM) as "force quit": it
            stopped waiting for the requests in flight and skipped the ASGI lifespan's shutdown,
            whose task the closing event loop then cancelled, logging an ERROR with a traceback.
            The wait is bounded by GRACEFUL_HTTP_SECONDS anyway, and what follows it (integrating
            the queued scans, the final snapshot) does not stop for a signal either."""
            if not self.should_exit:
                super().handle_exit(sig, frame)

    return ReadyServer
