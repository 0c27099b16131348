"""The `fleetmap` command line.

`fleetmap build DATASET --out DIR` maps a recorded dataset with the engine and writes the exports.
Other commands live beside the code they drive, each module contributing an `add_parser(sub)`:
see `COMMAND_MODULES`.
"""

from __future__ import annotations

import argparse
import contextlib
import difflib
import importlib
import json
import logging
import os
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from pydantic import ValidationError

from fleetmap.codec import repeated_key
from fleetmap.config import MapConfig
from fleetmap.log_format import plain_line
from fleetmap.signal_event import HANGUPS, SignalEvent
from fleetmap.version import installed_version

if TYPE_CHECKING:
    from fleetmap.grid_map import GridMap
    from fleetmap.scan import Scan


def main(argv: Sequence[str] | None = None) -> int:
    give_stderr_a_sink()
    try:
        parser, sub = command_line_parser(sys.argv[1:] if argv is None else argv)
        args = parse_command_line(parser, sub, argv)
    except KeyboardInterrupt:
        # Ctrl-C in the second or two the commands' modules (numba's among them) take to import
        # ended in the traceback of the import in progress; one line, as `run_command` says it.
        print("fleetmap: interrupted", file=DiagnosticStream(sys.stderr))
        return INTERRUPTED
    if HANGUPS.holding and not getattr(args, "takes_hangup", False):
        # A command that does not take SIGHUP (`takes_hangup`): its default action from now on,
        # and a SIGHUP held meanwhile ends it now, as it would have.
        HANGUPS.release(signal.SIG_DFL)
    return run_command(args)


def command_line_parser(
    argv: Sequence[str] | None = None,
) -> tuple[argparse.ArgumentParser, argparse._SubParsersAction[argparse.ArgumentParser]]:
    """The `fleetmap` command line's parser (its own options: `--version`) and its commands' (each
    command's parser is `sub.choices[name]`). For a command line `argv` (without the program's
    name) that names a command first, only that command's module is imported and only its commands'
    parsers added (`command_modules`); for any other `argv`, and for None, every command's."""
    parser = argparse.ArgumentParser(prog="fleetmap", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"fleetmap {installed_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    modules = command_modules(argv)
    if modules is None or argv and argv[0] == "build":
        _add_build(sub)
    if modules is None:
        modules = list(dict.fromkeys(COMMAND_MODULES.values()))  # each once, in the table's order
    for name in modules:
        importlib.import_module(name).add_parser(sub)
    return parser, sub


def command_modules(argv: Sequence[str] | None) -> list[str] | None:
    """The modules of `COMMAND_MODULES` the command line `argv` needs: none for `build` (its parser is
    this module's), its command's module for a command given first, and None (every command's) for
    anything else: no command, an unknown one, `--help` or `--version` before it, `argv` None."""
    if not argv or argv[0].startswith("-"):
        return None
    if argv[0] == "build":
        return []
    module = COMMAND_MODULES.get(argv[0])
    return None if module is None else [module]


def parse_command_line(
    parser: argparse.ArgumentParser,
    sub: argparse._SubParsersAction[argparse.ArgumentParser],
    argv: Sequence[str] | None,
) -> argparse.Namespace:
    """`parser.parse_args(argv)`, but an argument no option takes is refused by its command's parser:
    argparse's top level said `fleetmap: error: unrecognized arguments: --data_dir x` under the usage
    `fleetmap [-h] COMMAND ...`, which names neither the command nor its options. Now the command's
    own error (`fleetmap serve: error: ...`, with `serve`'s one-line form), naming the option a
    mistyped one looks like."""
    args, extras = parser.parse_known_args(argv)
    if extras:
        command = sub.choices[args.command]
        command.error(unrecognized_arguments(command, extras))
    return args


def unrecognized_arguments(parser: argparse.ArgumentParser, extras: Sequence[str]) -> str:
    """The error for `extras`, with the option each one that looks like an option may stand for
    (`--data_dir`: `--data-dir`)."""
    options = [option for action in parser._actions for option in action.option_strings]
    hints = []
    for word in extras:
        if word.startswith("--"):
            name = word.split("=", 1)[0]
            close = difflib.get_close_matches(name.replace("_", "-").lower(), options, n=1, cutoff=0.75)
            if close:
                hints.append(f"{name}: did you mean {close[0]}?")
    return f"unrecognized arguments: {' '.join(extras)}" + (f" ({'; '.join(hints)})" if hints else "")


def run_command(args: argparse.Namespace) -> int:
    """Run a parsed subcommand; a `CliError` is printed without a traceback, exit code 2 (as a
    JSON log object with `serve --log-format json`, whose log pipeline reads JSON only). Ctrl-C
    that the command does not take itself is one line, exit code `INTERRUPTED`; a stdout whose
    reader exited ends the command quietly, exit code `STDOUT_GONE`."""
    try:
        try:
            return int(args.run(args) or 0)
        finally:
            # Here, not in the interpreter's exit: a failure of it is then caught below.
            if sys.stdout is not None:
                sys.stdout.flush()
    except CliError as exc:
        line = plain_line(
            f"fleetmap {args.command}: error: {exc}", getattr(args, "log_format", "text"), logging.ERROR
        )
        print(line, file=DiagnosticStream(sys.stderr))
        return 2
    except KeyboardInterrupt:  # Ctrl-C where a command does not take it itself
        print(f"fleetmap {args.command}: interrupted", file=DiagnosticStream(sys.stderr))
        return INTERRUPTED
    except BrokenPipeError:
        # `fleetmap build ... | head -1`, `fleetmap sim | grep -m1 ...`: the reader had what it
        # wanted. This ended in a traceback, exit 1, or (stdout buffered) in Python's "Exception
        # ignored ... BrokenPipeError" at exit, exit 120.
        discard_stdout()
        return STDOUT_GONE


def give_stderr_a_sink() -> None:
    """Point a missing stderr at /dev/null. A command started with file descriptor 2 closed (`2>&-`,
    a daemon's child) has `sys.stderr` None: a notice printed to it (`file=None`) went to STDOUT,
    into the summary a script reads, and tqdm's progress bar raised AttributeError (a build exited
    1, having written and said nothing). Its diagnostics now go nowhere, as a closed stderr means.
    /dev/null takes the lowest free descriptor: 2 when only stderr is closed, which child processes
    then inherit as theirs."""
    if sys.stderr is None:
        sys.stderr = open(os.devnull, "w")  # noqa: SIM115 - the process's stderr until it exits


def print_out(lines: Sequence[str]) -> None:
    """Print `lines` to stdout, and flush it. A stdout that cannot be written (a file on a full disk,
    /dev/full) raises `CliError` saying so, its output discarded (`discard_stdout`): `print` raised
    OSError, a traceback and exit 1. A reader gone raises BrokenPipeError, which `run_command`
    takes."""
    try:
        print("\n".join(lines), flush=True)
    except BrokenPipeError:
        raise
    except OSError as exc:
        discard_stdout()
        raise CliError(f"cannot write to stdout: {exc.strerror or exc}") from None


def discard_stdout() -> None:
    """Point stdout (file descriptor 1's) at /dev/null, once it cannot be written (its reader gone, a
    full disk): what is still in its buffer, and whatever comes later, then goes nowhere, and the
    interpreter's flush at exit does not fail again (a clean stop exited 120)."""
    _point_at_devnull(sys.stdout)


def _point_at_devnull(stream: TextIO) -> None:
    """Make `stream`'s file descriptor /dev/null's: what it still buffers, and all it is given later,
    is then written, and goes nowhere."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, stream.fileno())
    os.close(devnull)


class DiagnosticStream:
    """A command's stderr as its diagnostics (notices, the progress bar, its error line) are written
    to it: once it cannot take them (its reader has exited: `2>&1 | head -1`, a log reader that
    died; a full disk: `2>/dev/full`), they go nowhere (`_point_at_devnull`) instead of raising out
    of the command's work. `fleetmap build` ended so with exit 141 and without its map, the
    integration thrown away for a line no one would read; an error line ended in a traceback and
    exit 1 where the error's code is 2. (A command's result goes to stdout, which says, by
    `STDOUT_GONE`, whether its reader was there.) Every other attribute is the stream's (`encoding`,
    `fileno`, `isatty`: what tqdm asks of its file)."""

    def __init__(self, stream: TextIO) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except OSError:
            _point_at_devnull(self._stream)
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except OSError:
            _point_at_devnull(self._stream)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


#: The exit code of a command that Ctrl-C stopped: a shell's code for SIGINT (128 + 2).
INTERRUPTED = 130
#: The exit code of a command whose stdout's reader exited: a shell's code for a command that
#: SIGPIPE ended (128 + 13), as other commands in a pipeline end when they write to it.
STDOUT_GONE = 141


#: The commands other modules add, each with its module: the module's `add_parser(sub)` calls
#: `sub.add_parser(...)` for each of its commands and sets `run=callable(args) -> int`. Raising
#: `CliError` from `run` prints a clean error, exit 2. A command line that names its command imports
#: that module alone (`command_modules`): `fleetmap build` imported the service's and the demo's
#: modules too, 0.7 s of its start.
COMMAND_MODULES = {
    "demo": "fleetmap.cli_demo",
    "serve": "fleetmap.server",
    "replay": "fleetmap_client.cli",
    "sim": "fleetmap_client.cli",
}


class CliError(Exception):
    """An error the user can fix; printed without a traceback."""


def counted(number: int, noun: str) -> str:
    """`number` and `noun`, plural but for 1, as the commands' summaries say it ("1 robots published
    1 scans", "too busy for 1 robots" were printed)."""
    return f"{number} {noun}{'' if number == 1 else 's'}"


def dataset_error(path: str, exc: Exception) -> CliError:
    """The `CliError` for a dataset `load_dataset` could not read. A missing one gets a hint: the
    README's examples name `../shared/datasets/...`, which a fresh clone does not have, and a bare
    `[Errno 2] No such file or directory` left a newcomer with no idea where to find a log."""
    if isinstance(exc, FileNotFoundError):
        return CliError(
            f"no such file: {path} (a recorded laser log: CARMEN, plain or .gz, or MATLAB .mat; a "
            'clone of fleetmap has none: README.md, "Build a map from a recorded dataset", says '
            "where to find one)"
        )
    if isinstance(exc, OSError) and exc.strerror:
        # A folder given for the log said "[Errno 21] Is a directory: 'logs'".
        return CliError(
            f"cannot read {path}: {exc.strerror} (give a recorded laser log: CARMEN, plain or .gz, or .mat)"
        )
    return CliError(str(exc))


def load_config(path: str | None, **overrides: object) -> MapConfig:
    """A map configuration from a JSON file (or defaults), with command-line overrides applied: each
    keyword is a field, given by the option `--field-name` (`no_return_range`: `--no-return-range`),
    or None when not given. Raises `CliError` if the file cannot be read, is not JSON text (UTF-8, or
    the UTF-16 / 32 that JSON allows), nests too deeply for the parser, holds a key twice in one
    object or does not validate; a field that does not is named as the user gave it: the option, or
    the field in the file."""
    data: dict[str, object] = {}
    if path:
        try:
            data = json.loads(Path(path).read_bytes(), object_pairs_hook=_unique_keys)
        except (OSError, json.JSONDecodeError) as exc:
            raise CliError(f"cannot read config {path}: {exc}") from None
        except _RepeatedKey as exc:
            raise CliError(f"cannot read config {path}: the key {exc} appears twice in an object") from None
        except UnicodeDecodeError as exc:  # not text: a traceback and exit 1 said nothing of the file
            raise CliError(f"cannot read config {path}: not UTF-8 text (byte {exc.start})") from None
        except RecursionError:  # arrays in arrays thousands deep: json's parser recurses
            raise CliError(f"cannot read config {path}: its JSON nests too deeply") from None
        if not isinstance(data, dict):
            raise CliError(f"config {path} must hold a JSON object")
    given = {k: v for k, v in overrides.items() if v is not None}
    data.update(given)
    try:
        return MapConfig.model_validate(data)
    except ValidationError as exc:
        problems = [f"{_config_source(e['loc'], given, path)}: {e['msg']}" for e in exc.errors()]
        raise CliError("invalid map configuration: " + "; ".join(problems)) from None


def _config_source(loc: tuple[int | str, ...], options: dict[str, object], path: str | None) -> str:
    """Where the value at `loc` of a configuration came from, as the user gave it: `--resolution`
    for an option's (`load_config`'s keyword `resolution`), `tsdf.max_weight in FILE.json` for the
    file's. Naming the field for an option's value ("resolution: Input should be ...") left whoever
    typed `--resolution 0` to work out that it meant the option."""
    field = ".".join(map(str, loc))
    if not field:
        return "config"
    if loc[0] in options:
        return "--" + str(loc[0]).replace("_", "-")
    return f"{field} in {path}" if path else field


class _RepeatedKey(Exception):
    """A JSON object of a configuration file holds this key twice."""


def _unique_keys(pairs: list[tuple[str, object]]) -> dict[str, object]:
    """`json.loads`' object hook for configuration files: a key given twice (`"resolution": 0.05`,
    later `"resolution": 0.1`) was read as its last value, silently; which one was meant is a guess,
    and the REST API refuses such a body (as `PUT /maps/{id}` takes the same configuration)."""
    repeated = repeated_key(pairs)
    if repeated is not None:
        raise _RepeatedKey(repr(repeated))
    return dict(pairs)


# -- build -----------------------------------------------------------------------------------------


def _add_build(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "build",
        help="build a map from a recorded dataset (CARMEN log or .mat)",
        # The other commands' --help say what they do; this one showed its usage and options only.
        description="Build a map from a recorded laser log with the engine alone (no service, no "
        "Zenoh), and write it into --out as a nav2 map_server map (map.yaml, map.pgm), a PNG, every "
        "layer as .npy and meta.json (README.md, 'Build a map from a recorded dataset').",
    )
    p.add_argument("dataset", help="CARMEN log (plain or .gz) or MATLAB .mat file")
    p.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        help="directory for map.yaml, map.pgm, map.png, *.npy, meta.json",
    )
    p.add_argument("--config", metavar="FILE.json", help="map configuration as a JSON file")
    # Each says what it is when not given: "--resolution (default 0.05)" was wrong with a --config
    # file of another resolution, which is used.
    p.add_argument(
        "--resolution",
        type=float,
        metavar="R",
        help="metres per cell (default: the --config file's, else 0.05)",
    )
    p.add_argument(
        "--range-min",
        type=float,
        metavar="M",
        help="ignore readings below this, metres (default 0.001: zeros are ignored)",
    )
    p.add_argument(
        "--range-max",
        type=float,
        metavar="M",
        help="readings at or above this are 'no return', metres (default: the log's own, none for .mat)",
    )
    p.add_argument(
        "--no-return-range",
        type=float,
        metavar="M",
        help="clear this many metres of no-return beams (default: the --config file's, else 0: ignore them)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(run=_build)


def _build(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from fleetmap.datasets import DatasetError, load_dataset
    from fleetmap.datasets.base import check_range_window
    from fleetmap.export import earlier_build_files, write_build_outputs
    from fleetmap.grid_map import GridMap
    from fleetmap.scan import ScanError
    from fleetmap.tiles import TileLimitError

    config = load_config(args.config, resolution=args.resolution, no_return_range=args.no_return_range)
    try:
        # Here, with the options' names, not only as the log is read (which names the fields).
        check_range_window(args.range_min, args.range_max, names=("--range-min", "--range-max"))
    except DatasetError as exc:
        raise CliError(str(exc)) from None
    if not args.out.strip():
        # Path("") is the current folder: `--out "$OUT"` with OUT unset wrote the map there.
        raise CliError("--out is empty: give the folder to write the map into")
    out_dir = Path(args.out)
    _check_out_dir(out_dir)  # before the build, which can take minutes, is done for nothing
    try:
        dataset = load_dataset(args.dataset, range_min=args.range_min, range_max=args.range_max)
    except (DatasetError, OSError) as exc:
        raise dataset_error(args.dataset, exc) from None
    gmap = GridMap(config)
    diagnostics = DiagnosticStream(sys.stderr)
    if len(dataset):
        _load_kernels(config, dataset[0], args.quiet, diagnostics)
    started = time.perf_counter()
    updates = tsdf_updates = skipped = done = 0
    # Ctrl-C is taken between two scans: raised inside a compiled kernel's call, KeyboardInterrupt
    # came out as numba's SystemError ("returned a result with an exception set"), a traceback and
    # exit 1. A build started with SIGINT ignored keeps ignoring it, as Python does: a script's
    # `fleetmap build ... &` is started so, that a Ctrl-C meant for the script leaves it running,
    # and the handler put in place of the ignore stopped it ("interrupted", nothing written).
    interrupted = SignalEvent()
    previous = signal.getsignal(signal.SIGINT)
    if previous is not signal.SIG_IGN:
        signal.signal(signal.SIGINT, lambda *_: interrupted.set_in_handler())
    try:
        for scan in tqdm(dataset, total=len(dataset), unit="scan", disable=args.quiet, file=diagnostics):
            if interrupted.is_set():
                break
            done += 1
            try:
                result = gmap.integrate(scan)
                updates += result.cell_updates
                tsdf_updates += result.tsdf_updates
            except (ScanError, TileLimitError) as exc:
                skipped += 1
                # Which one: a log holds thousands, and 'skipped a scan' could not be found in it.
                tqdm.write(f"skipped scan {done} of {len(dataset)}: {exc}", file=diagnostics)
            except MemoryError:
                raise CliError(_out_of_memory(gmap, done, len(dataset))) from None
    finally:
        if previous is not signal.SIG_IGN:
            signal.signal(signal.SIGINT, previous)
    if interrupted.is_set():
        print(
            f"fleetmap build: interrupted after {done} of {len(dataset)} scans; nothing written",
            file=diagnostics,
        )
        return INTERRUPTED
    elapsed = time.perf_counter() - started
    earlier = earlier_build_files(out_dir)
    try:
        written = write_build_outputs(gmap, out_dir)
    except ValueError as exc:
        # Why it is empty, when scans were skipped: the error alone read as if the log held nothing.
        why = f" ({skipped} of {len(dataset)} scans skipped, see above)" if skipped else ""
        raise CliError(f"{exc}{why}") from None
    except OSError as exc:  # a full disk, or a directory made unwritable during the build
        raise CliError(f"cannot write the outputs to {out_dir}: {exc}") from None
    except MemoryError:
        raise CliError(_too_large(gmap)) from None
    rates = [f"{updates / max(elapsed, 1e-9) / 1e6:.1f} M cell updates/s"] if config.has_cell_layers else []
    if config.has("tsdf"):  # a TSDF-only map said "0.0 M cell updates/s"
        rates.append(f"{tsdf_updates / max(elapsed, 1e-9) / 1e6:.1f} M TSDF updates/s")
    print_out(
        [
            f"{counted(len(dataset) - skipped, 'scan')} integrated ({skipped} skipped) in {elapsed:.2f} s, "
            f"{', '.join(rates)}, {len(gmap.store)} tiles",
            *(f"wrote {path}" for path in written),
            *(
                f"removed {path}, an earlier build's: this map has no such layer"
                for path in earlier
                if path not in written
            ),
        ]
    )
    return 0


def _too_large(gmap: GridMap) -> str:
    """The error for a map whose dense exports do not fit in memory. One pose kilometres from the
    others (a log's glitch, or two sessions in one log) spans the map over all the space between:
    the sparse tiles hold it, but its images and arrays cover the whole window, and the build
    ended in numpy's traceback ('Unable to allocate 3.64 TiB')."""
    from fleetmap.export import known_window

    window = known_window(gmap)
    assert window is not None  # the exports refuse an empty map before they allocate
    ny, nx = window.shape
    res = gmap.resolution
    return (
        f"the map spans {nx} x {ny} cells ({nx * res:.6g} x {ny * res:.6g} m at {res:g} m), too many "
        f"for its images and arrays (map.pgm alone would be {nx * ny / 2**30:,.1f} GiB, each .npy four "
        "times that); look for a pose far from the others in the log, or use a coarser --resolution"
    )


def _out_of_memory(gmap: GridMap, scan: int, scans: int) -> str:
    """The error for a build whose map's tiles outgrew the memory the process may have. A map at a
    fine resolution (or of large tiles) grows its pools by doubling, and a growth past what the
    machine, or a `ulimit -v`, allows ended the build in numpy's traceback ('Unable to allocate
    2.50 GiB for an array with shape (40, 4096, 4096)'), exit 1."""
    from fleetmap.memory_budget import format_size

    store = gmap.store
    return (
        f"out of memory at scan {scan} of {scans}, growing the map past its {len(store)} tiles of "
        f"{store.tile_size} x {store.tile_size} cells ({format_size(store.memory_bytes())}); nothing "
        "written: use a coarser --resolution, or a --config with fewer layers or smaller tiles"
    )


def _load_kernels(
    config: MapConfig, scan: Scan, quiet: bool, diagnostics: DiagnosticStream | None = None
) -> None:
    """Load the compiled kernels `config`'s maps use, by integrating `scan` twice into a throwaway map
    (into a new tile, then an existing one: both paths of `GridMap.integrate`), so that the build's
    rate leaves them out. The first run after an install compiles them, which takes 15-30 s: it
    said nothing, and put the time into the rate it printed (0.3 M cell updates/s for 19). Unless
    `quiet`, a notice says so on `diagnostics` (default: stderr)."""
    from fleetmap.grid_map import GridMap
    from fleetmap.scan import ScanError
    from fleetmap.tiles import TileLimitError

    if not quiet:
        print("loading the engine's compiled kernels (the first run after an install compiles them)",
              file=diagnostics or DiagnosticStream(sys.stderr), flush=True)  # fmt: skip
    throwaway = GridMap(config)
    # The build skips such a scan and says so; and it stops at a scan whose tiles do not fit in
    # memory with a clear error, where this one ended in a traceback.
    with contextlib.suppress(ScanError, TileLimitError, MemoryError):
        throwaway.integrate(scan)
        throwaway.integrate(scan)


def _check_out_dir(out_dir: Path) -> None:
    """Raise `CliError` unless `out_dir` is a directory, or can be made one, that can be written to:
    its nearest existing ancestor must be a writable directory. Creates nothing, so that a build
    that fails later (no observed cell) leaves no empty directory behind."""
    existing = out_dir
    try:
        while not existing.exists() and existing != existing.parent:
            existing = existing.parent
        is_dir = existing.is_dir()
    except OSError as exc:
        # `exists` answers False only for a name that is not there: a name too long for the file
        # system, or one in a folder the user may not look into, raised, and ended in a traceback.
        raise CliError(f"cannot write the outputs to {out_dir}: {exc.strerror or exc}") from None
    if not is_dir:
        raise CliError(f"cannot write the outputs to {out_dir}: {existing} is not a directory")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise CliError(f"cannot write the outputs to {out_dir}: {existing} is not writable")


if __name__ == "__main__":
    # Run as `python -m fleetmap.cli`, this file is `__main__`, and the command modules would raise
    # `fleetmap.cli.CliError`, another class than this module's: go through the real module.
    from fleetmap.cli import main as cli_main

    sys.exit(cli_main())
