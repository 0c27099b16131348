"""`fleetmap demo`: the main job. Starts the service and a small fleet of simulated robots exploring
a synthetic floor plan, and prints the web viewer's address; runs until Ctrl-C (or `--seconds`).
SIGTERM and SIGHUP stop it as Ctrl-C does, and its service is sent SIGTERM if it dies otherwise.

The service runs as its own process (`fleetmap serve`), exactly as in production; the robots run
in this process and publish over Zenoh in client mode, as real robots would.
"""

from __future__ import annotations

import argparse
import errno
import functools
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import httpx

from fleetmap.cli import CliError, counted
from fleetmap.http_server import url_host
from fleetmap.network import is_loopback_host
from fleetmap.parent_death import end_with_parent
from fleetmap.serve_environment import CLIENT_VARIABLES, ENV_PREFIX
from fleetmap.serve_options import DEFAULT_DATA_DIR, DEFAULT_HTTP, parse_http
from fleetmap.signal_event import HANGUPS, SignalEvent
from fleetmap.wire import DEFAULT_ENDPOINT, is_valid_id


class _DefaultsShown(argparse.ArgumentDefaultsHelpFormatter):
    """Each option's default in its help, except a None default, which the help itself describes
    (`--seconds` printed "(default: None)"), and an on/off flag's False (`--insecure`: off unless
    given, as every flag)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or action.default is False:
            return action.help
        return super()._get_help_string(action)


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "demo",
        help="run the service with simulated robots and print the viewer's address",
        description="Start the service and simulated robots mapping a synthetic floor plan; open the "
        "printed address to watch. Ctrl-C stops everything; the map is kept in --data-dir.",
        formatter_class=_DefaultsShown,
    )
    # The defaults of `fleetmap serve`, which this command starts.
    p.add_argument("--http", default=DEFAULT_HTTP, metavar="HOST:PORT", help="viewer and API address")
    p.add_argument("--zenoh", default=DEFAULT_ENDPOINT, metavar="ENDPOINT", help="where robots connect")
    p.add_argument(
        "--data-dir", default=DEFAULT_DATA_DIR, metavar="DIR", help="the service's durable storage"
    )
    # The service refuses a non-loopback --http without API tokens and says to give --insecure:
    # the demo had no such option, so a demo shown to another machine could not be started.
    p.add_argument(
        "--insecure",
        action="store_true",
        help="let --http listen beyond loopback (e.g. 0.0.0.0:8000) without API tokens: anyone who "
        "can reach it may change the maps (as fleetmap serve --insecure)",
    )
    p.add_argument("--robots", type=int, default=3, metavar="N", help="simulated robots")
    p.add_argument("--map", default="demo", metavar="MAP_ID", help="map id the robots publish to")
    p.add_argument("--seed", type=int, default=1, metavar="SEED", help="floor plan and robots' seed")
    p.add_argument("--rate", type=float, default=10.0, metavar="HZ", help="scans per second per robot")
    p.add_argument(
        "--seconds", type=float, default=None, metavar="T", help="stop after T s (default: at Ctrl-C)"
    )
    p.set_defaults(run=run, takes_hangup=True)


def run(args: argparse.Namespace) -> int:
    from fleetmap_client.cli import skipped_warning
    from fleetmap_client.sim import run_sim

    _check_fleet(args)
    _viewer_url(args.http)  # a bad --http refused before anything starts
    # Another service on these ports would answer /healthz for ours, which would die unseen, and
    # the robots would map into that other service: refuse before starting anything.
    for option, value in (("--http", args.http), ("--zenoh", args.zenoh)):
        _check_free(option, value)
    _check_exposure(args)  # after: an address not this machine's is that first
    stop = SignalEvent()

    def on_stop(_signum: int, _frame: object) -> None:
        stop.set_in_handler()

    # Ctrl-C, and also `kill`, `timeout`, `docker stop` (SIGTERM) and a closed terminal (SIGHUP):
    # each ended the demo at once and left its service running on, holding the ports and the data
    # directory that the next `make demo` then found in use.
    previous = {sig: signal.signal(sig, on_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    # SIGHUP was held from the start (`HANGUPS`): one that came meanwhile stops the demo now.
    previous[signal.SIGHUP] = HANGUPS.release(on_stop)
    # The demo's options alone set its service up. FLEETMAP_* variables meant for `fleetmap serve`
    # (an operator's shell) made it contradict the demo: FLEETMAP_IN_MEMORY kept no map where the
    # demo said it was kept, FLEETMAP_ZENOH_CONFIG of a TLS router left its plain-TCP robots
    # waiting for ever. They are left out, and named.
    env = {key: value for key, value in os.environ.items() if not key.startswith(ENV_PREFIX)}
    # Named but for the clients' own (the REST client's token): no setting of `fleetmap serve`.
    ignored = sorted(set(os.environ) - set(env) - CLIENT_VARIABLES.keys())
    if ignored:
        print(
            f"fleetmap demo: its service ignores {', '.join(ignored)} (the demo's options set it up; "
            "fleetmap serve reads them)",
            flush=True,
        )
    service = subprocess.Popen(
        [sys.executable, "-m", "fleetmap.server", "--http", args.http, "--zenoh-listen", args.zenoh,
         "--data-dir", args.data_dir, *(["--insecure"] if args.insecure else [])],
        # (The demo runs no thread yet: the child may run Python between fork and exec.)
        preexec_fn=functools.partial(end_with_parent, os.getpid()), env=env,
    )  # fmt: skip
    ready = False
    try:
        url = _viewer_url(args.http)
        _wait_for_service(service, url, stop)
        if stop.is_set():
            return 0
        ready = True
        fleet = counted(args.robots, "robot")
        earlier = _earlier_scans(url, args.map)
        if earlier:
            print(
                f"\nfleetmap demo: map {args.map} in {args.data_dir} already holds "
                f"{counted(earlier, 'scan')} of an earlier run, which the robots add to (another "
                "--seed draws another floor plan over it): --map NAME starts a new map",
                flush=True,
            )
        print(f"\nfleetmap demo: open {url}#map={args.map} to watch {fleet} map a floor plan")
        print(
            f"  (Ctrl-C stops the robots and the service; the map is kept in {args.data_dir})\n", flush=True
        )
        watcher = threading.Thread(target=_watch, args=(service, stop), daemon=True)
        watcher.start()
        result = run_sim(
            args.robots, map_id=args.map, seed=args.seed, rate=args.rate, seconds=args.seconds,
            connect=[args.zenoh], stop=stop,
        )  # fmt: skip
        sent, dropped = sum(result.published.values()), sum(result.dropped.values())
        robots = counted(len(result.robots), "robot")
        print(f"fleetmap demo: {robots} published {counted(sent, 'scan')} ({dropped} dropped)")
        warning = skipped_warning(result, args.rate)
        if warning is not None:  # the summary counts what was sent: scans never made go unsaid
            print(f"fleetmap demo: warning: {warning} (run fewer, or a lower --rate)", file=sys.stderr)
        if service.poll() is not None:
            raise CliError(f"the service stopped unexpectedly (exit code {service.returncode}); see above")
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        service.terminate()
        try:
            service.wait(30)
        except subprocess.TimeoutExpired:
            service.kill()
            service.wait()
        # The last words after Ctrl-C, below the service's own: where the map went (it was said
        # at the start, scrolled away since).
        if ready and service.returncode == 0:
            print(f"fleetmap demo: stopped; the map is kept in {args.data_dir}", flush=True)
    if ready and service.returncode != 0:
        # Its last snapshot failed (a full or failing disk: it said which maps a restart finds as
        # they were stored last) or it had to be killed: the demo exited 0 all the same.
        raise CliError(
            f"the service did not stop cleanly (exit code {service.returncode}): the map may lack its "
            "last scans; see its last lines above"
        )
    return 0


def _viewer_url(http: str) -> str:
    """The address of the viewer (and of /healthz below it) that `--http` `http` serves, as the
    service's ready line names it: `:8000` (all interfaces, with --insecure) was polled and printed
    as `http://:8000/`, which nothing answers, so the demo waited for its service until it gave
    up. Raises CliError for an address the service would refuse."""
    host, port = parse_http(http)
    return f"http://{url_host(host)}:{port}/"


def _earlier_scans(url: str, map_id: str) -> int:
    """The scans map `map_id` of the service at `url` holds from an earlier run (0 when it has none,
    or cannot say). The map is kept in the data directory, and a second demo's robots map into it:
    with another --seed, another floor plan over the first, silently, which looked like a broken map."""
    try:
        # Never through a proxy, as _wait_for_service.
        answer = httpx.get(f"{url}maps/{map_id}", timeout=10.0, trust_env=False)
        if answer.status_code != 200:
            return 0
        scans = answer.json()["stats"]["scans_integrated"]
    except (httpx.HTTPError, ValueError, KeyError, TypeError):
        return 0  # a note only: the demo runs all the same
    return scans if isinstance(scans, int) else 0


def _check_fleet(args: argparse.Namespace) -> None:
    """Raise CliError for options the robots cannot run with, before the service starts: `--robots
    0` started the service, waited for it, then ended in a traceback from `run_sim`. Raises this
    process's soft `ulimit -n` to its hard limit, for the robots' file descriptors."""
    if args.robots < 1:
        raise CliError(f"--robots must be at least 1, got {args.robots}")
    if not (0.0 < args.rate < math.inf):
        raise CliError(f"--rate must be a number of scans per second above 0, got {args.rate:g}")
    if args.seconds is not None and not args.seconds >= 0.0:
        raise CliError(f"--seconds must be 0 or more (or left out: until Ctrl-C), got {args.seconds:g}")
    if args.seed < 0:  # numpy's traceback, once the service was up ("expected non-negative integer")
        raise CliError(f"--seed must be 0 or more, got {args.seed}")
    if not is_valid_id(args.map):
        raise CliError(f"--map {args.map!r} is no map id: use 1 to 64 characters from A-Z a-z 0-9 _ -")
    from fleetmap_client.cli import SIM_OPTIONS
    from fleetmap_client.sim import check_fleet

    from fleetmap.http_limits import raise_descriptor_limit

    # The rest of what `run_sim` refuses: more robots than this process has file descriptors or the
    # machine threads for, a rate slower than a thread can wait. It raised them as a traceback,
    # once the service was up.
    raise_descriptor_limit()
    try:
        # Named as the demo's options, which are the sim's ("rate 1e-300 is too slow" named none).
        check_fleet(args.robots, args.rate, args.seconds, seed=args.seed, names=SIM_OPTIONS)
    except ValueError as exc:
        raise CliError(str(exc)) from None


def _check_exposure(args: argparse.Namespace) -> None:
    """Raise CliError for an `--http` beyond loopback without `--insecure`, which the demo's service,
    run without API tokens, would refuse: the service's refusal said to give `--auth-tokens FILE`
    (or $FLEETMAP_TOKENS), which the demo takes neither of (it leaves out every FLEETMAP_ variable),
    or `--insecure`, the one that a demo can take."""
    host, _ = parse_http(args.http)
    if not args.insecure and not is_loopback_host(host):
        raise CliError(
            f"--http {args.http} listens beyond this machine, and the demo's service runs without API "
            "tokens: anyone who can reach it could change the maps; give --insecure to accept that"
        )


def _check_free(option: str, value: str) -> None:
    """Raise CliError if nothing can listen on the address of `option`'s `value` (HOST:PORT, or a
    Zenoh endpoint PROTOCOL/HOST:PORT): something else does, the host is not this machine's, or the
    port is 0 or past 65535."""
    address = value.split("/", 1)[-1]
    host, _, port = address.rpartition(":")
    host = host.strip("[]") or "127.0.0.1"
    if not port.isdigit():
        return  # the service reports an address it cannot parse itself
    if int(port) > 65535:  # socket.bind's OverflowError: a traceback
        raise CliError(f"{option} {value}: port must be at most 65535")
    if int(port) == 0:
        # `serve --http HOST:0` picks a free port, but the demo polls, prints and connects its
        # robots to the port it was given: with 0 it waited 120 s for an answer on port 0 (or its
        # robots waited for ever) while its service ran on another port.
        raise CliError(
            f"{option} {value}: the demo needs a fixed port, not 0 (it prints the viewer's address "
            "and points its robots at the service)"
        )
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, int(port)))
        except OSError as exc:
            if exc.errno != errno.EADDRINUSE:
                # A host that is not this machine's (EADDRNOTAVAIL), a name that does not resolve,
                # a port it may not use: "is another fleetmap service running?" sent the user
                # after a service that was not there.
                raise CliError(
                    f"cannot listen on {address}: {exc.strerror or exc} (the demo's service runs on "
                    f"this machine: give {option} one of its addresses and a port it may use, e.g. "
                    f"{'127.0.0.1:8001' if option == '--http' else 'tcp/127.0.0.1:7448'})"
                ) from None
            # `make demo` is how the README starts it, and `make demo --http ...` is make's own
            # option error: say how make passes them on.
            # Another demo or `fleetmap serve` started in this folder also holds ./fleetmap-data,
            # which one service at a time may use: other addresses alone were refused in turn.
            raise CliError(
                f"cannot listen on {address}: {exc.strerror} (is another fleetmap service running? Stop "
                "it, or give the demo other addresses and its own data directory: --http HOST:PORT, "
                '--zenoh tcp/HOST:PORT, --data-dir DIR; with make: make demo DEMO_ARGS="--http '
                '127.0.0.1:8001 --zenoh tcp/127.0.0.1:7448 --data-dir ./fleetmap-data-2")'
            ) from None


def _watch(service: subprocess.Popen, stop: threading.Event) -> None:
    """Stop the robots if the service exits while they run."""
    while not stop.is_set():
        if service.poll() is not None:
            stop.set()
            return
        time.sleep(0.5)


#: Seconds between the demo's reminders that it still waits for its service to answer.
WAIT_NOTE_S = 30.0


def _wait_for_service(service: subprocess.Popen, url: str, stop: threading.Event) -> None:
    """Until the service answers `/healthz` at `url`, `stop` is set, or the service exits (CliError).
    No time limit while it runs: a first start compiles the kernels (a minute or two on a busy
    machine, several on a small board), and a restart restores every stored map; a fixed 120 s gave
    up on such a start and killed it, compile and all. It says every WAIT_NOTE_S that it waits, and
    Ctrl-C stops it, as always."""
    noted = time.monotonic()
    while not stop.is_set():
        if service.poll() is not None:
            # Its ports were free a moment ago (`_check_free`): the service said why on the line
            # above (its data directory in use, say), which a guess at the ports contradicted.
            raise CliError(
                f"the service exited with code {service.returncode} before it was ready (see its error above)"
            )
        try:
            # Never through a proxy (trust_env=False): the service is this machine's, and with
            # HTTP_PROXY set and 127.0.0.1 not in NO_PROXY (a company network) every poll went to
            # the proxy, and the demo gave up on a service that ran.
            if httpx.get(url + "healthz", timeout=1.0, trust_env=False).status_code == 200:
                return
        except httpx.TransportError:
            pass
        if time.monotonic() - noted >= WAIT_NOTE_S:
            noted = time.monotonic()
            print(
                f"fleetmap demo: still waiting for the service to answer at {url} (a first start "
                "compiles its kernels; Ctrl-C stops)",
                flush=True,
            )
        time.sleep(0.2)
