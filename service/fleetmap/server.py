"""`fleetmap serve`: the long-running service. Robots publish scans over Zenoh; maps are served over HTTP.

    fleetmap serve [OPTIONS]     (`fleetmap serve --help` lists them; they are defined in `serve_options`)

One process holds everything: a `MapRegistry` (maps, robots, integration worker threads), a
`ZenohIngest` (the service's own Zenoh session: a router by default, so robots connect to it
directly in client mode and nothing else needs installing) and the REST API (`fleetmap.api`) run by
uvicorn in the main thread; with `--ros-scans`, a `RosScanIngest` (fleetmap.ros.ingest) takes ROS 2
robots' LaserScans, and with `--ros-publish-map` a `RosMapPublisher` (fleetmap.ros.map_publisher)
publishes maps to ROS 2, both on the same Zenoh session from a thread of their own.

Start-up order: the HTTP socket is bound first (so a port in use fails before anything else starts),
the data directory is opened, the compiled kernels are warmed, the registry restores the stored maps
and starts its workers, the Zenoh session opens (and the ROS 2 parts on it), then uvicorn serves.
Only then is the ready line printed on stdout:

    fleetmap serving http://HOST:PORT  zenoh: ENDPOINTS

(with `--log-format json`, a JSON log object whose message is that line: see fleetmap.log_format).
SIGINT / SIGTERM during the warm-up or the restore end the start there ("stopped before serving",
exit 0): the Zenoh session is not opened, and restored maps are snapshotted as restored.

Every option can also be given as an environment variable, `FLEETMAP_` and the option's name in
capitals with `-` as `_` (`--data-dir` is `FLEETMAP_DATA_DIR`, `--insecure` is `FLEETMAP_INSECURE=1`,
lists separated by spaces); the command line wins (`serve_environment`).

SIGHUP reads the `--auth-tokens` file again (a file that cannot be used keeps the tokens in force).
SIGINT / SIGTERM shut down gracefully: uvicorn stops serving (open event streams end at once, other
requests in flight get `http_server.GRACEFUL_HTTP_SECONDS`, then are answered 503 or cut off: `ShutdownCutoff`
in api/errors.py), the Zenoh session closes (no more scans come in), the
registry integrates every scan already queued, stops its workers and snapshots every map, and the
process exits 0 (a second signal changes nothing: it does not cut the shutdown short), or 1 when
storage failed and a map's last state could not be stored (the last line names those maps). A
configuration error (bad address, port in use, bad config file) prints one line
`fleetmap serve: error: ...` and exits 2, without a traceback.

This module is the start-up and shutdown sequence (`run`, and the steps it takes in order). The
rest of the command: `serve_options` (the options, their defaults and the checks of their values),
`serve_environment` (the options as FLEETMAP_ variables), `http_server` (the HTTP socket and the
uvicorn server), `serve_ros` (the ROS 2 options, scan ingest and map publisher) and `warm_up` (the
compiled kernels loaded before serving).
"""

from __future__ import annotations

import argparse
import gc
import logging
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

from fleetmap.auth import TokenFile, TokenFileError, TokenSet, others_may_read
from fleetmap.cli import CliError, load_config, parse_command_line, run_command
from fleetmap.codec import InputLimits
from fleetmap.config import MapConfig
from fleetmap.database import StorageError
from fleetmap.http_limits import raise_descriptor_limit, zenoh_session_limit
from fleetmap.http_server import bind_http, make_server, url_host
from fleetmap.log_format import configure_logging
from fleetmap.malloc_arenas import (
    SERVICE_ARENAS,
    SERVICE_MMAP_THRESHOLD,
    fix_mmap_threshold,
    limit_malloc_arenas,
)
from fleetmap.memory_budget import format_size
from fleetmap.network import is_loopback_host
from fleetmap.persistence import DurableStore
from fleetmap.serve_options import (
    DEFAULT_DATA_DIR,
    ROS_MAP_DEFAULTS,
    add_serve_parser,
    parse_http,
    proxies_of_uvicorns_variable,
)
from fleetmap.serve_ros import ros_domain, ros_options, start_ros_maps, start_ros_scans, zenoh_status
from fleetmap.shown_endpoint import shown_endpoints
from fleetmap.signal_event import HANGUPS, SignalEvent, SignalWakeups
from fleetmap.tiles import TileStore
from fleetmap.warm_up import compile_in_child, warm_up
from fleetmap.zenoh_ingest import IngestStartError, ZenohIngest, load_config_file

if TYPE_CHECKING:
    from fleetmap.ros.ingest import RosScanIngest

log = logging.getLogger("fleetmap.server")


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> argparse.ArgumentParser:
    """Add the `serve` subcommand to the `fleetmap` command line: its options (`serve_options`), run
    by `run`."""
    parser = add_serve_parser(sub)
    parser.set_defaults(run=run, takes_hangup=True)
    return parser


def run(args: argparse.Namespace) -> int:
    """`fleetmap serve`: run until SIGINT / SIGTERM, then shut down cleanly and return 0.

    In order: the process set up (`_configure_process`), the options checked (`_checked_options`),
    the HTTP socket bound, storage opened (`_open_storage`), the engine warmed, the registry
    restored and started, the Zenoh session opened, then the API served by uvicorn
    (`http_server.make_server`) until a signal; the Zenoh session and the registry close whatever happened.
    SIGINT, SIGTERM and SIGHUP are left ignored when it returns: the process is to exit then."""
    from fleetmap.registry import MapRegistry

    _configure_process(args)
    stop = SignalEvent()
    server: Any = None

    def on_signal(signum: int, _frame: object) -> None:
        # Before uvicorn runs (start-up) and after it returns (uvicorn re-raises the signal it
        # caught): note the request; uvicorn handles the signal itself while it serves.
        stop.set_in_handler()
        if server is not None:
            server.should_exit = True

    tokens: TokenSet | TokenFile | None = None
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    # SIGHUP's default action ends the process at once (no snapshot, no clean close): `kill -HUP` or
    # systemd's ExecReload must reload the token file instead, on a thread of its own (`SignalWakeups`).
    hangups = SignalWakeups()
    reloader = threading.Thread(
        target=_reload_on_hangup, args=(hangups, lambda: tokens), name="fleetmap-sighup", daemon=True
    )
    reloader.start()
    ros: RosScanIngest | None = None
    unstored: tuple[str, ...] = ()  # maps the registry's close could not store
    try:
        options = _checked_options(args)
        tokens = options.tokens
        # Installed once the tokens are read: a SIGHUP held since the start (`HANGUPS`) reads the
        # token file again now, where before it was said to have nothing to reload.
        HANGUPS.release(lambda _signum, _frame: hangups.notify_in_handler())
        # The HTTP socket first: a second instance on a busy port must fail before it opens the
        # (possibly shared) data directory.
        sock = bind_http(options.host, options.port)
        port = sock.getsockname()[1]
        durable = _open_storage(args, sock)
        _warm_engine(stop)
        if stop.is_set():  # signalled while starting: nothing restored or served yet, nothing to save
            sock.close()
            if durable is not None:
                durable.close()
            log.info("stopped before serving")
            return 0
        registry = MapRegistry(
            options.default_config,
            auto_create=not args.no_auto_create,
            workers=args.workers,
            on_integrated=_integration_hook(),
            durable=durable,
            memory_budget=args.max_memory,
            max_robots_per_map=args.max_robots_per_map,
            input_limits=options.input_limits,
        )
        # Zenoh's sessions (one descriptor each) and HTTP's connections share the descriptors.
        descriptors = raise_descriptor_limit()
        ingest = ZenohIngest(
            registry,
            listen=args.zenoh_listen,
            connect=args.zenoh_connect,
            config_file=args.zenoh_config,
            shared_memory=args.zenoh_shared_memory,
            session_limit=zenoh_session_limit(descriptors, args.max_http_connections),
        )
        try:
            registry.start()  # restores the stored maps
        except StorageError as exc:
            sock.close()
            assert durable is not None  # only a durable registry reads storage at start
            durable.close()
            raise CliError(str(exc)) from None
        if stop.is_set():
            # Signalled during the restore (10-20 s a map with a long journal): it went on to open
            # the Zenoh session, taking robots' scans for a moment, and logged where it served.
            # Closed now, the registry snapshots the maps as restored: the next start replays
            # nothing (and nothing is new that storage could fail to keep).
            sock.close()
            registry.close()
            log.info("stopped before serving")
            return 0
        ros_maps: Any = None
        try:
            try:
                ingest.start()
            except IngestStartError as exc:
                raise CliError(str(exc)) from None
            ros = start_ros_scans(args, options.ros, registry, ingest)
            ros_maps = start_ros_maps(args, registry, ingest)
            settings = options.settings_cls(
                zenoh_status=zenoh_status(ingest, ros, ros_maps),
                cors_origins=args.cors_origin,
                ingest_backlog=args.ingest_backlog_ms / 1000,
                max_read_delay=args.max_read_delay_ms / 1000,
                max_event_streams=args.max_event_streams,
                keepalive=args.events_keepalive,
                metrics_robot_idle=args.metrics_robot_idle,
                tokens=tokens,
                require_read_token=args.require_read_token,
                signin_max_failures=args.max_failed_sign_ins,
                signin_window=args.failed_sign_in_window,
                # Without tokens only this machine may change the maps: its socket is on loopback,
                # and a web page rebound to 127.0.0.1 names another host.
                loopback_hosts_only=tokens is None and not args.insecure,
            )
            app = options.create_app(registry, settings=settings)
            _log_protection(args, tokens, durable is not None, options.default_config)
            server = make_server(
                args, app, f"http://{url_host(options.host)}:{port}", shown_endpoints(ingest.endpoints),
                descriptors - (ingest.max_sessions or 0),
            )  # fmt: skip
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
            unstored = registry.close()
    finally:
        # Ignored, not given back their default action: the process ends once `run` returns, and a
        # signal in that last moment (the interpreter's exit takes ~50 ms) killed it, exit -15 / -1
        # instead of 0, after a clean stop: a repeated `kill`, a Ctrl-C pressed twice, systemd's
        # SendSIGHUP=.
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, signal.SIG_IGN)
        hangups.close()
        reloader.join(timeout=5)
    if unstored:
        # After the errors that said what failed: the outcome, and an exit code a supervisor sees.
        log.error(
            "stopped, but storage failed to keep maps %s (see the errors above): a restart finds them "
            "as they were stored last",
            ", ".join(unstored),
        )
        return 1
    log.info("stopped")
    return 0


def _configure_process(args: argparse.Namespace) -> None:
    """What `serve` sets for the whole process before anything starts: malloc's arenas, the log,
    Zenoh's own log, the GIL's switch interval."""
    # First, before any thread of the service allocates (see malloc_arenas).
    limited = limit_malloc_arenas()
    fixed = fix_mmap_threshold()
    configure_logging(str(args.log_level), str(args.log_format))
    log.debug("malloc arenas %s", f"limited to {SERVICE_ARENAS}" if limited else "as the environment says")
    log.debug(
        "malloc mmap threshold %s",
        f"fixed at {SERVICE_MMAP_THRESHOLD >> 20} MiB" if fixed else "as the environment says",
    )
    for warning in getattr(args, "environment_warnings", ()):
        log.warning("%s", warning)
    # Zenoh's own log: refused TLS handshakes and wrong passwords show there (RUST_LOG=warn for more).
    import zenoh

    zenoh.init_log_from_env_or("error")
    # Integration workers hold the map lock while they apply a scan; under HTTP load they wait for
    # the GIL to come back to them. A shorter switch interval hands it over sooner (about halved the
    # scans dropped under read load in the service benchmark).
    sys.setswitchinterval(0.0005)


class _StartOptions(NamedTuple):
    """What `run` starts from, read from the options by `_checked_options`."""

    host: str
    port: int  # 0: any free port
    default_config: MapConfig  # of maps created automatically (--config)
    create_app: Any  # fleetmap.api.app's, and ...
    settings_cls: Any  # ... its ApiSettings (`_load_api`)
    tokens: TokenSet | TokenFile | None
    ros: tuple[int, str] | None  # --ros-scans' (domain id, fixed frame)
    input_limits: InputLimits  # --world-bound, --max-beams, --max-range


def _checked_options(args: argparse.Namespace) -> _StartOptions:
    """What `run` starts from, after the checks of the options that need no socket or storage.
    Raises CliError."""
    host, port = parse_http(args.http)
    default_config = load_config(args.config)
    if args.zenoh_config:
        try:
            load_config_file(args.zenoh_config)  # checked now; the ingest loads it once the maps are in
        except IngestStartError as exc:
            raise CliError(str(exc)) from None
    create_app, settings_cls = _load_api()
    input_limits = InputLimits(args.world_bound, args.max_beams, args.max_range)
    if args.forwarded_allow_ips is None:  # else the option (or its variable) wins, as documented
        args.forwarded_allow_ips = proxies_of_uvicorns_variable(os.environ)
    if args.ros_publish_map:
        from fleetmap.ros.map_publisher import topic_clash

        if (clash := topic_clash(args.ros_publish_map)) is not None:
            raise CliError(f"--ros-publish-map: {clash}")
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
    if tokens is None and not is_loopback_host(host) and not args.insecure:
        raise CliError(
            f"refusing to serve {host} without API tokens: anyone on the network could change the "
            "maps. Give --auth-tokens FILE (or $FLEETMAP_TOKENS), or --insecure to accept that"
        )
    ros = ros_options(args)
    return _StartOptions(host, port, default_config, create_app, settings_cls, tokens, ros, input_limits)


def _load_tokens(path: str | None) -> TokenSet | TokenFile | None:
    """The API tokens: a `TokenFile` (read again on SIGHUP) for `--auth-tokens`, else those of
    $FLEETMAP_TOKENS, else None. Raises CliError."""
    try:
        return TokenFile(path) if path else TokenSet.load(None)
    except TokenFileError as exc:
        raise CliError(str(exc)) from None


def _reload_on_hangup(hangups: SignalWakeups, tokens: Callable[[], TokenSet | TokenFile | None]) -> None:
    """The SIGHUP thread: `reload_tokens` after each wake-up (once for the signals that came while
    it ran), until `hangups` is closed. `tokens` gives the tokens in force (None until the options
    are read)."""
    while hangups.wait():
        try:
            reload_tokens(tokens())
        except Exception:  # the next SIGHUP must still be served
            log.exception("SIGHUP: the reload failed; the tokens in force are kept")


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
    if (warning := others_may_read(tokens.path)) is not None:
        log.warning("%s", warning)


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


def _warm_engine(stop: threading.Event) -> None:
    """`warm_up`, said in the log. The first start after an install compiles the kernels (10-30 s)
    in a child process (`compile_in_child`: the memory LLVM takes goes with the child), then loads
    them like any later start; if the child fails, this process compiles them itself, unless the
    service is stopping (`stop`: the child is ended then, see `compile_in_child`). What the child
    printed is logged as one warning, in the log's format."""
    from fleetmap.kernels import one_call_kernel_cached  # here: numba loads with it

    started = time.perf_counter()
    if not one_call_kernel_cached():
        log.info(
            "compiling the engine's kernels in a child process (the first start after an install: "
            "about 15 s, a minute or two on a busy machine; later starts load them from disk)"
        )
        compiled = compile_in_child(stop)
        if compiled.output.strip():  # one record, in the log's format (numba's warnings, a traceback)
            log.warning("the kernels' compilation in a child process printed:\n%s", compiled.output.rstrip())
        if not compiled.finished and stop.is_set():  # ended by us (`compile_in_child`)
            log.info("stopping: the kernels' compilation was cut short")
            return
        if not compiled.finished:
            log.warning("compiling the kernels in a child process failed; compiling them here")
    else:
        log.info("loading the engine's compiled kernels")
    warm_up()
    log.info("engine ready in %.1f s", time.perf_counter() - started)


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


def _log_protection(
    args: argparse.Namespace, tokens: TokenSet | TokenFile | None, durable: bool, default_config: MapConfig
) -> None:
    """The start-up lines that say how the service is protected and bounded: API tokens, where
    maps are kept and their memory budget, and a warning when that budget cannot hold one tile of
    the maps scans create (`--config`)."""
    budget = args.max_memory
    source = f"file {args.auth_tokens}, read again on SIGHUP" if args.auth_tokens else "$FLEETMAP_TOKENS"
    log.info(
        "API tokens: %s",
        f"required to write{' and read' if args.require_read_token else ''} ({source})" if tokens
        else "NONE: anyone who can reach the API may change maps (loopback only unless --insecure)",
    )  # fmt: skip
    if isinstance(tokens, TokenFile) and (warning := others_may_read(tokens.path)) is not None:
        log.warning("%s", warning)
    log.info(
        "maps: %s; their tiles within %s (%.0f MiB held)",
        f"durable in {Path(args.data_dir).resolve()}" if durable else "in memory only (--in-memory)",
        "no limit" if budget.limit is None else f"{budget.limit / 2**20:.0f} MiB (--max-memory)",
        budget.used / 2**20,
    )  # fmt: skip
    tile = TileStore(default_config.tile_size, default_config.layers, 1).bytes_for(1)  # an empty store
    if budget.limit is not None and tile > budget.limit:
        # Else every scan of such a map is refused 507 and nothing says why until the first one is:
        # `--max-memory 1MiB` holds no tile of the default map (1.3 MiB), though it was taken.
        log.warning(
            "--max-memory %s holds no tile of the default map configuration (--config; %s a tile: "
            "%d x %d cells of %s): every scan of such a map will be refused (507); raise it, or give "
            "a --config of smaller tiles or fewer layers",
            format_size(budget.limit), format_size(tile), default_config.tile_size,
            default_config.tile_size, ", ".join(default_config.layers),
        )  # fmt: skip
    if args.in_memory and args.data_dir != DEFAULT_DATA_DIR:
        # Both given (the Docker image sets $FLEETMAP_DATA_DIR): the directory is not used, and a
        # reader of the options alone expected the maps to be kept there.
        log.warning(
            "--in-memory: --data-dir %s is not used; the maps are lost when the service stops",
            args.data_dir,
        )


def freeze_startup_objects() -> int:
    """Move every object alive now (modules, compiled kernels, the app: ~160,000 objects that live as
    long as the process) out of the garbage collector's reach; returns how many. Requests that
    allocate many containers (a 10,000-point cell query parses 10,000 lists) trigger full
    collections, and each walked all of them for ~70 ms holding the GIL, stalling the integration
    workers. Afterwards a full collection walks only what was created since."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m fleetmap.server [serve options]`: the same as `fleetmap serve` (SIGHUP held from
    here, after this module's imports, where `fleetmap`'s entry point holds it before them)."""
    HANGUPS.hold()
    parser = argparse.ArgumentParser(prog="fleetmap")
    sub = parser.add_subparsers(dest="command", required=True)
    add_parser(sub)
    args = parse_command_line(parser, sub, ["serve", *(sys.argv[1:] if argv is None else argv)])
    return run_command(args)


if __name__ == "__main__":
    sys.exit(main())
