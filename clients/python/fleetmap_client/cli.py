"""The `fleetmap replay` and `fleetmap sim` commands (robots for a running `fleetmap serve`).

    fleetmap replay DATASET --map M --robot R [--rate X] [--connect EP ...] [--zenoh-config FILE]
                    [--encoding binary|json] [--limit N] [--wait-timeout S] [--confirm-timeout S]
                    [--no-confirm] [--quiet]
    fleetmap sim [--robots N] [--map M] [--seed S] [--rate HZ] [--seconds T] [--connect EP ...]
                 [--zenoh-config FILE] [--encoding binary|json] [--beams B] [--speed V]
                 [--wait-timeout S] [--confirm-timeout S] [--no-confirm]

`add_parser(sub)` adds both to the `fleetmap` command line (listed in `fleetmap.cli.COMMAND_MODULES`);
`python -m fleetmap_client.cli replay ...` runs them without it.
"""

from __future__ import annotations

import argparse
import signal
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING

from fleetmap.cli import CliError, counted, dataset_error, run_command
from fleetmap.signal_event import SignalEvent

from .publisher import ScanPublisher
from .zenoh_config import DEFAULT_CONNECT

if TYPE_CHECKING:  # imported where the sim runs: the command line's other commands do without it
    from .sim import SimResult


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `replay` and `sim` to a `fleetmap` subcommand parser."""
    add_replay_parser(sub)
    add_sim_parser(sub)


def _add_connection(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--connect",
        nargs="+",
        action="extend",  # given twice, both lists (argparse's default kept the last alone)
        metavar="EP",
        default=None,
        help=f"Zenoh endpoints of the service (default {DEFAULT_CONNECT[0]}, where `fleetmap serve` listens)",
    )
    p.add_argument(
        "--zenoh-config",
        metavar="FILE.json5",
        help="Zenoh configuration for the robot side (TLS, mutual TLS, user/password: docs/security.md)",
    )
    p.add_argument(
        "--encoding",
        choices=["binary", "json"],
        default="binary",
        help="payload encoding (default binary: compact; json is readable, about 5 times larger)",
    )
    p.add_argument(
        "--wait-timeout",
        type=float,
        default=None,
        metavar="S",
        help="give up when the service is not reachable for S seconds (default: wait forever)",
    )


def skipped_warning(result: SimResult, rate: float) -> str | None:
    """What to warn of the scans the robots of a sim at `rate` scans/s skipped because they fell
    behind it (`SimResult.skipped`), or None if they skipped none: `fleetmap sim` and `fleetmap
    demo` both say so (the demo said nothing of them, its summary counting only what was sent)."""
    skipped, robots = sum(result.skipped.values()), len(result.robots)
    if not skipped:
        return None
    who = "the robot" if robots == 1 else "the robots"
    return (
        f"{counted(skipped, 'scan')} skipped: {who} fell behind {rate:g} scans/s, this machine is too "
        f"busy for {counted(robots, 'robot')} at that rate"
    )


def _waiting(pub: ScanPublisher) -> None:
    print(
        f"waiting for the fleetmap service at {', '.join(pub.shown_endpoints)} (start it with "
        "`fleetmap serve`; Ctrl-C to stop)",
        file=sys.stderr,
        flush=True,
    )


# -- replay ----------------------------------------------------------------------------------------


#: `check_replay`'s parameters as `fleetmap replay`'s options, which its errors name ("limit must be
#: >= 0" was said of `--limit -1`).
REPLAY_OPTIONS = {
    name: "--" + name.replace("_", "-") for name in ("rate", "limit", "wait_timeout", "confirm_timeout")
}


def add_replay_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "replay",
        help="publish a recorded dataset to the service over Zenoh, as one robot",
        description=(
            "Publish a recorded laser log (CARMEN log, plain or .gz, or .mat) to a running fleetmap "
            "service over Zenoh as one robot: scan k gets seq k. Scans go out at a nominal 10 per "
            "second, not at the log's timestamps (some logs have none: the Freiburg campus log's are "
            "all 0): --rate X publishes 10*X scans per second (0: as fast as Zenoh takes them, and the "
            "service drops, counting them as dropped on the robot, the scans its ingest queue of 1024 "
            "per robot cannot hold: use a finite rate for a lossless replay). Waits for the service "
            "first; after a lost connection it pauses until the service is back, which then fetches "
            "the scans in flight from the robot's backlog. After the last scan it asks the service "
            "whether every scan is integrated and says so; it exits with 1 when some are not confirmed."
        ),
    )
    p.add_argument("dataset", help="CARMEN log (plain or .gz) or MATLAB .mat file")
    p.add_argument("--map", required=True, dest="map_id", help="map id ([A-Za-z0-9_-]{1,64})")
    p.add_argument("--robot", required=True, dest="robot_id", help="robot id ([A-Za-z0-9_-]{1,64})")
    p.add_argument(
        "--rate", type=float, default=1.0, metavar="X",
        help="speed: X times the nominal 10 scans/s (default 1; 0 = as fast as possible, and the service "
        "drops what it cannot integrate in time)",
    )  # fmt: skip
    p.add_argument("--limit", type=int, default=None, metavar="N", help="publish only the first N scans")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--confirm-timeout", type=float, default=None, metavar="S",
        help="after the last scan, wait at most S seconds for the service to confirm every scan "
        "(default: --wait-timeout, else 60)",
    )  # fmt: skip
    p.add_argument(
        "--no-confirm", action="store_true",
        help="do not ask the service whether the scans are integrated (for a service older than that)",
    )  # fmt: skip
    _add_connection(p)
    p.set_defaults(run=run_replay)
    return p


def run_replay(args: argparse.Namespace) -> int:
    from fleetmap.datasets import DatasetError, load_dataset

    from .replay import ReplayError, check_replay, replay

    try:  # before the log is read (the Intel log takes a second), named as the options
        check_replay(args.rate, args.limit, args.wait_timeout, args.confirm_timeout, REPLAY_OPTIONS)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    try:
        dataset = load_dataset(args.dataset)
    except (DatasetError, OSError) as exc:
        raise dataset_error(args.dataset, exc) from None
    # SIGTERM (`kill`, `docker stop`, a job's deadline) stops the replay as Ctrl-C does: it ended it
    # at once, with no word of it, and as a container's PID 1, which receives no signal it has no
    # handler for, it went on replaying until Docker killed it 10 s later.
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        result = replay(
            dataset,
            args.map_id,
            args.robot_id,
            rate=args.rate,
            connect=args.connect,
            zenoh_config=args.zenoh_config,
            encoding=args.encoding,
            limit=args.limit,
            wait_timeout=args.wait_timeout,
            progress=not args.quiet,
            on_waiting=_waiting,
            confirm=not args.no_confirm,
            confirm_timeout=args.confirm_timeout,
        )
    except (ValueError, ReplayError) as exc:
        raise CliError(str(exc)) from None
    except KeyboardInterrupt:
        print("replay interrupted", file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
    pauses = f", paused {counted(result.pauses, 'time')} for a lost connection" if result.pauses else ""
    print(
        f"replayed {result.scans} scans of {dataset.name} to map {args.map_id!r} as robot "
        f"{args.robot_id!r} in {result.seconds:.1f} s{pauses}"
    )
    if result.unconfirmable is not None:  # an older service: what the replay always did, with a warning
        print(f"fleetmap replay: warning: not confirmed: {result.unconfirmable}", file=sys.stderr)
        return 0
    if result.confirm_error is not None:  # the scans are not confirmed: as when some are not
        print(f"fleetmap replay: warning: not confirmed: {result.confirm_error}", file=sys.stderr)
        return 1
    if result.delivery is None:  # --no-confirm
        return 0
    if result.delivery.confirmed:
        print(result.delivery.summary())
        return 0
    print(f"fleetmap replay: warning: {result.delivery.summary()}", file=sys.stderr)
    return 1


# -- sim -------------------------------------------------------------------------------------------

#: Seconds `fleetmap sim` waits, once its robots stop, for the service to confirm their scans.
SIM_CONFIRM_TIMEOUT = 10.0
#: `check_fleet`'s parameters as `fleetmap sim`'s options, which its errors name: "robots must be
#: >= 1" left whoever typed `--robots 0` to work out which value was meant.
SIM_OPTIONS = {name: f"--{name}" for name in ("robots", "rate", "seconds", "beams", "speed", "seed")}


def add_sim_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "sim",
        help="simulated robots exploring a synthetic floor plan, publishing to the service",
        description=(
            "Simulated robots (ids sim-1, sim-2, ...) explore one synthetic floor plan and publish "
            "their scans to a running fleetmap service over Zenoh in real time, each with its own "
            "Zenoh session and liveliness token, until --seconds pass or Ctrl-C (or SIGTERM)."
        ),
    )
    p.add_argument("--robots", type=int, default=3, metavar="N", help="number of robots (default 3)")
    p.add_argument("--map", default="sim", dest="map_id", help="map id (default sim)")
    p.add_argument("--seed", type=int, default=1, help="floor plan and robots seed (default 1)")
    p.add_argument(
        "--rate", type=float, default=10.0, metavar="HZ", help="scans per second per robot (default 10)"
    )
    p.add_argument(
        "--seconds", type=float, default=None, metavar="T", help="stop after T s (default: Ctrl-C)"
    )
    p.add_argument("--beams", type=int, default=1081, help="beams per scan over 270 degrees (default 1081)")
    p.add_argument("--speed", type=float, default=1.0, help="robot speed, m/s, 0 to 50 (default 1)")
    p.add_argument(
        "--confirm-timeout", type=float, default=SIM_CONFIRM_TIMEOUT, metavar="S",
        help="once the robots stop, wait at most S seconds in all for the service to confirm every "
        f"scan (default {SIM_CONFIRM_TIMEOUT:g}); exit 1 when some are not",
    )  # fmt: skip
    p.add_argument(
        "--no-confirm", action="store_true",
        help="do not ask the service whether the scans are integrated (for a service older than that)",
    )  # fmt: skip
    _add_connection(p)
    p.set_defaults(run=run_sim_command)
    return p


def run_sim_command(args: argparse.Namespace) -> int:
    from fleetmap.http_limits import raise_descriptor_limit
    from fleetmap.wire import ID_PATTERN, is_valid_id

    from .sim import SERVICE_SESSIONS, SimError, check_fleet, run_sim
    from .zenoh_config import client_config

    if not is_valid_id(args.map_id):
        raise CliError(f"map id {args.map_id!r} must match {ID_PATTERN}")
    # As fleetmap serve does; before check_fleet, which counts the file descriptors robots need.
    raise_descriptor_limit()
    try:  # before the line announcing the robots
        check_fleet(args.robots, args.rate, args.seconds, args.beams, args.speed, args.seed, SIM_OPTIONS)
        # The robots' Zenoh configuration too (an endpoint `foo`, a missing --zenoh-config file): it
        # was refused only as their sessions opened, after the banner had announced them.
        client_config(args.connect, args.zenoh_config)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    # Before the line announcing the robots too, named as options (run_sim checks them again).
    for option, value in (("--confirm-timeout", args.confirm_timeout), ("--wait-timeout", args.wait_timeout)):
        if value is not None and not value >= 0.0:  # NaN: the wait for the service never ended
            raise CliError(f"{option} must be a number of seconds >= 0, got {value}")
    if args.robots > SERVICE_SESSIONS:
        # Past it the service refuses the other robots' sessions as an absent one would, and logs
        # nothing: without --wait-timeout the robots beyond waited for ever, with no word of why.
        print(
            f"fleetmap sim: warning: a fleetmap service takes at most {SERVICE_SESSIONS} robots at once "
            "unless its --zenoh-config raises transport/unicast/max_sessions (docs/protocol.md); the "
            "robots beyond wait for a free session",
            file=sys.stderr,
            flush=True,
        )
    stop = SignalEvent()

    # Ctrl-C (or SIGINT from a script that started us with SIGINT ignored) stops the robots, and the
    # summary of what they published is still printed; a second one ends the wait for confirmation.
    # SIGTERM too (`kill`, `docker stop`): it ended the sim at once, without its summary, and as a
    # container's PID 1 (compose.yaml's robots), which gets no signal it has no handler for, it was
    # not stopped at all until Docker killed it 10 s later.
    def interrupt(*_: object) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set_in_handler()

    previous = {sig: signal.signal(sig, interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    print(
        f"sim: {counted(args.robots, 'robot')} on map {args.map_id!r} "
        f"(floor plan seed {args.seed}), "
        f"{args.rate:g} scans/s each"
        # inf is no limit to run_sim, as None: "for inf s" announced one.
        + (f" for {args.seconds:g} s" if args.seconds not in (None, float("inf")) else ""),
        flush=True,
    )
    try:
        result = run_sim(
            args.robots,
            map_id=args.map_id,
            seed=args.seed,
            rate=args.rate,
            seconds=args.seconds,
            connect=args.connect,
            zenoh_config=args.zenoh_config,
            encoding=args.encoding,
            beams=args.beams,
            speed=args.speed,
            wait_timeout=args.wait_timeout,
            stop=stop,
            on_waiting=_waiting,
            confirm_timeout=None if args.no_confirm else args.confirm_timeout,
        )
    except (ValueError, SimError) as exc:
        raise CliError(str(exc)) from None
    except KeyboardInterrupt:
        print("sim interrupted", file=sys.stderr)
        return 130
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    dropped, kept = sum(result.dropped.values()), sum(result.backlogged.values())
    robots = len(result.robots)
    print(
        f"sim: {counted(robots, 'robot')} published {counted(result.total, 'scan')} in {result.seconds:.1f} s"
        + (f" ({kept} kept for re-delivery while the service was unreachable)" if kept else "")
        + (f" ({dropped} dropped)" if dropped else "")
    )
    warning = skipped_warning(result, args.rate)
    if warning is not None:
        advice = "run fewer, or fewer --beams or a lower --rate"
        print(f"fleetmap sim: warning: {warning} ({advice})", file=sys.stderr)
    if args.no_confirm:
        return 0
    if result.total == 0:
        # Stopped before a scan went out (Ctrl-C while it waited for the service, say): there is
        # nothing to confirm, and "all 0 scans confirmed integrated" claimed a service had answered.
        print("sim: nothing published, nothing to confirm")
        return 0
    if result.unconfirmable is not None:  # an older service: what sim always did, with a warning
        print(f"fleetmap sim: warning: not confirmed: {result.unconfirmable}", file=sys.stderr)
        return 0
    # As `fleetmap replay`: a robot's scans refused by the service (more beams than its --max-beams,
    # say) were reported as published, and the command said nothing more.
    for robot in result.robots:
        report = result.delivery.get(robot)
        if report is None or not report.confirmed:
            why = (
                report.summary()
                if report is not None
                else f"not confirmed: {result.confirm_errors.get(robot)}"
            )
            print(f"fleetmap sim: warning: {robot}: {why}", file=sys.stderr)
    if not result.confirmed:
        return 1
    integrated = sum(report.integrated for report in result.delivery.values())
    # "all 1 scans" was said of a sim that published one (`--seconds` shorter than a period).
    print(f"sim: {'the 1 scan' if integrated == 1 else f'all {integrated} scans'} confirmed integrated")
    return 0


# -- standalone ------------------------------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m fleetmap_client.cli {replay,sim} ...`: the same commands outside `fleetmap`."""
    parser = argparse.ArgumentParser(prog="fleetmap", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add_parser(sub)
    args = parser.parse_args(argv)
    return run_command(args)


if __name__ == "__main__":
    sys.exit(main())
