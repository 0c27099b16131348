"""Zenoh ingest: the service's own Zenoh session, subscribed to every robot's scans and liveliness.

`ZenohIngest` opens one Zenoh session for the service and hands every scan sample to the
`MapRegistry`. The subscriber callback runs on a Zenoh thread, so it must never block and never
integrate: it parses the key, decodes the payload and calls `MapRegistry.submit`, which checks the
sequence number and puts the scan on a bounded per-robot queue without waiting (a full queue refuses
the NEWEST scan and counts it as `dropped` on the robot; of an advanced publisher, it defers it, and
`BacklogRefetch` fetches it again from the publisher's cache once there is room: `backlog_refetch.py`).
Integration happens on the registry's worker threads.

Decoding happens in the callback because it is cheap and never waits: measured on the development
machine, a 1081-beam scan decodes in about 11 us (binary) and 80 us (JSON, pydantic-validated); the
whole callback takes about 20 us / 90 us (median). That is far below the 1 ms at which a separate
decode pool (which would then have to restore per-robot order) would pay off. Zenoh delivers the
samples of one connection one at a time, in order, so each robot's scans reach `submit` in
publication order.

Session set-up (`start`):

1. The JSON5 file `config_file`, if given, is loaded first (`load_config_file`).
2. The constructor's arguments are applied on top of it:
   - `mode`: given explicitly, it wins. Otherwise the file's `mode` if the file sets one; otherwise
     `router` when there are no `connect` endpoints (the service IS the network: robots connect to it
     in client mode, no zenohd needed); with `connect` endpoints the service joins an existing network,
     as a `peer` when it also listens (robots may then connect to it directly, and the network's
     router(s) reach it over the connect link), or as a `client` of that network's router when it
     does not listen.
   - `listen`: given (a list, possibly empty), it wins. `None` keeps the file's endpoints if the file
     sets them (a list, or per mode: the service's mode's), else `DEFAULT_LISTEN` without `connect`
     endpoints and no listening with them.
   - `connect`: non-empty, it replaces the file's.
   - multicast scouting is switched off (robots find the service by its endpoint), unless the file
     sets `scouting/multicast/enabled` itself.
   - `connect/retry` is `CONNECT_RETRY` (a lost router is tried again every 0.5 s at most, not
     Zenoh's 4 s), unless the file sets it.
   - a router without `connect` endpoints gets `scouting/delay` 0, unless the file sets it: Zenoh's
     0.5 s between listening and returning from `zenoh.open` let robots connect before the scan
     subscriber existed, and the subscriber's history then fetched their caches twice at once and
     lost part of them (see "Recovered samples" below).
   - timestamping is switched off, unless the file sets `timestamping/enabled` itself for the
     session's mode (then a warning says why it should not; see below). Set per mode for other
     modes only, it is switched off for this one (Zenoh's default would be on for a router).
3. A scan subscriber on `fleetmap/*/*/scan`, a liveliness subscriber (with history, so robots
   already online are reported) on `fleetmap/*/*/alive` and a queryable on `fleetmap/*/*/delivery`
   are declared. The queryable answers a robot what became of its scans (`MapRegistry.
   delivery_status`, a `fleetmap.wire.DeliveryStatus` as JSON; docs/protocol.md, "Delivery
   confirmation"): `ScanPublisher.flush` asks it whether every scan it published is in the map.

The scan subscriber is zenoh-ext's ADVANCED subscriber, so that robots publishing with an advanced
publisher (`ScanPublisher`'s `backlog`: a cache of its last scans and heartbeats) lose no scan to a
dead zone or a restart of this service (docs/protocol.md, "Delivery guarantees"):

- `history` with `detect_late_publishers`: when the subscriber starts, and whenever a robot's
  publisher appears (a robot that connects, or reconnects after its link died), what that
  publisher's cache holds is fetched. After a restart of the service that includes scans the
  previous process had integrated already: the registry's per-robot seq bookkeeping, which survives a
  restart with persistence, ignores them as duplicates (`zenoh.rejected.duplicate`);
- `recovery` by heartbeat: a publisher announces its last sample's sequence number every heartbeat,
  so that samples lost in flight (a link that died under them) are fetched from its cache;
- `subscriber_detection`: publishers see this subscriber (a liveliness token) and know to send to it.

Recovered samples of one publisher reach the callback in publication order, without duplicates,
before its newer ones, except for a publisher already connected when the subscriber is declared:
its cache is fetched twice at once (the initial query, and the one for each publisher detected),
and zenoh-ext (1.10) then skipped a run of its samples, unreported (tests/test_crash_exactly_once.py
lost 6-450 scans of a robot in about half of its runs of 10 restarts). Hence no `scouting/delay`.
Samples that could not be recovered (no longer in the publisher's cache) are
reported by zenoh-ext's sample miss listener: counted in `unrecoverable` (`/healthz`
`zenoh.unrecoverable`, `/metrics` `fleetmap_zenoh_scans_unrecoverable_total`) and logged,
rate-limited; the registry counts them as `lost` on the robot anyway once a later seq arrives. Plain
publishers (`session.put`, `declare_publisher`, any language, `backlog=0`) reach the advanced
subscriber like a plain one: their samples are delivered live, with their encoding and attachment,
and nothing is recovered for them. That holds only while the service's session does not timestamp
samples, which a Zenoh router does by default: the advanced subscriber orders samples without a
sequence number by their timestamp, per timestamp source, and drops one older than the last it
delivered; the router's one clock stamps every robot's samples on several receiving threads, so with
robots publishing at once some samples are delivered after a later-stamped one and dropped, silently
(measured: 6 plain publishers of 2000 samples each lost 7 to 21 samples each, none with
timestamping off; and 1 scan in about 5 runs of tests/test_durability.py's kill -9 test).

Failures to open (an endpoint in use, a malformed endpoint, a config file that does not parse, a
client with nothing to connect to) raise `IngestStartError` with a readable message.
"""

from __future__ import annotations

import contextlib
import json
import logging
import re
import resource
import socket
import threading
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import zenoh
import zenoh.ext

from fleetmap import codec
from fleetmap.backlog_refetch import BacklogRefetch, Origin
from fleetmap.map_entry import DEFERRED, IngestRejected
from fleetmap.network import is_loopback_host
from fleetmap.rate_limited_log import RateLimitedLog
from fleetmap.registry import InvalidId, MapRegistry
from fleetmap.shown_endpoint import shown_endpoints
from fleetmap.wire import (
    ALIVE_KEY_WILDCARD,
    CONNECT_RETRY,
    DEFAULT_ENDPOINT,
    DELIVERY_ERROR_ENCODING,
    DELIVERY_FIELDS_1_EXCLUDE,
    DELIVERY_FIELDS_PARAMETER,
    DELIVERY_KEY_WILDCARD,
    DELIVERY_SESSION_PARAMETER,
    JSON_ENCODING,
    SCAN_KEY_WILDCARD,
    SESSION_LIMIT,
    check_endpoint_form,
    is_valid_id,
    shown_config_path,
    zenoh_error_text,
)

# The logger keeps the module's first name: log configurations and filters in use name it.
log = logging.getLogger("fleetmap.ingest")

#: Where the service listens when nothing else is said: loopback only, Zenoh's usual port.
DEFAULT_LISTEN: tuple[str, ...] = (DEFAULT_ENDPOINT,)
#: Zenoh session modes.
MODES = ("router", "peer", "client")


class IngestStartError(RuntimeError):
    """The Zenoh session could not be opened; the message says why (no Rust source locations)."""


#: A listen endpoint on port 0 of an IP link (`tcp/127.0.0.1:0`, `udp/[::1]:0#iface=lo`): the
#: protocol, the host as written, and what follows the port.
_PORT_ZERO = re.compile(r"(tcp|udp|tls|quic)/(\[[^\]]*\]|[^/:?#\[\]]+):0((?:[?#].*)?)")


def with_free_port(endpoint: str) -> str:
    """`endpoint` with port 0 replaced by a port of its host free now (the operating system's pick,
    as for `--http HOST:0`); any other endpoint as it is. Zenoh, given port 0, listens on a port of
    its choosing but reports it nowhere (neither its API nor its log), so the service's start-up
    line, its ready line and /healthz said `tcp/127.0.0.1:0`, which no robot can connect to. A host
    that cannot be bound is left to Zenoh, whose error names it."""
    match = _PORT_ZERO.fullmatch(endpoint)
    if match is None:
        return endpoint
    protocol, host, rest = match.groups()
    address = host.strip("[]")
    family = socket.AF_INET6 if ":" in address else socket.AF_INET
    kind = socket.SOCK_DGRAM if protocol in ("udp", "quic") else socket.SOCK_STREAM
    try:
        with socket.socket(family, kind) as probe:
            probe.bind((address, 0))
            port = probe.getsockname()[1]
    except OSError:
        return endpoint
    return f"{protocol}/{host}:{port}{rest}"


#: Zenoh link protocols whose endpoints can authenticate the other side: with mutual TLS
#: (`transport/link/tls/enable_mtls`) a robot must present a certificate. Without it, TLS encrypts
#: but the service accepts any robot (docs/security.md).
_CERTIFICATE_PROTOCOLS = frozenset({"tls", "quic"})


def asks_for_passwords(cfg: zenoh.Config) -> bool:
    """Whether `cfg`'s user / password authentication (`transport/auth/usrpwd`) is on: the session has
    a user of its own, or a dictionary file that holds a user. Zenoh (1.10.2) turns it off when the
    dictionary holds none (an empty file, or blank lines only, as one made before its users were
    added) and the session has no user: a robot without credentials is then let in. A dictionary that
    cannot be read now counts as on: Zenoh read it when the session opened (a file it could not read
    stopped the start), and it is not for this check to say otherwise."""
    usrpwd = json.loads(cfg.get_json("transport/auth/usrpwd"))
    if not isinstance(usrpwd, dict):
        return False
    if usrpwd.get("user"):
        return True
    dictionary = usrpwd.get("dictionary_file")
    if not dictionary:
        return False
    try:
        text = Path(dictionary).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return True
    return any(line.strip() for line in text.splitlines())


def unauthenticated_endpoints(listen: Sequence[str], cfg: zenoh.Config) -> list[str]:
    """The endpoints of `listen` that anyone beyond this host may connect to without credentials:
    not loopback, and neither TLS / QUIC with mutual TLS, in a configuration without user /
    password authentication (`asks_for_passwords`: a dictionary file without users asks for none)."""
    if asks_for_passwords(cfg):
        return []
    mtls = json.loads(cfg.get_json("transport/link/tls/enable_mtls")) is True
    found = []
    for endpoint in listen:
        protocol, _, address = endpoint.partition("/")
        host = address.split("#", 1)[0].rpartition(":")[0].strip("[]")
        local = protocol in ("unixsock-stream", "unixpipe") or is_loopback_host(host)
        if not (local or (mtls and protocol in _CERTIFICATE_PROTOCOLS)):
            found.append(endpoint)
    return found


def parse_key(key: str, suffix: str) -> tuple[str, str] | None:
    """(map_id, robot_id) of `fleetmap/<map_id>/<robot_id>/<suffix>`, or None if the key is not
    exactly that with two valid ids."""
    parts = key.split("/")
    if len(parts) != 4 or parts[0] != "fleetmap" or parts[3] != suffix:
        return None
    map_id, robot_id = parts[1], parts[2]
    if not (is_valid_id(map_id) and is_valid_id(robot_id)):
        return None
    return map_id, robot_id


class ZenohIngest:
    """The service's Zenoh session, feeding scans and liveliness into a `MapRegistry`.

    Contract: after `start()`, every scan sample (a put: a delete carries no scan and is ignored) on
    `fleetmap/<map>/<robot>/scan` is either submitted to the registry or counted (globally in
    `status()`, and on the robot through the registry where the ids are valid) with a rate-limited
    log line saying why. `close()` undeclares the subscribers
    and closes the session. Both are idempotent. Zenoh may still run a scan callback for a moment
    after the session closed (seen at a SIGTERM during a robot's cache fetch): what it submits then,
    the closing registry refuses without recording it (`MapRegistry.submit`, `shutting_down`), so
    the robot's cache sends it again to the next process.
    """

    def __init__(
        self,
        registry: MapRegistry,
        *,
        listen: Sequence[str] | None = None,
        connect: Sequence[str] = (),
        config_file: str | Path | None = None,
        mode: str | None = None,
        shared_memory: bool = False,
        session_limit: int | None = None,
    ) -> None:
        if mode is not None and mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
        self.registry = registry
        self._listen_arg = None if listen is None else list(listen)
        self.connect = list(connect)
        self.config_file = Path(config_file) if config_file is not None else None
        #: Zenoh's shared-memory transport for robots on this host. Off by default: it maps a 16 MiB
        #: pool per local robot (430 MiB of RSS for 25 robots) and delayed each robot's first samples
        #: by up to 250 ms, while loopback TCP carries a 4 KB scan in microseconds.
        self.shared_memory = shared_memory
        #: The most sessions the process's file descriptors hold (`http_limits.zenoh_session_limit`):
        #: the configuration's `transport/unicast/max_sessions` is lowered to it, with a warning.
        self.session_limit = session_limit
        self._mode_arg = mode
        # Resolved by start(): what the session actually uses.
        self.mode: str | None = None
        self.listen: list[str] = []
        self._session: zenoh.Session | None = None
        self._subscribers: list[Any] = []
        self._closed = False
        self._lock = threading.Lock()  # guards the counters and `_alive`
        self._alive: set[tuple[str, str]] = set()  # robots whose liveliness token is present
        self.messages_received = 0
        self.scans_submitted = 0
        self.invalid_keys = 0
        self.decode_errors = 0
        self.rejected: Counter[str] = Counter()  # submit refusals by kind: duplicate, queue_full, ...
        #: Scans that advanced publishers published but zenoh-ext could not recover (the sample miss
        #: listener's `Miss.nb`, summed): gone from the publisher's cache before they could be fetched.
        self.unrecoverable = 0
        #: Samples of advanced publishers the full queue deferred, or held back behind a deferred
        #: one, to be fetched again from their publisher's cache (`backlog_refetch.py`).
        self.deferred = 0
        self._refetch = BacklogRefetch(self._queue_room, self._handle_fetched, self._count_unrecoverable)
        self.liveliness_events = 0
        self.delivery_queries = 0  # delivery queries answered (errors included)
        #: The Zenoh ids of the unicast sessions connected to this one now (robots; with
        #: `--zenoh-connect`, routers and peers too), kept by `_on_transport`; and the most the
        #: session accepts, its `transport/unicast/max_sessions` (set by `start`).
        self._sessions: set[str] = set()
        self.max_sessions: int | None = None
        #: How to accept more sessions, for the warning at the limit (`_bounded_sessions`).
        self._more_sessions = "raise it in the --zenoh-config file (docs/protocol.md)"
        self._log = RateLimitedLog(log)
        # Robots coming online and going offline: any Zenoh peer can declare and drop liveliness
        # tokens thousands of times a second (13000 lines a second were written, unbounded), so these
        # lines are rate-limited too, apart from the refusals' (a token flood must not hide them):
        # one line per robot and state per interval, and at most 100 in all per interval.
        self._alive_log = RateLimitedLog(log, max_lines=100)
        # Scans the full queue deferred: a line per robot, apart from the refusals' budget (a fleet's
        # backlogs deferred at once held back the warnings of scans that could not be fetched again).
        self._deferred_log = RateLimitedLog(log, max_lines=5)

    # -- lifecycle -------------------------------------------------------------------------------

    def build_config(self) -> zenoh.Config:
        """The session's configuration: the file, then the arguments on top (see the module doc).
        Sets `self.mode` and `self.listen`. Raises `IngestStartError`."""
        cfg = load_config_file(self.config_file) if self.config_file else zenoh.Config()
        file_mode = json.loads(cfg.get_json("mode"))
        file_listen = json.loads(cfg.get_json("listen/endpoints"))
        # Zenoh's built-in default is a per-mode dict: a list, or a dict other than that default,
        # means "the file chose endpoints". A dict gives each mode's own (Zenoh's own form): taken
        # as "no endpoints", the service listened on loopback alone, robots elsewhere kept out.
        if self.config_file is None or file_listen == json.loads(zenoh.Config().get_json("listen/endpoints")):
            file_listen = None
        if self._listen_arg is not None:
            listen = self._listen_arg
        elif isinstance(file_listen, list):
            listen = list(file_listen)
        elif isinstance(file_listen, dict):
            # The mode's own, as Zenoh picks them: the mode as decided below without endpoints to
            # go by (a peer's with `connect` endpoints and no mode said: a peer if it has any).
            mode_of_file = self._mode_arg or (str(file_mode) if file_mode is not None else None)
            mode_of_file = mode_of_file or ("router" if not self.connect else "peer")
            listen = list(file_listen.get(mode_of_file) or [])
        else:
            listen = [] if self.connect else list(DEFAULT_LISTEN)
        if twice := sorted({e for e in listen if listen.count(e) > 1 and _PORT_ZERO.fullmatch(e) is None}):
            # Zenoh opens a listener per endpoint, and the second failed with "Address already in
            # use", which sent the user after another process that was not there.
            raise IngestStartError(f"the listen endpoint {', '.join(twice)} is given twice: give each once")
        listen = [with_free_port(endpoint) for endpoint in listen]
        if self._mode_arg is not None:
            mode = self._mode_arg
        elif self.config_file is not None and file_mode is not None:
            mode = str(file_mode)
        elif not self.connect:
            mode = "router"
        else:
            mode = "peer" if listen else "client"
        if mode == "client" and listen:
            raise IngestStartError("a Zenoh client cannot listen; drop the listen endpoints or use peer mode")
        if mode == "client" and not self.connect:
            file_connect = json.loads(cfg.get_json("connect/endpoints"))
            if not file_connect:
                raise IngestStartError("Zenoh client mode needs connect endpoints")
        try:
            for endpoint in (*listen, *self.connect):
                check_endpoint_form(endpoint)
            cfg.insert_json5("mode", json.dumps(mode))
            cfg.insert_json5("listen/endpoints", json.dumps(listen))
            if self.connect:
                cfg.insert_json5("connect/endpoints", json.dumps(self.connect))
            if json.loads(cfg.get_json("scouting/multicast/enabled")) is None:  # the file did not say
                cfg.insert_json5("scouting/multicast/enabled", "false")
            if json.loads(cfg.get_json("connect/retry")) is None:  # used only with connect endpoints
                cfg.insert_json5("connect/retry", json.dumps(CONNECT_RETRY))
            if mode == "router" and not self.connect and json.loads(cfg.get_json("scouting/delay")) is None:
                # A router opens its listeners at once, then waits `scouting/delay` (0.5 s by
                # default) before `zenoh.open` returns: robots waiting for a restarted service
                # connected in that time, before the scan subscriber existed, and its history then
                # fetched their caches twice at once (once for every publisher, once for each one
                # detected), which lost part of a robot's cache. A router that connects to no one
                # has nothing to wait for.
                cfg.insert_json5("scouting/delay", "0")
            cfg.insert_json5("transport/shared_memory/enabled", json.dumps(self.shared_memory))
            timestamping = json.loads(cfg.get_json("timestamping/enabled"))
            if timestamping is None:  # the file did not say
                cfg.insert_json5("timestamping/enabled", "false")
            elif isinstance(timestamping, dict) and timestamping.get(mode) is None:
                # Said for other modes only: this mode's default (a router's: on) would apply.
                modes = {k: v for k, v in timestamping.items() if v is not None} | {mode: False}
                cfg.insert_json5("timestamping/enabled", json.dumps(modes))
            elif timestamping is True or (isinstance(timestamping, dict) and timestamping.get(mode)):
                log.warning(
                    "the Zenoh configuration sets timestamping/enabled: with timestamps from this "
                    "session, the scan subscriber may drop scans of plain publishers (robots without "
                    "a backlog) that several robots publish at once; see docs/protocol.md"
                )
        except (zenoh.ZError, ValueError) as exc:
            raise IngestStartError(f"invalid Zenoh endpoint: {zenoh_error_text(exc)}") from None
        self.mode, self.listen = mode, list(listen)
        return cfg

    def start(self) -> None:
        """Open the session and declare the subscribers. Raises `IngestStartError`."""
        if self._session is not None:
            return
        if self._closed:
            raise IngestStartError("this ingest was closed; create a new one")
        cfg = self.build_config()
        self.max_sessions = self._bounded_sessions(cfg)
        try:
            session = zenoh.open(cfg)
        except zenoh.ZError as exc:
            message = f"cannot open the Zenoh session ({self.mode}): {zenoh_error_text(exc)}"
            raise IngestStartError(message) from None
        self._session = session
        try:
            scans = zenoh.ext.declare_advanced_subscriber(
                session,
                SCAN_KEY_WILDCARD,
                self._on_scan,
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True),
                recovery=zenoh.ext.RecoveryConfig(periodic_queries=None, heartbeat=True),
                subscriber_detection=True,
            )
            self._subscribers.append(scans)
            self._subscribers.append(scans.sample_miss_listener(self._on_miss))
            # history=True: tokens declared before the service started are reported as PUTs too.
            self._subscribers.append(
                session.liveliness().declare_subscriber(ALIVE_KEY_WILDCARD, self._on_alive, history=True)
            )
            self._subscribers.append(
                session.declare_queryable(DELIVERY_KEY_WILDCARD, self._on_delivery_query)
            )
            # history=True: sessions that connected before it was declared count too.
            self._subscribers.append(
                session.info.declare_transport_events_listener(self._on_transport, history=True)
            )
        except zenoh.ZError as exc:
            self.close()
            raise IngestStartError(f"cannot subscribe: {zenoh_error_text(exc)}") from None
        self._refetch.start(session)
        log.info(
            "zenoh %s session %s listening on %s%s%s",
            self.mode,
            session.zid(),
            ", ".join(shown_endpoints(self.listen)) or "nothing",
            f", connecting to {', '.join(shown_endpoints(self.connect))}" if self.connect else "",
            "" if self.max_sessions is None else f"; at most {self.max_sessions} sessions (robots) at once",
        )
        open_endpoints = unauthenticated_endpoints(self.listen, cfg)
        if open_endpoints:
            # The REST API refuses to serve beyond loopback without tokens; Zenoh has no such check
            # of its own, and a plain endpoint took anyone's scans (and maps, with auto-create).
            log.warning(
                "zenoh listens on %s beyond loopback with neither mutual TLS nor a user / password: "
                "anyone who reaches it can publish scans (see docs/security.md)",
                ", ".join(shown_endpoints(open_endpoints)),
            )

    def _bounded_sessions(self, cfg: zenoh.Config) -> int | None:
        """The most sessions `cfg` lets the session accept, lowered (in `cfg`) to `session_limit`
        with a warning when that is fewer: a session past the descriptors took those HTTP needs."""
        configured = _max_sessions(cfg)
        limit = self.session_limit
        if limit is None or (configured is not None and configured <= limit):
            return configured
        cfg.insert_json5("transport/unicast/max_sessions", json.dumps(limit))
        self._more_sessions = "it was lowered to the open files limit: raise the service's hard ulimit -n"
        log.warning(
            "zenoh: at most %d Zenoh sessions (robots), not %s: this process may open %s files "
            "(ulimit -n), each session holds one, and HTTP needs its share; raise the hard limit for "
            "more robots (docs/protocol.md)",
            limit, configured, _open_files_limit(),
        )  # fmt: skip
        return limit

    def close(self) -> None:
        """Undeclare the subscribers and close the session. Idempotent."""
        self._closed = True
        subscribers, self._subscribers = self._subscribers, []
        for sub in reversed(subscribers):  # the miss listener before its subscriber
            with contextlib.suppress(zenoh.ZError):  # already gone with the session: nothing to undo
                sub.undeclare()
        session, self._session = self._session, None
        if session is not None:
            session.close()
        self._refetch.close()  # after the session, whose close ends its fetch in progress

    def __enter__(self) -> ZenohIngest:
        self.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    @property
    def session(self) -> zenoh.Session | None:
        return self._session

    @property
    def endpoints(self) -> list[str]:
        """What robots connect to: the listen endpoints, else (joined network) the connect ones."""
        return self.listen or self.connect

    # -- callbacks (Zenoh threads: never block) --------------------------------------------------

    def _on_scan(self, sample: zenoh.Sample) -> None:
        try:
            if sample.kind != zenoh.SampleKind.PUT:
                # A DELETE on a scan key (`publisher.delete()`) carries no scan: decoded as one, its
                # empty payload was counted as the robot's refused scan, and its reason ("a payload
                # starting b'' is neither a binary scan ...") replaced the robot's real last_error.
                return
            key = str(sample.key_expr)
            with self._lock:
                self.messages_received += 1
            self._handle_scan(key, sample.payload, str(sample.encoding), Origin.of(key, sample))
        except Exception:  # an exception must not escape into Zenoh's thread; a bug is logged
            log.exception("unexpected error handling a scan sample on %s", sample.key_expr)

    def _handle_fetched(self, key: str, sample: zenoh.Sample, origin: Origin) -> None:
        """A deferred sample fetched again from its publisher's cache (`BacklogRefetch`'s thread)."""
        self._handle_scan(key, sample.payload, str(sample.encoding), origin)

    def _handle_scan(
        self, key: str, payload: zenoh.ZBytes | bytes, encoding: str, origin: Origin | None = None
    ) -> None:
        """Parse, decode and submit one scan sample. Never blocks: every step is CPU only, and
        `MapRegistry.submit` refuses rather than waits when the queue is full. A sample of an
        advanced publisher (`origin`) passes `BacklogRefetch`'s gate: the full queue defers it
        rather than dropping it, and it is fetched again from the publisher's cache (as are its
        publisher's later ones, held back meanwhile)."""
        ids = parse_key(key, "scan")
        if ids is None:
            with self._lock:
                self.invalid_keys += 1
            self._log.warning("invalid-key", f"ignored a scan on invalid key {_shown_key(key)}: ids must "
                              "match [A-Za-z0-9_-]{1,64} in fleetmap/<map_id>/<robot_id>/scan")  # fmt: skip
            return
        map_id, robot_id = ids
        if origin is None:
            self._decode_and_submit(map_id, robot_id, payload, encoding, defer=False)
            return
        with self._refetch.lock:
            if not self._refetch.admit(origin):
                with self._lock:
                    self.deferred += 1
                return
            deferred = self._decode_and_submit(map_id, robot_id, payload, encoding, defer=True)
            self._refetch.taken(origin, deferred)

    def _decode_and_submit(
        self, map_id: str, robot_id: str, payload: zenoh.ZBytes | bytes, encoding: str, defer: bool
    ) -> bool:
        """Decode a scan sample of robot `robot_id` on map `map_id` and submit it (`defer`: as
        `MapRegistry.submit`'s `defer_when_full`), counting and logging a refusal. Returns whether
        the full queue deferred it (taken nowhere: it is to be fetched again)."""
        limits = self.registry.input_limits
        try:
            # Its size before it is copied out of Zenoh's buffer: Zenoh takes messages of up to
            # 1 GiB, and a 200 MB put was copied whole into Python, 170 MB more held, to be refused.
            codec.check_payload_size(len(payload), limits)
            data = payload if isinstance(payload, bytes) else payload.to_bytes()
            wire = codec.decode(data, encoding, limits)
        except codec.DecodeError as exc:
            if exc.scan_id is None:
                reason = f"undecodable {encoding or 'unspecified'} payload: {exc}"
            else:  # well-formed, refused by the engine's checks or the input limits
                reason = f"scan seq {exc.scan_id[0]} refused: {exc}"
            with self._lock:
                self.decode_errors += 1
            self.registry.reject(map_id, robot_id, reason, exc.scan_id)
            # Its seq as a field too when it was read (a scan past the input limits), as the lines
            # of the scans the registry refuses carry theirs.
            seq = {} if exc.scan_id is None else {"seq": exc.scan_id[0]}
            self._log.warning(
                f"decode:{map_id}/{robot_id}", f"rejected a scan from {map_id}/{robot_id}: {reason}",
                map_id=map_id, robot_id=robot_id, **seq,
            )  # fmt: skip
            return False
        try:
            self.registry.submit(map_id, robot_id, wire, defer_when_full=defer)
        except IngestRejected as exc:
            kind = exc.kind
            if kind == DEFERRED:
                with self._lock:
                    self.deferred += 1
                self._deferred_log.log(
                    logging.INFO, f"deferred:{map_id}/{robot_id}",
                    f"scan seq {wire.seq} from {map_id}/{robot_id}: {exc.reason}; it is fetched again from "
                    "the robot's cache as the queue drains",
                    map_id=map_id, robot_id=robot_id, seq=wire.seq,
                )  # fmt: skip
                return True
            with self._lock:
                self.rejected[kind] += 1
            self._log.warning(
                f"{kind}:{map_id}/{robot_id}", f"scan seq {wire.seq} from {map_id}/{robot_id}: {exc.reason}",
                map_id=map_id, robot_id=robot_id, seq=wire.seq,
            )  # fmt: skip
            return False
        except InvalidId:  # parse_key validated the ids; kept for safety
            with self._lock:
                self.invalid_keys += 1
            return False
        with self._lock:
            self.scans_submitted += 1
            alive = (map_id, robot_id) in self._alive
            if alive:
                # The map may have been (re)created after the token appeared (auto-create, PUT
                # after DELETE): make sure its robot shows as online. Under our lock so a token
                # DELETE cannot slip in between.
                self.registry.mark_online(map_id, robot_id)
        return False

    def _on_transport(self, event: zenoh.TransportEvent) -> None:
        """A unicast session (a robot's, or with `--zenoh-connect` a router's or peer's) connected to
        this one or left it: count it, and warn (rate-limited) when the sessions reach
        `max_sessions`, past which Zenoh refuses a robot at its handshake without telling this
        session (the robot sees "Unable to connect" and retries for ever). CPU only."""
        try:
            transport = event.transport
            if transport.is_multicast:
                return
            zid = str(transport.zid)
            with self._lock:
                if event.kind == zenoh.SampleKind.PUT:
                    self._sessions.add(zid)
                else:
                    self._sessions.discard(zid)
                held = len(self._sessions)
            limit = self.max_sessions
            if event.kind == zenoh.SampleKind.PUT and limit is not None and held >= limit:
                self._log.warning(
                    "max-sessions",
                    f"the Zenoh {self.mode} holds {held} Zenoh sessions, its limit "
                    "(transport/unicast/max_sessions): further robots are refused at their handshake "
                    f"(they see 'Unable to connect' and retry) until one leaves; {self._more_sessions}",
                )
        except Exception:  # an exception must not escape into Zenoh's thread; a bug is logged
            log.exception("unexpected error handling a Zenoh transport event")

    def _queue_room(self, key: str, promised: Mapping[str, int]) -> int:
        """How many more scans of scan key `key` the ingest queue takes now, counting `promised[k]`
        more of scan key `k` as queued (`BacklogRefetch`'s fetches in flight)."""
        ids = parse_key(key, "scan")
        if ids is None:
            return 0
        sources = {
            source: count for k, count in promised.items() if (source := parse_key(k, "scan")) is not None
        }
        return self.registry.queue.room(ids, sources)

    def _count_unrecoverable(self, count: int, source: str) -> None:
        """`count` deferred scans of the advanced publisher `source` were gone from its cache when
        they were fetched again: counted and logged as zenoh-ext's own misses are."""
        with self._lock:
            self.unrecoverable += count
        self._log.warning(
            f"unrecoverable:{source}",
            f"{count} deferred scan(s) of the advanced publisher {source} could not be fetched again: gone "
            "from its cache (its last scans) before the ingest queue had room for them",
        )

    def _on_miss(self, miss: zenoh.ext.Miss) -> None:
        """zenoh-ext gave up on `miss.nb` samples of the publisher `miss.source`: count and log them.
        CPU only: the counter under the lock and a rate-limited line."""
        try:
            nb = int(miss.nb)
            with self._lock:
                self.unrecoverable += nb
            source = str(miss.source)
            self._log.warning(
                f"unrecoverable:{source}",
                f"{nb} scan(s) of the advanced publisher {source} could not be recovered: gone from its "
                "cache (its last scans) before this service could fetch them",
            )
        except Exception:
            log.exception("unexpected error handling a sample miss")

    def _on_delivery_query(self, query: zenoh.Query) -> None:
        """Answer a delivery query on `fleetmap/<map>/<robot>/delivery[?session=<id>]` with the
        registry's `DeliveryStatus` as JSON (also when there is no such map or robot: its `status`
        says so), or an error reply for a key with wildcards or invalid ids, or a bad session id.
        Never blocks beyond the registry's lock, held briefly: this is a Zenoh thread."""
        try:
            key = str(query.key_expr)
            with self._lock:
                self.delivery_queries += 1
            ids = parse_key(key, "delivery")
            error = zenoh.Encoding(DELIVERY_ERROR_ENCODING)
            if ids is None:
                query.reply_err(
                    f"ask for one robot: fleetmap/<map_id>/<robot_id>/delivery, not {key!r}", encoding=error
                )
                return
            try:
                session = _session_parameter(query.parameters.get(DELIVERY_SESSION_PARAMETER))
            except ValueError as exc:
                query.reply_err(str(exc), encoding=error)
                return
            status = self.registry.delivery_status(ids[0], ids[1], session)
            # The fields added since the first version only when asked for: a client of that
            # version refuses a field it does not know (its flush failed: "not a fleetmap one").
            newer = query.parameters.get(DELIVERY_FIELDS_PARAMETER) not in (None, "", "1")
            exclude = None if newer else DELIVERY_FIELDS_1_EXCLUDE
            reply = status.model_dump_json(exclude=exclude)
            query.reply(query.key_expr, reply, encoding=zenoh.Encoding(JSON_ENCODING))
        except Exception:  # an exception must not escape into Zenoh's thread; a bug is logged
            log.exception("unexpected error answering a delivery query on %s", query.key_expr)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        try:
            key = str(sample.key_expr)
            ids = parse_key(key, "alive")
            if ids is None:
                if sample.kind == zenoh.SampleKind.PUT:  # its disappearance is no second message
                    with self._lock:
                        self.invalid_keys += 1
                self._log.warning(
                    "invalid-alive-key", f"ignored a liveliness token on invalid key {_shown_key(key)}"
                )
                return
            online = sample.kind == zenoh.SampleKind.PUT
            with self._lock:
                self.liveliness_events += 1
                if online:
                    self._alive.add(ids)
                else:
                    self._alive.discard(ids)
                unshown = self.registry.set_online(ids[0], ids[1], online)
            state = "online" if online else "offline"
            # A token the map cannot show (no room, no map) is no robot online in GET /maps/{id} nor
            # /metrics: the line says so, rather than "is online" of a robot listed nowhere.
            shown = f" (its liveliness token), but not on its map: {unshown}" if unshown else ""
            self._alive_log.log(
                logging.INFO, f"{state}:{ids[0]}/{ids[1]}", f"robot {ids[0]}/{ids[1]} is {state}{shown}",
                map_id=ids[0], robot_id=ids[1],
            )  # fmt: skip
        except Exception:
            log.exception("unexpected error handling a liveliness sample")

    # -- reporting -------------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """A JSON-able summary for the API's `zenoh_status`: mode, endpoints and counters."""
        session = self._session
        info: dict[str, Any] = {}
        if session is not None:
            try:
                info = {
                    "zid": str(session.zid()),
                    "routers": len(session.info.routers_zid()),
                    "peers": len(session.info.peers_zid()),
                }
            except zenoh.ZError:  # closing concurrently
                info = {}
        with self._lock:
            return {
                "running": session is not None,
                "mode": self.mode,
                # Without their configuration values (a TLS key given inline): /healthz answers anyone.
                "listen": shown_endpoints(self.listen),
                "connect": shown_endpoints(self.connect),
                "endpoints": shown_endpoints(self.endpoints),
                **info,
                "messages_received": self.messages_received,
                "scans_submitted": self.scans_submitted,
                "invalid_keys": self.invalid_keys,
                "decode_errors": self.decode_errors,
                "rejected": dict(self.rejected),
                "unrecoverable": self.unrecoverable,
                "deferred": self.deferred,
                "refetched": self._refetch.refetched,
                "liveliness_events": self.liveliness_events,
                "delivery_queries": self.delivery_queries,
                "robots_alive": len(self._alive),
                "sessions": len(self._sessions),
                "max_sessions": self.max_sessions,
            }


def _max_sessions(cfg: zenoh.Config) -> int | None:
    """The most unicast sessions a session of `cfg` accepts (`transport/unicast/max_sessions`:
    Zenoh's default 1000, or what the `--zenoh-config` file sets); None if it says no number."""
    value = json.loads(cfg.get_json("transport/unicast/max_sessions"))
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def _open_files_limit() -> str:
    """This process's soft limit of open files, for a log line."""
    soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    return "unlimited" if soft == resource.RLIM_INFINITY else str(soft)


#: The most characters of a key a log line quotes (as the ROS ingest's lines do).
SHOWN_KEY_CHARS = 200


def load_config_file(path: str | Path) -> zenoh.Config:
    """The Zenoh configuration in file `path` (`--zenoh-config`). Raises `IngestStartError` saying
    why it cannot be loaded: absent, unreadable, not JSON5, not a Zenoh configuration. `fleetmap
    serve` calls it among its checks of the options too: found only when the session opened, after
    the kernels were loaded and every map restored, a typo in the file's path or syntax took
    minutes to tell."""
    try:
        return zenoh.Config.from_file(str(path))
    except zenoh.ZError as exc:
        # A configuration given itself where its path goes is not shown: it may hold a password.
        shown = shown_config_path(str(path))
        raise IngestStartError(f"cannot load Zenoh config {shown}: {zenoh_error_text(exc)}") from None


def _shown_key(key: str) -> str:
    """`key` quoted for a log line, cut to SHOWN_KEY_CHARS with its length said. A key is the
    sender's to make, as long as a Zenoh message holds (some 60 KB): its warning wrote it whole."""
    if len(key) <= SHOWN_KEY_CHARS:
        return repr(key)
    return f"{key[:SHOWN_KEY_CHARS]!r}... ({len(key)} characters)"


def _session_parameter(value: str | None) -> int | None:
    """A delivery query's `session` parameter: None when absent (every session), else the session
    id (0: scans without one). Raises ValueError, saying what it must be, for anything else."""
    if value is None:
        return None
    if not (value.isascii() and value.isdigit() and len(value) <= 16 and int(value) < SESSION_LIMIT):
        raise ValueError(f"{DELIVERY_SESSION_PARAMETER} must be an integer in [0, 2**53)")
    return int(value)


__all__ = [
    "DEFAULT_LISTEN",
    "MODES",
    "IngestStartError",
    "ZenohIngest",
    "parse_key",
    "unauthenticated_endpoints",
]
