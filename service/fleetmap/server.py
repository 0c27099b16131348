"""`fleetmap serve`: the long-running service. Robots publish scans over Zenoh; maps are served over HTTP.

    fleetmap serve [--http HOST:PORT] [--zenoh-listen EP ...] [--zenoh-connect EP ...]
                   [--zenoh-config FILE.json5] [--data-dir DIR] [--config FILE] [--no-auto-create]
                   [--workers N] [--ingest-backlog-ms MS] [--max-read-delay-ms MS]
                   [--ros-publish-map MAP_ID[=TOPIC] ...] [--ros-domain N] [--ros-map-frame FRAME]
                   [--ros-map-period S] [--ros-distro jazzy|humble]
                   [--log-level LEVEL] [--log-format text|json] [--access-log]

One process holds everything: a `MapRegistry` (maps, robots, integration worker threads), a
`ZenohIngest` (the service's own Zenoh session: a router by default, so robots connect to it
directly in client mode and nothing else needs installing) and the REST API (`fleetmap.api`) run by
uvicorn in the main thread; with `--ros-publish-map`, a `RosMapPublisher` (fleetmap.ros.map_publisher)
publishes maps to ROS 2 on the same Zenoh session from a thread of its own.

Start-up order: the HTTP socket is bound first (so a port in use fails before anything else starts),
the compiled kernels are warmed, the registry's workers start, the Zenoh session opens, then uvicorn
serves. Only then is the ready line printed on stdout:

    fleetmap serving http://HOST:PORT  zenoh: ENDPOINTS

(with `--log-format json`, a JSON log object whose message is that line: see fleetmap.log_format).

Every option can also be given as an environment variable, `FLEETMAP_` and the option's name in
capitals with `-` as `_` (`--data-dir` is `FLEETMAP_DATA_DIR`, `--insecure` is `FLEETMAP_INSECURE=1`,
lists separated by spaces); the command line wins (`_environment_first`).

SIGHUP reads the `--auth-tokens` file again (a file that cannot be used keeps the tokens in force).
SIGINT / SIGTERM shut down gracefully: uvicorn stops serving (open event streams end at once, other
requests in flight get `GRACEFUL_HTTP_SECONDS`, then are answered 503 or cut off: `ShutdownCutoff`
in api/errors.py), the Zenoh session closes (no more scans come in), the
registry integrates every scan already queued and stops its workers, and the process exits 0 (a
second signal changes nothing: it does not cut the shutdown short). A configuration error (bad
address, port in use, bad config file) prints one line `fleetmap serve: error: ...` and exits 2,
without a traceback.
"""

from __future__ import annotations

import argparse
import asyncio
import errno
import gc
import ipaddress
import logging
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, NoReturn, TypeVar

import zenoh

from fleetmap.auth import TokenFile, TokenFileError, TokenSet
from fleetmap.cli import CliError, load_config, parse_command_line, run_command
from fleetmap.codec import InputLimits, configure_limits
from fleetmap.config import MapConfig
from fleetmap.database import StorageError
from fleetmap.failed_signins import DEFAULT_MAX_FAILURES, DEFAULT_WINDOW
from fleetmap.http_limits import (
    ACCEPT_BACKLOG,
    RESERVED_DESCRIPTORS,
    bounded_http_protocol,
    connection_limit,
    quiet_accept_errors,
    raise_descriptor_limit,
)
from fleetmap.ingest import DEFAULT_LISTEN, IngestStartError, ZenohIngest
from fleetmap.log_format import LOG_FORMATS, UVICORN_LOG_CONFIG, configure_logging, plain_line
from fleetmap.memory_budget import DEFAULT_SHARE, MemoryBudget, parse_size
from fleetmap.persistence import SNAPSHOT_INTERVAL, SNAPSHOT_ROWS, DurableStore
from fleetmap.ros.transforms import TfError, normalize_frame
from fleetmap.scan import MAX_BEAMS
from fleetmap.wire import is_valid_id

if TYPE_CHECKING:
    from fleetmap.registry import MapRegistry
    from fleetmap.ros.ingest import RosScanIngest

log = logging.getLogger("fleetmap.server")

DEFAULT_HTTP = "127.0.0.1:8000"
DEFAULT_DATA_DIR = "./fleetmap-data"
#: Prefix of the environment variables that give `serve` options (FLEETMAP_DATA_DIR, ...).
ENV_PREFIX = "FLEETMAP_"
#: What a FLEETMAP_* variable of an on/off option (--insecure, ...) may say.
_ENV_TRUE = {"1", "true", "yes", "on"}
_ENV_FALSE = {"0", "false", "no", "off", ""}
LOG_LEVELS = ("debug", "info", "warning", "error")
#: The defaults of --ros-map-frame, --ros-map-period and --ros-distro (any other value needs
#: --ros-publish-map). The frame's None: --ros-fixed-frame's for the map of --ros-scans, else map
#: (`ros_map_frame`).
ROS_MAP_DEFAULTS = (None, 1.0, "jazzy")
#: Seconds uvicorn waits at shutdown for the requests in flight (event streams end at once).
GRACEFUL_HTTP_SECONDS = 3  # uvicorn takes whole seconds (int)


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> argparse.ArgumentParser:
    """Add the `serve` subcommand to the `fleetmap` command line."""
    p = sub.add_parser(
        "serve",
        help="run the service: Zenoh ingest from robots, REST API and web viewer",
        exit_on_error=False,  # _environment_first reports errors, naming a variable at fault
        description=(
            "Run the fleetmap service: robots publish scans over Zenoh (key fleetmap/<map>/<robot>/scan, "
            "see docs/protocol.md), maps are served over HTTP (REST API and web viewer). The service's "
            "own Zenoh session is a router, so robots connect to it directly in client mode. Every "
            "option may also be set in the environment: FLEETMAP_ and the option's name in capitals, "
            "- as _ (--data-dir DIR: FLEETMAP_DATA_DIR=DIR; --insecure: FLEETMAP_INSECURE=1; lists "
            "separated by spaces); the command line wins. SIGHUP reads the --auth-tokens file again."
        ),
    )
    p.add_argument(
        "--http",
        default=DEFAULT_HTTP,
        metavar="HOST:PORT",
        help=f"address of the REST API and web viewer (default {DEFAULT_HTTP}; port 0 picks a free port)",
    )
    p.add_argument(
        "--zenoh-listen",
        nargs="+",
        metavar="ENDPOINT",
        help=(
            f"Zenoh endpoints robots connect to (default {' '.join(DEFAULT_LISTEN)}; with --zenoh-connect "
            "the default is not to listen)"
        ),
    )
    p.add_argument(
        "--zenoh-connect",
        nargs="+",
        default=[],
        metavar="ENDPOINT",
        help=(
            "join an existing Zenoh network through these endpoints (e.g. a zenohd router) instead of "
            "being its own: the session is then a peer if it also listens, else a client"
        ),
    )
    p.add_argument(
        "--zenoh-config",
        type=_path,
        metavar="FILE.json5",
        help=(
            "Zenoh configuration file, loaded first; the --zenoh-* options apply on top of it. Its "
            "'mode' is kept when set; multicast scouting stays off unless the file switches it on"
        ),
    )
    p.add_argument(
        "--zenoh-shared-memory",
        action="store_true",
        help=(
            "use Zenoh's shared-memory transport with robots on this host (off by default, whatever "
            "the config file says: it maps a 16 MiB pool per local robot and delayed each robot's "
            "first scans by up to 250 ms, while loopback TCP is fast enough)"
        ),
    )
    p.add_argument(
        "--ros-scans",
        type=_map_id,
        metavar="MAP_ID",
        help=(
            "also integrate the sensor_msgs/LaserScan topics ROS 2 robots publish over rmw_zenoh into "
            "map MAP_ID, posed by their TF (robot id: the topic's namespace, and its name if not scan; "
            "see docs/ros.md)"
        ),
    )
    p.add_argument(
        "--ros-domain",
        type=_int_between(0, 2**32 - 1),
        metavar="N",
        help="the ROS domain id of --ros-scans and --ros-publish-map (default $ROS_DOMAIN_ID, else 0)",
    )
    p.add_argument(
        "--ros-fixed-frame",
        type=_frame_id,
        metavar="FRAME",
        help="the TF frame --ros-scans' maps are built in (default map)",
    )
    p.add_argument(
        "--data-dir",
        type=_path,
        default=DEFAULT_DATA_DIR,
        metavar="DIR",
        help=(
            f"durable map storage (SQLite, WAL): configurations, tile snapshots and the scan journal "
            f"(default {DEFAULT_DATA_DIR}). An unwritable or full directory stops the service at start"
        ),
    )
    p.add_argument(
        "--snapshot-interval",
        type=_seconds_between(0.5, 86400.0),
        default=SNAPSHOT_INTERVAL,
        metavar="S",
        help=(
            f"snapshot every changed map this often, seconds (default {SNAPSHOT_INTERVAL:g}; also "
            f"after {SNAPSHOT_ROWS} journaled scans, and at shutdown): shorter means a shorter journal to "
            "replay at start and sooner recovery of scans a failing disk could not journal"
        ),
    )
    p.add_argument(
        "--max-memory",
        type=_memory_budget,
        default="auto",
        metavar="SIZE",
        help=(
            "bytes all maps' tiles may hold together, e.g. 4GiB; scans that would need more are "
            f"refused (507) and their maps unchanged. 'auto' (default): {DEFAULT_SHARE * 100:.0f}%% of the "
            "memory this process may use (its cgroup's limit, else the machine's); 'none': no limit"
        ),
    )
    p.add_argument(
        "--in-memory",
        action="store_true",
        help="keep maps in memory only (lost when the service stops); for demos and tests",
    )
    p.add_argument(
        "--auth-tokens",
        type=_path,
        metavar="FILE",
        help=(
            "API tokens, one 'ROLE TOKEN' per line (ROLE: read, write or admin); also read from "
            "$FLEETMAP_TOKENS ('ROLE TOKEN; ROLE TOKEN'). Writing needs write or admin"
        ),
    )
    p.add_argument(
        "--require-read-token",
        action="store_true",
        help=(
            "reading also needs a token (read, write or admin; so tokens must be given); by default "
            "reading is open"
        ),
    )
    p.add_argument(
        "--max-failed-sign-ins",
        type=_int_between(1, 1_000_000),
        default=DEFAULT_MAX_FAILURES,
        metavar="N",
        help=(
            "failed sign-ins (POST /session with a wrong token) from one client address within "
            "--failed-sign-in-window before its sign-ins are refused with 429 "
            f"(default {DEFAULT_MAX_FAILURES})"
        ),
    )
    p.add_argument(
        "--failed-sign-in-window",
        type=_seconds_between(1.0, 86400.0),
        default=DEFAULT_WINDOW,
        metavar="S",
        help=(
            "seconds from an address's first failed sign-in within which its failures count, and "
            f"the longest it is refused (default {DEFAULT_WINDOW:g})"
        ),
    )
    p.add_argument(
        "--insecure",
        action="store_true",
        help="allow binding HTTP to a non-loopback address without API tokens",
    )
    limits = InputLimits()
    p.add_argument(
        "--world-bound",
        type=float,
        default=limits.world_bound,
        metavar="M",
        help=f"refuse poses farther than this on x or y, metres (default {limits.world_bound:g})",
    )
    p.add_argument(
        "--max-beams",
        type=_int_between(1, MAX_BEAMS),
        default=limits.max_beams,
        metavar="N",
        help=f"refuse scans with more beams (default {limits.max_beams})",
    )
    p.add_argument(
        "--max-range",
        type=float,
        default=limits.max_range,
        metavar="M",
        help=f"readings at or beyond this (metres) are 'no return' (default {limits.max_range:g})",
    )
    p.add_argument(
        "--cors-origin",
        nargs="+",
        default=[],
        metavar="ORIGIN",
        help="origins allowed to call the API from a browser (CORS), matched exactly ('*': any); "
        "default none",
    )
    p.add_argument(
        "--forwarded-allow-ips",
        nargs="+",
        type=_proxy_address,
        default=None,
        metavar="IP",
        help="addresses (or networks, 10.0.0.0/8) of the reverse proxies whose X-Forwarded-Proto / "
        "-For headers are trusted (the session cookie's Secure, the access log's client), separated "
        "by spaces; '*': any; default 127.0.0.1, or uvicorn's $FORWARDED_ALLOW_IPS",
    )
    p.add_argument(
        "--max-event-streams",
        type=_int_between(1, 100_000),
        default=256,
        metavar="N",
        help=(
            "event streams (GET /maps/{id}/events, one per open viewer) open at once; past it new ones "
            "are refused with 503 and retry by themselves (default 256): each holds memory and CPU"
        ),
    )
    p.add_argument(
        "--events-keepalive",
        type=_seconds_between(0.1, 3600.0),
        default=15.0,
        metavar="S",
        help=(
            "seconds of silence after which an event stream sends a ': keepalive' comment (default "
            "15): shorter than the idle timeout of any proxy in front; clients take a stream silent "
            "for a few of these as broken (the Python client: 45 s) and resume it"
        ),
    )
    p.add_argument(
        "--max-robots-per-map",
        type=_int_between(1, 1_000_000),
        default=1024,
        metavar="N",
        help=(
            "robots one map keeps; a new robot on a full map makes room by forgetting the offline one "
            "heard from least recently (default 1024)"
        ),
    )
    p.add_argument(
        "--max-http-connections",
        type=_int_between(16, 1_000_000),
        default=1024,
        metavar="N",
        help=(
            "HTTP connections open at once; past it a new one gets 503 and is closed (default 1024, "
            f"lowered to leave {RESERVED_DESCRIPTORS} of the process's file descriptors to Zenoh and storage)"
        ),
    )
    p.add_argument(
        "--http-head-timeout",
        type=_seconds_between(0.1, 3600.0),
        default=10.0,
        metavar="S",
        help=(
            "close a connection whose request line and headers have not all arrived this many seconds "
            "after it opened (or after the request's first byte) (default 10)"
        ),
    )
    p.add_argument(
        "--http-body-timeout",
        type=_seconds_between(0.1, 3600.0),
        default=60.0,
        metavar="S",
        help=(
            "close a connection whose request body has not all arrived this many seconds after its "
            "headers (default 60: a 16 MiB body at 2.2 Mbit/s)"
        ),
    )
    p.add_argument(
        "--config",
        type=_path,
        metavar="FILE",
        help="map configuration (JSON, the schema of PUT /maps/{id}) for maps created automatically",
    )
    p.add_argument(
        "--no-auto-create",
        action="store_true",
        help="refuse scans for maps that do not exist (create maps with PUT /maps/{id}) instead of "
        "creating them with the default configuration",
    )
    p.add_argument(
        "--workers",
        type=_int_between(1, 64),
        default=2,
        metavar="N",
        help="integration worker threads (default 2)",
    )
    p.add_argument(
        "--ingest-backlog-ms",
        type=_int_between(0, 60_000),
        default=10,
        metavar="MS",
        help=(
            "ingest before reads: while the oldest scan waiting for integration has waited longer than "
            "this, new HTTP requests wait (all but /healthz, /metrics and POST scans); 0: off (default 10)"
        ),
    )
    p.add_argument(
        "--max-read-delay-ms",
        type=_int_between(0, 600_000),
        default=1000,
        metavar="MS",
        help="the longest an HTTP request waits for the ingest backlog; then it is served (default 1000)",
    )
    p.add_argument(
        "--ros-publish-map",
        nargs="+",
        action=_RepeatedOption,
        type=_map_topic,
        default=[],
        metavar="MAP_ID[=TOPIC]",
        help=(
            "publish this map to ROS 2 (rmw_zenoh) as a nav_msgs/msg/OccupancyGrid on TOPIC (default "
            "/map), as nav2's map_server does (TRANSIENT_LOCAL), whole, when it changed, on the service's "
            "Zenoh session; repeatable (see docs/ros.md). Off by default"
        ),
    )
    p.add_argument(
        "--ros-map-frame",
        type=_frame_id,
        default=ROS_MAP_DEFAULTS[0],
        metavar="FRAME",
        help=(
            "header.frame_id of the published maps (default: --ros-fixed-frame's for the map of "
            "--ros-scans, else map)"
        ),
    )
    p.add_argument(
        "--ros-map-period",
        type=_seconds_between(0.05, 3600.0),
        default=ROS_MAP_DEFAULTS[1],
        metavar="S",
        help=(
            "seconds between checks of the published maps: a map that changed is published again at "
            "most this often, one that did not is not sent again (default 1)"
        ),
    )
    p.add_argument(
        "--ros-distro",
        choices=("jazzy", "humble"),
        default=ROS_MAP_DEFAULTS[2],
        help=(
            "ROS 2 distribution of the subscribers, for the type hash in the topic's key: jazzy "
            "(default; also Kilted and Rolling) or humble (rmw_zenoh's backport, without type hashes)"
        ),
    )
    p.add_argument(
        "--log-level",
        choices=LOG_LEVELS,
        default="info",
        help="the least severe log messages written (default info: start-up, robots, maps, warnings)",
    )
    p.add_argument(
        "--log-format",
        choices=LOG_FORMATS,
        default="text",
        help=(
            "text (default): one line per message for people; json: one JSON object per line (time, "
            "level, logger, message, exception, map_id, robot_id, ...) for a log pipeline, uvicorn's "
            "lines and the ready line included (see docs/security.md, What is logged)"
        ),
    )
    p.add_argument(
        "--access-log",
        action="store_true",
        help="log every HTTP request (client, method, path, status) at info; off by default (cost)",
    )
    p.set_defaults(run=run)
    # Replaced on this one parser instance. mypy refuses assigning to a method, and compares the
    # function to the method unbound (with its self).
    p.error = _one_line_error(p)  # type: ignore[method-assign,assignment]
    p.parse_known_args = _environment_first(p)  # type: ignore[method-assign]
    return p


def _one_line_error(parser: argparse.ArgumentParser) -> Callable[[str], NoReturn]:
    """`parser.error` that prints one line, not argparse's usage first (`serve` has 28 options: the
    usage took 15 lines above the error, which a service manager's log shows out of order)."""

    def error(message: str) -> NoReturn:
        parser.exit(2, f"{parser.prog}: error: {message} (see {parser.prog} --help)\n")

    return error


def env_name(action: argparse.Action) -> str:
    """The environment variable of an option: `--data-dir` -> `FLEETMAP_DATA_DIR`."""
    return ENV_PREFIX + action.option_strings[-1].lstrip("-").replace("-", "_").upper()


def _environment_first(parser: argparse.ArgumentParser) -> Callable[..., Any]:
    """`parser.parse_known_args` that parses the `FLEETMAP_<OPTION>` variables set (when it runs:
    the environment counts for `serve` only) as their options on a command line before the real
    one, which therefore wins. A bad variable stops with one line naming it, after the command line
    is parsed (so `--log-format json` makes that line JSON); `parser` must not exit on errors."""
    parse = parser.parse_known_args

    def parse_known_args(args: Sequence[str] | None = None, namespace: Any = None) -> Any:
        problem = None
        for action in parser._actions:
            variable = env_name(action)
            text = os.environ.get(variable)
            if text is None or action.dest == "help":
                continue
            try:
                namespace = parse(_as_arguments(action, text), namespace)[0]
            except argparse.ArgumentError as exc:
                problem = problem or f"${variable}={text!r}: {exc.message}"
            else:
                if isinstance(action, _RepeatedOption):
                    values = getattr(namespace, action.dest)
                    setattr(namespace, action.dest, _FromEnvironment(values))
        try:
            namespace, extras = parse(args, namespace)
        except argparse.ArgumentError as exc:
            parser.error(str(exc))
        if problem:
            line = plain_line(f"{parser.prog}: error: {problem}", namespace.log_format, logging.ERROR)
            parser.exit(2, line + "\n")
        return namespace, extras

    return parse_known_args


def _as_arguments(action: argparse.Action, text: str) -> list[str]:
    """The command-line arguments a variable's `text` stands for: an on/off option's flag (or none),
    a list option's words (none: no list), else `--option=TEXT`. Raises ArgumentError."""
    option = action.option_strings[-1]
    if action.nargs == 0:
        word = text.strip().lower()
        if word not in _ENV_TRUE | _ENV_FALSE:
            raise argparse.ArgumentError(action, "expected 1, true, yes, on or 0, false, no, off")
        return [option] if word in _ENV_TRUE else []
    if action.nargs == "+":
        return [option, *text.split()] if text.split() else []
    return [f"{option}={text}"]


class _FromEnvironment(list):
    """The values a repeatable option got from its FLEETMAP_ variable (see `_RepeatedOption`)."""


class _RepeatedOption(argparse.Action):
    """An option that may be given several times, each with one or more values, all kept in order
    (`--ros-publish-map a --ros-publish-map b c`: a, b, c). Its variable gives values separated by
    spaces; the command line's first occurrence replaces those (the command line wins, as for every
    option) rather than adding to them."""

    def __call__(
        self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any, option: Any = None
    ) -> None:
        current = getattr(namespace, self.dest, None)
        kept = [] if current is None or isinstance(current, _FromEnvironment) else list(current)
        setattr(namespace, self.dest, kept + list(values))


def _map_topic(text: str) -> Any:
    """An argparse `type` for `--ros-publish-map`: `MAP_ID[=TOPIC]` as a `MapTopic`."""
    from fleetmap.ros.map_publisher import parse_map_topic

    try:
        return parse_map_topic(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _load_tokens(path: str | None) -> TokenSet | TokenFile | None:
    """The API tokens: a `TokenFile` (read again on SIGHUP) for `--auth-tokens`, else those of
    $FLEETMAP_TOKENS, else None. Raises CliError."""
    try:
        return TokenFile(path) if path else TokenSet.load(None)
    except TokenFileError as exc:
        raise CliError(str(exc)) from None


def reload_tokens(tokens: TokenSet | TokenFile | None) -> None:
    """SIGHUP: read the token file again and log the outcome (never a token)."""
    if not isinstance(tokens, TokenFile):
        where = "$FLEETMAP_TOKENS" if tokens is not None else "no --auth-tokens"
        log.warning("SIGHUP: nothing to reload (tokens: %s; restart to change them)", where)
        return
    try:
        count = tokens.reload()
    except TokenFileError as exc:
        log.error("SIGHUP: kept the tokens in force: %s", exc)
        return
    log.info("SIGHUP: %d API tokens read from %s", count, tokens.path)


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


def _memory_budget(text: str) -> MemoryBudget:
    """An argparse `type`: `--max-memory`'s budget (see `memory_budget.parse_size`)."""
    try:
        return MemoryBudget(parse_size(text))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _path(text: str) -> str:
    """An argparse `type` for a file or directory option: any path but an empty one. An empty
    FLEETMAP_DATA_DIR (a template's unset variable) kept the maps in the working directory, and an
    empty FLEETMAP_CONFIG or FLEETMAP_AUTH_TOKENS was taken as no option at all, all silently."""
    if not text.strip():
        raise argparse.ArgumentTypeError("expected a path, got an empty value")
    return text


def _map_id(text: str) -> str:
    """An argparse `type` for a map id: `[A-Za-z0-9_-]{1,64}`."""
    if not is_valid_id(text):
        raise argparse.ArgumentTypeError(f"expected a map id of 1 to 64 of A-Z a-z 0-9 _ -, got {text!r}")
    return text


def _frame_id(text: str) -> str:
    """An argparse `type` for a TF frame id (tf2's form: a leading `/` dropped)."""
    try:
        return normalize_frame(text.strip())
    except TfError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def ros_map_frame(args: argparse.Namespace, map_id: str) -> str:
    """The frame id of map `map_id`'s published grids: `--ros-map-frame`, else, for the map of
    `--ros-scans`, `--ros-fixed-frame` (the frame it builds that map in: a grid labelled `map` while
    its cells are in `world` would put it in the wrong place for nav2), else `map`. Another map
    (native robots') is not in that frame, so it is not labelled with it."""
    if args.ros_map_frame:
        return str(args.ros_map_frame)
    if map_id == args.ros_scans and args.ros_fixed_frame:
        return str(args.ros_fixed_frame)
    return "map"


def ros_domain(args: argparse.Namespace, environ: dict[str, str] | None = None) -> int:
    """The ROS domain id of `--ros-scans` and `--ros-publish-map`: `--ros-domain` (or
    FLEETMAP_ROS_DOMAIN), else ROS's own $ROS_DOMAIN_ID, else 0. Raises CliError for an unusable
    $ROS_DOMAIN_ID."""
    if args.ros_domain is not None:
        return int(args.ros_domain)
    text = (os.environ if environ is None else environ).get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    if not text.isdigit() or int(text) >= 2**32:
        raise CliError(f"$ROS_DOMAIN_ID={text!r}: expected a whole number (or give --ros-domain N)")
    return int(text)


def ros_options(args: argparse.Namespace, environ: dict[str, str] | None = None) -> tuple[int, str] | None:
    """(domain id, fixed frame) of `--ros-scans`, None without it (`ros_domain`). Raises CliError
    for an unusable $ROS_DOMAIN_ID, --ros-fixed-frame without --ros-scans, or --ros-domain with
    neither --ros-scans nor --ros-publish-map."""
    if args.ros_scans is None:
        if args.ros_fixed_frame is not None:
            raise CliError("--ros-fixed-frame needs --ros-scans MAP_ID")
        if args.ros_domain is not None and not args.ros_publish_map:
            raise CliError("--ros-domain needs --ros-scans MAP_ID or --ros-publish-map MAP_ID")
        return None
    return ros_domain(args, environ), args.ros_fixed_frame or "map"


def _proxy_address(text: str) -> str:
    """An argparse `type` for `--forwarded-allow-ips`: `*`, an IP address or a network (`10.0.0.0/8`;
    host bits set are cleared), as uvicorn compares them with a connection's address. uvicorn takes
    anything else as a name that no address ever equals: `10.0.0.1,10.0.0.2` (its own variable's
    separator), `10.0.0.1,` (a list of a variable split at spaces), a host name, a typo. The proxy
    was then silently not trusted: its `https` ignored, the session cookie set without `Secure`."""
    text = text.strip()
    if text == "*":
        return text
    try:
        return str(ipaddress.ip_network(text, strict=False) if "/" in text else ipaddress.ip_address(text))
    except ValueError:
        pass
    message = f"expected an IP address, a network (10.0.0.0/8) or '*', got {text!r}"
    if "," in text:
        message += " (separate addresses with spaces, not commas)"
    elif ":" not in text and any(c.isalpha() for c in text):  # a name, not a mistyped IPv6 address
        message += " (host names are not looked up)"
    raise argparse.ArgumentTypeError(message)


N = TypeVar("N", int, float)


def _number_between(kind: Callable[[str], N], low: N, high: N, what: str) -> Callable[[str], N]:
    """An argparse `type` accepting `kind(text)` (`what`, for the message) in [low, high]."""

    def parse(text: str) -> N:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        if not low <= value <= high:  # NaN fails too
            # Whole: %g wrote 1_000_000 as 1e+06 and 2**32 - 1 as 4.29497e+09.
            bounds = (str(low), str(high)) if kind is int else (f"{low:g}", f"{high:g}")
            raise argparse.ArgumentTypeError(f"must be between {bounds[0]} and {bounds[1]}, got {text}")
        return value

    return parse


def _seconds_between(low: float, high: float) -> Callable[[str], float]:
    return _number_between(float, low, high, "a number of seconds")


def _int_between(low: int, high: int) -> Callable[[str], int]:
    return _number_between(int, low, high, "a whole number")


def parse_http(text: str) -> tuple[str, int]:
    """(host, port) of `HOST:PORT`, `[IPV6]:PORT` or `:PORT` (all interfaces). Raises CliError."""
    host, sep, port_text = text.rpartition(":")
    if not sep or not port_text.isdigit():
        raise CliError(f"--http {text!r}: expected HOST:PORT, e.g. 127.0.0.1:8000")
    port = int(port_text)
    if port > 65535:
        raise CliError(f"--http {text!r}: port must be at most 65535")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    return host or "0.0.0.0", port


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


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def warm_up() -> None:
    """Integrate tiny scans into throwaway maps so the compiled kernels are loaded (or compiled)
    before the first robot's scan: its latency should not include that (loading them from numba's
    cache takes about 50 ms, compiling them 10 s).

    Both paths a scan can take: the service's ingest plans and applies (`GridMap.plan`,
    `GridMap.apply`), into new tiles and then existing ones; journal replay and library users call
    `GridMap.integrate`, whose one compiled call creates tiles itself and so never reaches the
    planning kernels. A durable service also encodes every scan for its journal (`scan_to_blob`).
    The ray caster (`GridMap.cast_rays`) and the zoomed-out tile reductions (`kernels.reduce`, one per
    dtype) are loaded too, so a first ray query or zoomed-out tile does not compile them."""
    import numpy as np

    from fleetmap.config import MapConfig
    from fleetmap.grid_map import GridMap
    from fleetmap.kernels.reduce import reduce_max_tiles, reduce_tsdf_tiles
    from fleetmap.scan import Scan
    from fleetmap.storage_format import scan_to_blob

    scan = Scan.from_fan((0.0, 0.0, 0.0), -0.5, 0.1, [1.0] * 10 + [None], 0.0, 5.0)
    scan_to_blob(scan)
    for sensor_model in ("ray", "beam"):
        config = MapConfig(sensor_model=sensor_model, tile_size=16, resolution=0.1)
        GridMap(config).integrate(scan)
        gmap = GridMap(config)
        for _ in range(2):
            gmap.apply(gmap.plan(scan))
    gmap.cast_rays((0.0, 0.0), [0.0, 1.0], 2.0)
    # The reductions alone, of each pool dtype, not a whole render (a render's faults are the
    # request's, not the start's).
    slots = np.zeros(1, dtype=np.int64)
    for dtype in (np.float32, np.uint32):
        pool = np.zeros((1, 2, 2), dtype=dtype)
        reduce_max_tiles(pool, slots, 0, 0, 2, 2, np.empty((1, 1, 1), dtype=dtype))
    tsdf = np.zeros((1, 2, 2), dtype=np.float32)
    reduce_tsdf_tiles(tsdf, tsdf, slots, 0, 0, 2, 2, np.empty((1, 1, 1), dtype=np.float32))


def freeze_startup_objects() -> int:
    """Move every object alive now (modules, compiled kernels, the app: ~160,000 objects that live as
    long as the process) out of the garbage collector's reach; returns how many. Requests that
    allocate many containers (a 10,000-point cell query parses 10,000 lists) trigger full
    collections, and each walked all of them for ~70 ms holding the GIL, stalling the integration
    workers. Afterwards a full collection walks only what was created since."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def _integration_hook() -> Any:
    """The registry's `on_integrated` hook: a new `IntegrationMetrics`' (the app finds it there)."""
    from fleetmap.metrics import IntegrationMetrics

    return IntegrationMetrics().on_integrated


def _load_api() -> tuple[Any, Any]:
    """(create_app, ApiSettings) of the REST API (fleetmap.api.app). Raises CliError if missing."""
    try:
        from fleetmap.api.app import ApiSettings, create_app
    except ImportError as exc:
        raise CliError(f"the REST API (fleetmap.api.app) cannot be imported: {exc}") from None
    return create_app, ApiSettings


def _http_server_class() -> type:
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
                print(self.ready_line, flush=True)

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


def run(args: argparse.Namespace) -> int:
    """`fleetmap serve`: run until SIGINT / SIGTERM, then shut down cleanly and return 0.

    In order: the process set up (`_configure_process`), the options checked (`_checked_options`),
    the HTTP socket bound, storage opened (`_open_storage`), the engine warmed, the registry
    restored and started, the Zenoh session opened, then the API served by uvicorn
    (`_http_server`) until a signal; the Zenoh session and the registry close whatever happened.
    SIGINT, SIGTERM and SIGHUP are left ignored when it returns: the process is to exit then."""
    from fleetmap.registry import MapRegistry

    _configure_process(args)
    stop = threading.Event()
    server: Any = None

    def on_signal(signum: int, _frame: object) -> None:
        # Before uvicorn runs (start-up) and after it returns (uvicorn re-raises the signal it
        # caught): note the request; uvicorn handles the signal itself while it serves.
        stop.set()
        if server is not None:
            server.should_exit = True

    tokens: TokenSet | TokenFile | None = None
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    # SIGHUP's default action ends the process at once (no snapshot, no clean close): `kill -HUP` or
    # systemd's ExecReload must reload the token file instead.
    signal.signal(signal.SIGHUP, lambda _signum, _frame: reload_tokens(tokens))
    ros: RosScanIngest | None = None
    try:
        options = _checked_options(args)
        tokens = options.tokens
        # The HTTP socket first: a second instance on a busy port must fail before it opens the
        # (possibly shared) data directory.
        sock = bind_http(options.host, options.port)
        port = sock.getsockname()[1]
        durable = _open_storage(args, sock)
        _warm_engine()
        registry = MapRegistry(
            options.default_config,
            auto_create=not args.no_auto_create,
            workers=args.workers,
            on_integrated=_integration_hook(),
            durable=durable,
            memory_budget=args.max_memory,
            max_robots_per_map=args.max_robots_per_map,
        )
        ingest = ZenohIngest(
            registry,
            listen=args.zenoh_listen,
            connect=args.zenoh_connect,
            config_file=args.zenoh_config,
            shared_memory=args.zenoh_shared_memory,
        )
        try:
            registry.start()  # restores the stored maps
        except StorageError as exc:
            sock.close()
            assert durable is not None  # only a durable registry reads storage at start
            durable.close()
            raise CliError(str(exc)) from None
        ros_maps: Any = None
        try:
            try:
                ingest.start()
            except IngestStartError as exc:
                raise CliError(str(exc)) from None
            ros = _start_ros(args, options, registry, ingest)
            ros_maps = _start_ros_maps(args, registry, ingest)
            settings = options.settings_cls(
                zenoh_status=_zenoh_status(ingest, ros, ros_maps),
                cors_origins=args.cors_origin,
                ingest_backlog=args.ingest_backlog_ms / 1000,
                max_read_delay=args.max_read_delay_ms / 1000,
                max_event_streams=args.max_event_streams,
                keepalive=args.events_keepalive,
                tokens=tokens,
                require_read_token=args.require_read_token,
                signin_max_failures=args.max_failed_sign_ins,
                signin_window=args.failed_sign_in_window,
            )
            app = options.create_app(registry, settings=settings)
            _log_protection(args, tokens, durable is not None)
            server = _http_server(args, app, f"http://{_url_host(options.host)}:{port}", ingest.endpoints)
            freeze_startup_objects()
            if not stop.is_set():
                server.run(sockets=[sock])
        finally:
            sock.close()
            log.info("shutting down: closing the Zenoh session, integrating queued scans")
            if ros_maps is not None:
                ros_maps.close()  # before the session it publishes on
            if ros is not None:
                ros.close()
            ingest.close()
            registry.close()
    finally:
        # Ignored, not given back their default action: the process ends once `run` returns, and a
        # signal in that last moment (the interpreter's exit takes ~50 ms) killed it, exit -15 / -1
        # instead of 0, after a clean stop: a repeated `kill`, a Ctrl-C pressed twice, systemd's
        # SendSIGHUP=.
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, signal.SIG_IGN)
    log.info("stopped")
    return 0


def _start_ros_maps(args: argparse.Namespace, registry: Any, ingest: ZenohIngest) -> Any:
    """The `RosMapPublisher` of the `--ros-publish-map` maps on the ingest's session, started; None
    when no map is published to ROS 2."""
    if not args.ros_publish_map:
        return None
    from fleetmap.ros.map_publisher import RosMapOptions, RosMapPublisher

    assert ingest.session is not None  # started
    options = RosMapOptions(
        topics=tuple(args.ros_publish_map),
        domain_id=ros_domain(args),
        frame_id=args.ros_map_frame or "map",
        map_frames=tuple((spec.map_id, ros_map_frame(args, spec.map_id)) for spec in args.ros_publish_map),
        period=args.ros_map_period,
        distro=args.ros_distro,
    )
    publisher = RosMapPublisher(registry, ingest.session, options)
    publisher.start()
    return publisher


def _configure_process(args: argparse.Namespace) -> None:
    """What `serve` sets for the whole process before anything starts: the log, Zenoh's own log,
    the GIL's switch interval."""
    configure_logging(str(args.log_level), str(args.log_format))
    # Zenoh's own log: refused TLS handshakes and wrong passwords show there (RUST_LOG=warn for more).
    import zenoh

    zenoh.init_log_from_env_or("error")
    # Integration workers hold the map lock while they apply a scan; under HTTP load they wait for
    # the GIL to come back to them. A shorter switch interval hands it over sooner (about halved the
    # scans dropped under read load in the service benchmark).
    sys.setswitchinterval(0.0005)


def _zenoh_status(
    ingest: ZenohIngest, ros: RosScanIngest | None, ros_maps: Any
) -> Callable[[], dict[str, Any]]:
    """`GET /healthz`'s `zenoh`: the session's status, with the ROS ingest's under `ros` and the ROS
    map publisher's under `ros_maps`."""
    if ros is None and ros_maps is None:
        return ingest.status

    def status() -> dict[str, Any]:
        parts = ingest.status()
        if ros is not None:
            parts["ros"] = ros.status()
        if ros_maps is not None:
            parts["ros_maps"] = ros_maps.status()
        return parts

    return status


def _start_ros(
    args: argparse.Namespace, options: _StartOptions, registry: MapRegistry, ingest: ZenohIngest
) -> RosScanIngest | None:
    """The ROS 2 scan ingest on the service's Zenoh session (`--ros-scans`), started; None without."""
    if options.ros is None:
        return None
    from fleetmap.ros.ingest import RosScanIngest

    assert ingest.session is not None  # started
    domain, frame = options.ros
    ros = RosScanIngest(registry, ingest.session, args.ros_scans, domain_id=domain, fixed_frame=frame)
    try:
        ros.start()
    except zenoh.ZError as exc:
        raise CliError(f"cannot subscribe to ROS 2 topics: {exc}") from None
    return ros


class _StartOptions(NamedTuple):
    """What `run` starts from, read from the options by `_checked_options`."""

    host: str
    port: int  # 0: any free port
    default_config: MapConfig  # of maps created automatically (--config)
    create_app: Any  # fleetmap.api.app's, and ...
    settings_cls: Any  # ... its ApiSettings (`_load_api`)
    tokens: TokenSet | TokenFile | None
    ros: tuple[int, str] | None  # --ros-scans' (domain id, fixed frame)


def _checked_options(args: argparse.Namespace) -> _StartOptions:
    """What `run` starts from, after the checks of the options that need no socket or storage (the
    input limits are set for the process here). Raises CliError."""
    host, port = parse_http(args.http)
    default_config = load_config(args.config)
    create_app, settings_cls = _load_api()
    if not (args.world_bound > 0 and args.max_range > 0):
        raise CliError("--world-bound and --max-range must be positive")
    configure_limits(InputLimits(args.world_bound, args.max_beams, args.max_range))
    topics = [spec.topic for spec in args.ros_publish_map]
    if len(set(topics)) < len(topics):
        raise CliError("--ros-publish-map: two maps on one ROS topic; give each its own (MAP_ID=TOPIC)")
    if topics:
        ros_domain(args)  # a bad $ROS_DOMAIN_ID stops the start here, not once Zenoh runs
    elif (args.ros_map_frame, args.ros_map_period, args.ros_distro) != ROS_MAP_DEFAULTS:
        # Given for nothing: most likely --ros-publish-map was forgotten (or its variable unset).
        raise CliError("--ros-map-frame, --ros-map-period and --ros-distro need --ros-publish-map MAP_ID")
    tokens = _load_tokens(args.auth_tokens)
    if tokens is None and args.require_read_token:
        # Without tokens there is nothing to check: reads were served to anyone, silently.
        raise CliError(
            "--require-read-token needs API tokens, or reading stays open to anyone: give "
            "--auth-tokens FILE (or $FLEETMAP_TOKENS)"
        )
    if tokens is None and not _is_loopback(host) and not args.insecure:
        raise CliError(
            f"refusing to serve {host} without API tokens: anyone on the network could change the "
            "maps. Give --auth-tokens FILE (or $FLEETMAP_TOKENS), or --insecure to accept that"
        )
    ros = ros_options(args)
    return _StartOptions(host, port, default_config, create_app, settings_cls, tokens, ros)


def _open_storage(args: argparse.Namespace, sock: socket.socket) -> DurableStore | None:
    """The data directory's store (None with --in-memory). Raises CliError, `sock` closed, if it
    cannot be used."""
    if args.in_memory:
        return None
    try:
        return DurableStore(Path(args.data_dir), snapshot_interval=args.snapshot_interval)
    except StorageError as exc:
        sock.close()
        raise CliError(str(exc)) from None


def _warm_engine() -> None:
    """`warm_up`, said in the log: the first start after an install compiles the kernels (10-30 s,
    silent otherwise)."""
    log.info(
        "loading the engine's compiled kernels (the first start after an install compiles them: about "
        "15 s, a minute or two on a busy machine; later starts load them from disk)"
    )
    started = time.perf_counter()
    warm_up()
    log.info("engine ready in %.1f s", time.perf_counter() - started)


def _log_protection(args: argparse.Namespace, tokens: TokenSet | TokenFile | None, durable: bool) -> None:
    """The start-up lines that say how the service is protected and bounded: API tokens, where
    maps are kept and their memory budget."""
    budget = args.max_memory
    source = f"file {args.auth_tokens}, read again on SIGHUP" if args.auth_tokens else "$FLEETMAP_TOKENS"
    log.info(
        "API tokens: %s",
        f"required to write{' and read' if args.require_read_token else ''} ({source})" if tokens
        else "NONE: anyone who can reach the API may change maps (loopback only unless --insecure)",
    )  # fmt: skip
    log.info(
        "maps: %s; their tiles within %s (%.0f MiB held)",
        f"durable in {Path(args.data_dir).resolve()}" if durable else "in memory only (--in-memory)",
        "no limit" if budget.limit is None else f"{budget.limit / 2**20:.0f} MiB (--max-memory)",
        budget.used / 2**20,
    )  # fmt: skip


def _trusted_proxies(addresses: list[str] | None) -> list[str] | str | None:
    """uvicorn's `forwarded_allow_ips` for `--forwarded-allow-ips ADDRESS ...` (`_proxy_address`):
    None, uvicorn's own default ($FORWARDED_ALLOW_IPS, else 127.0.0.1), when not given; `*` when one
    of them is `*` (uvicorn trusts every client only for `*` alone: in a list, `*` was ignored)."""
    if addresses is not None and "*" in addresses:
        return "*"
    return addresses


def _http_server(args: argparse.Namespace, app: Any, url: str, zenoh_endpoints: Sequence[str]) -> Any:
    """The uvicorn server of `app` with fleetmap's connection limits and log, its ready line set;
    logs the HTTP limits and address."""
    import uvicorn

    max_connections = connection_limit(args.max_http_connections, raise_descriptor_limit())
    log.info(
        "HTTP: at most %d connections; request heads within %g s, bodies within %g s",
        max_connections, args.http_head_timeout, args.http_body_timeout,
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
        http=bounded_http_protocol(max_connections, args.http_head_timeout, args.http_body_timeout),
        backlog=ACCEPT_BACKLOG,
        forwarded_allow_ips=_trusted_proxies(args.forwarded_allow_ips),
    )
    if args.access_log:  # (log_level above set its level too)
        logging.getLogger("uvicorn.access").setLevel(logging.INFO)
    server = _http_server_class()(config)
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


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m fleetmap.server [serve options]`: the same as `fleetmap serve`."""
    parser = argparse.ArgumentParser(prog="fleetmap")
    sub = parser.add_subparsers(dest="command", required=True)
    add_parser(sub)
    args = parse_command_line(parser, sub, ["serve", *(sys.argv[1:] if argv is None else argv)])
    return run_command(args)


if __name__ == "__main__":
    sys.exit(main())
