"""`fleetmap serve`'s command line: the parser of its options (`add_serve_parser`), each option's
default and help, and the argparse `type`s that check a value as it is parsed (`_path`, `_map_id`,
`_int_between`, `_http_address`, ...), so that a bad value stops the start with one line
naming the option. Every option is also read from its FLEETMAP_ variable (`serve_environment`).
What the options then start is `server.run`'s."""

from __future__ import annotations

import argparse
import ipaddress
import re
from collections.abc import Callable, Mapping
from typing import Any, NoReturn, TypeVar

from fleetmap.cli import CliError
from fleetmap.codec import InputLimits
from fleetmap.failed_signins import DEFAULT_MAX_FAILURES, DEFAULT_WINDOW
from fleetmap.http_limits import RESERVED_DESCRIPTORS
from fleetmap.log_format import LOG_FORMATS
from fleetmap.memory_budget import DEFAULT_SHARE, RESERVED, MemoryBudget, parse_size
from fleetmap.metrics import ROBOT_SERIES_IDLE
from fleetmap.persistence import SNAPSHOT_INTERVAL, SNAPSHOT_ROWS
from fleetmap.ros.transforms import TfError, normalize_frame
from fleetmap.scan import MAX_BEAMS
from fleetmap.serve_environment import RepeatedOption, environment_first, one_line_error
from fleetmap.wire import check_endpoint_form, is_valid_id
from fleetmap.zenoh_ingest import DEFAULT_LISTEN

DEFAULT_HTTP = "127.0.0.1:8000"
DEFAULT_DATA_DIR = "./fleetmap-data"
LOG_LEVELS = ("debug", "info", "warning", "error")
#: The defaults of --ros-map-frame, --ros-map-period and --ros-distro (any other value needs
#: --ros-publish-map). The frame's None: --ros-fixed-frame's for the map of --ros-scans, else map
#: (`serve_ros.ros_map_frame`).
ROS_MAP_DEFAULTS = (None, 1.0, "jazzy")


def add_serve_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> argparse.ArgumentParser:
    """Add the `serve` subcommand and its options to the `fleetmap` command line (what it runs is
    set by `server.add_parser`)."""
    p = sub.add_parser(
        "serve",
        help="run the service: Zenoh ingest from robots, REST API and web viewer",
        exit_on_error=False,  # environment_first reports errors, naming a variable at fault
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
        type=_http_address,
        default=DEFAULT_HTTP,
        metavar="HOST:PORT",
        help=f"address of the REST API and web viewer (default {DEFAULT_HTTP}; port 0 picks a free port)",
    )
    p.add_argument(
        "--zenoh-listen",
        nargs="+",
        type=_zenoh_endpoint,
        action=RepeatedOption,
        metavar="ENDPOINT",
        help=(
            f"Zenoh endpoints robots connect to (default {' '.join(DEFAULT_LISTEN)}; with --zenoh-connect "
            "the default is not to listen; port 0 picks a free port, which the log and /healthz give)"
        ),
    )
    p.add_argument(
        "--zenoh-connect",
        nargs="+",
        type=_zenoh_endpoint,
        action=RepeatedOption,
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
            f"memory this process may use (its cgroup's limit, else the machine's), leaving at least "
            f"{RESERVED >> 30} GiB for the rest of the service (a quarter of less than 4/3 GiB); "
            "'none': no limit"
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
        help=(
            "serve without API tokens beyond this machine: bind HTTP to a non-loopback address, and "
            "answer requests whose Host names another machine (a proxy's)"
        ),
    )
    limits = InputLimits()
    p.add_argument(
        "--world-bound",
        type=_positive_metres,
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
        type=_positive_metres,
        default=limits.max_range,
        metavar="M",
        help=f"readings at or beyond this (metres) are 'no return' (default {limits.max_range:g})",
    )
    p.add_argument(
        "--cors-origin",
        nargs="+",
        action=RepeatedOption,
        default=[],
        type=_cors_origin,
        metavar="ORIGIN",
        help="origins allowed to call the API from a browser (CORS), as a browser sends them "
        "(https://viewer.example, http://localhost:5173: no path), matched exactly ('*': any); "
        "default none",
    )
    p.add_argument(
        "--forwarded-allow-ips",
        nargs="+",
        action=RepeatedOption,
        type=_proxy_address,
        default=None,
        metavar="IP",
        help="addresses (or networks, 10.0.0.0/8) of the reverse proxies whose X-Forwarded-Proto / "
        "-For headers are trusted (the session cookie's Secure, the access log's client), separated "
        "by spaces; '*': any; default 127.0.0.1 and ::1, or uvicorn's $FORWARDED_ALLOW_IPS",
    )
    p.add_argument(
        "--root-path",
        type=_root_path,
        default="",
        metavar="PREFIX",
        help="the path under which a reverse proxy serves the service, stripping it from the requests "
        "it passes on (/fleetmap for https://host/fleetmap/ proxied to the service's root): the "
        "Location of a made map, /docs, the session cookie's Path and the OpenAPI servers then "
        "name it; default none (served at the root)",
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
            "seconds of silence after which an event stream sends a ': keepalive' comment, or a "
            "keepalive event (?keepalive=event, the web viewer's) (default 15): shorter than the "
            "idle timeout of any proxy in front; clients take a stream silent for a few of these "
            "as broken (the Python client and the web viewer: 45 s) and resume it"
        ),
    )
    p.add_argument(
        "--metrics-robot-idle",
        type=_seconds_between(1.0, 366 * 86400.0),
        default=ROBOT_SERIES_IDLE,
        metavar="S",
        help=(
            "seconds after a robot was last heard that its counters leave /metrics, unless it is "
            "online (default 3600): robot ids that come and go must not grow every scrape for good; "
            "its fleetmap_robot_online stays while the map keeps the robot, and its counters come "
            "back when it is heard again"
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
            f"lowered to leave {RESERVED_DESCRIPTORS} of the process's file descriptors to Zenoh and "
            "storage, and robots' Zenoh sessions theirs)"
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
            "answer 408 and close a connection whose request body has not all arrived this many seconds "
            "after its headers (default 60: a 16 MiB body at 2.2 Mbit/s)"
        ),
    )
    p.add_argument(
        "--http-send-timeout",
        type=_seconds_between(0.1, 3600.0),
        default=60.0,
        metavar="S",
        help=(
            "drop a connection whose client has read nothing of its answer for this many seconds while "
            "the answer waits on it (default 60: a snapshot download's client that stops reading "
            "would hold one of the 4 download slots for ever)"
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
        action=RepeatedOption,
        type=_map_topic,
        default=[],
        metavar="MAP_ID[=TOPIC]",
        help=(
            "publish this map to ROS 2 (rmw_zenoh) as a nav_msgs/msg/OccupancyGrid on TOPIC (default "
            "/map), as nav2's map_server does (TRANSIENT_LOCAL), and its changes as "
            "map_msgs/msg/OccupancyGridUpdate on TOPIC_updates (a whole grid when the map grew), on the "
            "service's Zenoh session; repeatable (see docs/ros.md). Off by default"
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
    # Replaced on this one parser instance. mypy refuses assigning to a method, and compares the
    # function to the method unbound (with its self).
    p.error = _one_line_error(p)  # type: ignore[method-assign,assignment]
    p.parse_known_args = environment_first(p)  # type: ignore[method-assign]
    return p


def _one_line_error(parser: argparse.ArgumentParser) -> Callable[[str], NoReturn]:
    """`parser.error` that prints one line (`one_line_error`), not argparse's usage first."""

    def error(message: str) -> NoReturn:
        one_line_error(parser, message)

    return error


def _map_topic(text: str) -> Any:
    """An argparse `type` for `--ros-publish-map`: `MAP_ID[=TOPIC]` as a `MapTopic`."""
    from fleetmap.ros.map_publisher import parse_map_topic

    try:
        return parse_map_topic(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


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


#: uvicorn's own variable of the proxies it trusts (entries separated by commas), which `fleetmap
#: serve` reads when neither --forwarded-allow-ips nor $FLEETMAP_FORWARDED_ALLOW_IPS is given.
UVICORN_PROXIES_ENV = "FORWARDED_ALLOW_IPS"


def proxies_of_uvicorns_variable(environ: Mapping[str, str]) -> list[str] | None:
    """The proxies of uvicorn's $FORWARDED_ALLOW_IPS, checked and written as --forwarded-allow-ips'
    are (`_proxy_address`), or None when it is not set. It went to uvicorn as it was, which takes an
    entry it cannot parse as a name no connection's address equals: a host name, a typo, a network
    with host bits set (`10.0.0.5/8`, which the option takes), and `*` among other entries as
    nothing. The proxy was then silently not trusted (its `https` ignored, the session cookie set
    without `Secure`), though docs/api.md names the variable. Raises CliError naming it."""
    text = environ.get(UVICORN_PROXIES_ENV)
    if text is None:
        return None
    proxies = []
    for entry in (part.strip() for part in text.split(",")):
        if not entry:  # `a,` or an empty variable: uvicorn's literal "" matches no address either
            continue
        try:
            proxies.append(_proxy_address(entry))
        except argparse.ArgumentTypeError as exc:
            raise CliError(f"${UVICORN_PROXIES_ENV}={text!r}: {exc}") from None
    return proxies


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


#: A path prefix as `--root-path` takes it: `/` and segments of the characters a URL's path may hold
#: as they are (RFC 3986, 3.3), a percent-encoded byte included.
_ROOT_PATH = re.compile(r"^(/([A-Za-z0-9._~!$&'()*+,;=:@-]|%[0-9A-Fa-f]{2})+)+$")


def _root_path(text: str) -> str:
    """An argparse `type` for `--root-path`: a path prefix (`/fleetmap`, `/a/b`), written without its
    trailing `/`, or empty (`/` too: served at the root). It is put before every path the service
    names (uvicorn adds it to each request's path, as ASGI's root_path), so it must be a URL path as
    it is sent: uvicorn encodes it as ASCII for every request, and a character outside ASCII failed
    every one."""
    text = text.strip().rstrip("/")
    if not text or _ROOT_PATH.match(text):
        return text
    message = f"expected a URL path such as /fleetmap, got {text!r}"
    if not text.startswith("/"):
        message += " (a path starts with '/')"
    elif "//" in text:
        message += " (no empty segment: '//')"
    elif any(c in text for c in "?#"):
        message += " (a path only: no query or fragment)"
    else:
        message += " (characters other than letters, digits and -._~!$&'()*+,;=:@ are percent-encoded)"
    raise argparse.ArgumentTypeError(message)


#: An origin as a browser sends it in `Origin` (RFC 6454, 6.2): a scheme, `://`, a host (a name, or
#: an IPv6 address in brackets) and a port, in lower case, with nothing after.
_ORIGIN = re.compile(r"^[a-z][a-z0-9+.-]*://(\[[0-9a-f:.]+\]|[a-z0-9._~-]+)(:[0-9]{1,5})?$")
#: Ports a browser leaves out of an origin: the scheme's default.
_DEFAULT_PORTS = {"http": 80, "https": 443}


def _cors_origin(text: str) -> str:
    """An argparse `type` for `--cors-origin`: `*`, or an origin as a browser sends it in its
    `Origin` header. The CORS middleware compares that header with each value as it is, so a value
    no browser sends never matched, and nothing said so: `https://viewer.example/` (with the slash
    an address bar shows), `viewer.example` (no scheme), `https://Viewer.example`, or
    `https://viewer.example:443` (browsers leave the default port out) let no page in.

    `null` is refused too, though browsers send it: it is the origin of every sandboxed frame
    (`<iframe sandbox>`), `data:` page and local file, which any site can make, so allowing it let
    every site's pages call the API (read, and write without tokens) while it looked like no site."""
    text = text.strip()
    if text == "*":
        return text
    if text == "null":
        raise argparse.ArgumentTypeError(
            "expected an origin as a browser sends it (https://viewer.example:8443) or '*', got 'null' "
            "(the origin of sandboxed frames, data: pages and local files, which any site can make: it "
            "would let every site in; give '*' if that is meant)"
        )
    match = _ORIGIN.match(text)
    scheme, _, rest = text.partition("://")
    port = match.group(2) if match else None
    if match and not (port and (int(port[1:]) > 65535 or _DEFAULT_PORTS.get(scheme) == int(port[1:]))):
        return text
    message = f"expected an origin as a browser sends it (https://viewer.example:8443) or '*', got {text!r}"
    if not rest:
        message += " (an origin starts with its scheme: https://...)"
    elif any(c in rest for c in "/?#"):
        message += " (an origin has nothing after its host and port, not even a '/')"
    elif text != text.lower():
        message += " (browsers send it in lower case)"
    elif port and int(port[1:]) <= 65535:
        message += f" (browsers leave the default port {port[1:]} of {scheme} out)"
    raise argparse.ArgumentTypeError(message)


def _positive_metres(text: str) -> float:
    """An argparse `type` for `--world-bound` and `--max-range`: a distance above 0 (inf: no bound).
    Checked once parsed, the two shared one message, "--world-bound and --max-range must be
    positive", which named neither the one at fault, nor its value, nor its FLEETMAP_ variable."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of metres, got {text!r}") from None
    if not value > 0:  # NaN fails too
        raise argparse.ArgumentTypeError(f"must be a number of metres above 0, got {text}")
    return value


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
    """(host, port) of `HOST:PORT`, `[IPV6]:PORT` or `:PORT` (all interfaces). Raises CliError
    naming `--http` (the demo's option; `serve`'s is checked as it is parsed, `_http_address`)."""
    try:
        return _split_http(text)
    except ValueError as exc:
        raise CliError(f"--http {text!r}: {exc}") from None


def _http_address(text: str) -> str:
    """An argparse `type` for `--http`: `text` if `parse_http` takes it. Checked once parsed, a bad
    $FLEETMAP_HTTP (the Docker image sets it) was refused as "--http 'localhost': ...", naming an
    option the command line did not hold, where every other variable is named as itself."""
    try:
        _split_http(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{exc}, got {text!r}") from None
    return text


def _zenoh_endpoint(text: str) -> str:
    """An argparse `type` for `--zenoh-listen` / `--zenoh-connect`: `text` unless
    `wire.check_endpoint_form` refuses it (a URL, or no port). Checked by the ingest only once the
    service had loaded every map (minutes, for big ones), after which `tcp/127.0.0.1` failed with
    Zenoh's "invalid socket address", naming no endpoint."""
    try:
        check_endpoint_form(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def _split_http(text: str) -> tuple[str, int]:
    """`parse_http`'s (host, port); ValueError saying what is wrong, without the value."""
    host, sep, port_text = text.rpartition(":")
    if not sep or not port_text.isdigit():
        raise ValueError("expected HOST:PORT, e.g. 127.0.0.1:8000")
    port = int(port_text)
    if port > 65535:
        raise ValueError("port must be at most 65535")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    return host or "0.0.0.0", port
