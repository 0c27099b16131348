"""The user's documentation stays true to the program (README.md and docs/*.md but the benchmarks'):

- the ```console examples of docs/api.md run as written (curl, python, unzip) against the real
  service, in the page's order after the examples that make its map, and print what the page shows:
  `...` stands for anything, and whitespace is not compared, since the page wraps long JSON;
- every `--option` given to a `fleetmap` command exists in that command's parser, and every other
  `--option` named exists in one of them (or is one of the few of other tools, listed here);
- every `fleetmap_*` and `process_*` metric named is exported on the service's /metrics, and every
  metric exported is in docs/api.md's table of them;
- README.md's "Layout" table places every module of the service and the clients, and names no other;
- every relative link leads to a file, and its `#anchor` to a heading there; every file
  docs/architecture.md names exists.
"""

from __future__ import annotations

import argparse
import ast
import itertools
import json
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from service_process import REPO_DIR, ServiceProcess

from fleetmap import cli

USER_DOCS = [REPO_DIR / "README.md"] + [
    path for path in sorted((REPO_DIR / "docs").glob("*.md")) if not path.name.startswith("benchmark")
]
API_DOC = REPO_DIR / "docs" / "api.md"
#: The api.md examples that make the map the others read, run first: `PUT` the map, `POST` its scan.
SETUP_COMMANDS = ("-X PUT $U/maps/warehouse ", "$U/maps/warehouse/scans?robot_id=robot1")
#: Options the docs give to other programs than `fleetmap`.
#: curl's --http1.1 is matched as --http1.
OTHER_TOOLS_OPTIONS = {"--build", "--data-binary", "--http1", "--http2", "--max-time", "--ros-args"}
#: `fleetmap_*` names that are not metrics: a Python package, the browser session's cookie.
NOT_METRICS = {"fleetmap_client", "fleetmap_session", "fleetmap_scans"}  # the last: a ROS node


def console_steps(doc: Path) -> list[tuple[str, str]]:
    """(command, expected output) of every `$ ` line of the doc's ```console blocks, in order. A
    command goes on over lines ending in a backslash or inside an open single quote."""
    steps = []
    for block in re.findall(r"^```console\n(.*?)^```", doc.read_text(encoding="utf-8"), re.M | re.S):
        lines = block.splitlines()
        k = 0
        while k < len(lines):
            assert lines[k].startswith("$ "), (
                f"{doc.name}: a console block line that is no command: {lines[k]}"
            )
            command = lines[k][2:]
            while command.endswith("\\") or command.count("'") % 2:
                k += 1
                command += "\n" + lines[k]
            k += 1
            output = []
            while k < len(lines) and not lines[k].startswith("$ "):
                output.append(lines[k])
                k += 1
            steps.append((command, "\n".join(output)))
    return steps


def shows(expected: str, actual: str) -> bool:
    """Whether `actual` is what the doc shows as `expected` (`...`: anything; whitespace ignored)."""
    parts = [re.escape(re.sub(r"\s+", "", part)) for part in expected.split("...")]
    return re.fullmatch(".*?".join(parts), re.sub(r"\s+", "", actual), re.S) is not None


def test_api_examples_print_what_the_page_shows(service: ServiceProcess, tmp_path: Path) -> None:
    """On a service of its own: the examples show its only map, `warehouse`."""
    steps = console_steps(API_DOC)
    setup = [step for step in steps if any(s in step[0] for s in SETUP_COMMANDS)]
    assert len(setup) == len(SETUP_COMMANDS), f"docs/api.md should have one example each of {SETUP_COMMANDS}"
    bin_dir = str(Path(sys.executable).parent)  # `python` is the tests' interpreter, with numpy
    env = {**os.environ, "U": service.base_url, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}
    for command, expected in setup + [step for step in steps if step not in setup]:
        run = subprocess.run(
            ["bash", "-c", command], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60
        )
        assert shows(expected, run.stdout), (
            f"docs/api.md: `{command}` printed\n{run.stdout}{run.stderr}\nwhere the page shows\n{expected}"
        )


def fleetmap_parsers() -> dict[str, set[str]]:
    """Each `fleetmap` command's options, from the real parsers, and under "" the command line's own
    (`fleetmap --version`)."""
    parser, sub = cli.command_line_parser()
    parsers = {"": parser, **sub.choices}
    return {name: {o for a in p._actions for o in a.option_strings} for name, p in parsers.items()}


def test_no_command_help_shows_a_default_of_none() -> None:
    """`fleetmap demo --help` said "--seconds ... (default: None)": each command's help, as a user
    reads it, shows only defaults a user can read."""
    _, sub = cli.command_line_parser()
    for command, p in sub.choices.items():
        text = p.format_help()
        assert "default: None" not in text and "(None" not in text, f"fleetmap {command} --help:\n{text}"
        # An on/off flag's "(default: False)": off unless given, which every flag is. (Help lines
        # wrap: "(default:" may end one.)
        assert "default: False" not in " ".join(text.split()), f"fleetmap {command} --help:\n{text}"


def test_every_command_help_says_what_the_command_does() -> None:
    """`fleetmap build --help` was its usage and options alone, where every other command's says
    what it does first."""
    _, sub = cli.command_line_parser()
    silent = [command for command, p in sub.choices.items() if not (p.description or "").strip()]
    assert not silent, f"commands whose --help does not say what they do: {silent}"


def test_every_option_with_a_default_says_it_in_its_help() -> None:
    """`fleetmap replay --help` and `fleetmap sim --help` said "--encoding: payload encoding", not
    which one they send when not told (binary, as docs/clients.md says). An option whose default
    is a list, empty, or none, says nothing."""
    _, sub = cli.command_line_parser()
    silent = []
    for command, p in sub.choices.items():
        formatter = p.formatter_class(prog=p.prog)
        for action in p._actions:
            if action.default in (None, False, [], argparse.SUPPRESS):
                continue
            if "default" not in formatter._get_help_string(action):  # type: ignore[attr-defined]
                silent.append(f"fleetmap {command} {'/'.join(action.option_strings)}")
    assert not silent, f"options that do not say their default: {silent}"


def test_every_option_the_docs_name_exists() -> None:
    parsers = fleetmap_parsers()
    known = set().union(*parsers.values()) | OTHER_TOOLS_OPTIONS
    wrong = []
    for doc in USER_DOCS:
        for n, line in enumerate(doc.read_text(encoding="utf-8").splitlines(), 1):
            for option in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", line):
                if option not in known:
                    wrong.append(f"{doc.name}:{n}: {option} is no option of any fleetmap command")
            # A command in a code span or a code line: `fleetmap sim --robots 4 ...`.
            for command, rest in re.findall(r"fleetmap (build|demo|serve|replay|sim)\b([^`\n]*)", line):
                for option in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", rest.split("#")[0]):
                    if option not in parsers[command]:
                        wrong.append(f"{doc.name}:{n}: `fleetmap {command}` has no {option}")
    assert not wrong, "\n".join(wrong)


def test_the_command_synopses_of_clients_md_list_every_option() -> None:
    """docs/clients.md shows `fleetmap replay` and `fleetmap sim` as a usage block; both lacked
    `--zenoh-config` (TLS robots), which `--help` lists."""
    parsers = fleetmap_parsers()
    text = (REPO_DIR / "docs" / "clients.md").read_text(encoding="utf-8")
    for command in ("replay", "sim"):
        blocks = re.findall(rf"^```\n(fleetmap {command} .*?)^```", text, re.M | re.S)
        assert len(blocks) == 1, f"docs/clients.md: one usage block of fleetmap {command}"
        shown = set(re.findall(r"--[a-z][a-z0-9-]*", blocks[0]))
        missing = sorted(parsers[command] - shown - {"-h", "--help"})
        assert not missing, f"docs/clients.md: the usage of fleetmap {command} lacks {missing}"


@pytest.fixture(scope="module")
def metrics_service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One durable service with the default options for the module's two tests of its /metrics:
    both only read it, once `scrape_with_every_series` has made every series exist."""
    with ServiceProcess(tmp_path_factory.mktemp("docs-metrics")) as service:
        yield service


def scrape_with_every_series(service: ServiceProcess) -> str:
    """`service`'s /metrics once a robot has sent a scan and a tile was drawn: per-map and per-robot
    series exist only then, tile renders only once one is drawn."""
    url = f"{service.base_url}/maps/metrics-check"
    scan = {"seq": 0, "pose": {"x": 0, "y": 0, "theta": 0}, "angle_min": 0, "angle_increment": 0.1,
            "ranges": [1.0]}  # fmt: skip
    httpx.post(f"{url}/scans?robot_id=r1", json=scan).raise_for_status()
    httpx.get(f"{url}/tiles/0/0/-1.png").raise_for_status()
    return httpx.get(f"{service.base_url}/metrics").text


def test_every_metric_the_docs_name_is_exported(metrics_service: ServiceProcess) -> None:
    """On a durable service with the default options, as the docs describe: its storage metrics exist."""
    exported = scrape_with_every_series(metrics_service)
    missing = []
    for doc in USER_DOCS:
        for name in (
            set(re.findall(r"\b(?:fleetmap|process)_[a-z_]+\*?", doc.read_text(encoding="utf-8")))
            - NOT_METRICS
        ):
            prefix = name.rstrip("*")  # `fleetmap_http_delay*`: every metric that starts so
            pattern = (
                rf"^{prefix}\w*[{{ ]" if name.endswith("*") else rf"^{prefix}(_bucket|_sum|_count)?[{{ ]"
            )
            if not re.search(pattern, exported, re.M):
                missing.append(f"{doc.name}: {name}")
    assert not missing, "not on /metrics:\n" + "\n".join(sorted(missing))
    # The other way round: an operator reads docs/api.md's table to know what to alert on, so a
    # metric exported but not listed there is one nobody finds (the Zenoh session's, HTTP answers by
    # status and storage failures were added without it at first). `*_created`: prometheus_client's
    # creation times of its own counters and histograms, not metrics of the service.
    table = API_DOC.read_text(encoding="utf-8").split("### `GET /metrics`", 1)[1].split("\n### ", 1)[0]
    listed = set(re.findall(r"`((?:fleetmap|process)_[a-z_]+\*?)`", table))
    undocumented = [
        name
        for name in sorted(set(re.findall(r"^# TYPE (\S+) ", exported, re.M)))
        if not name.endswith("_created")
        and name not in listed
        and not any(n.endswith("*") and name.startswith(n[:-1]) for n in listed)
    ]
    assert not undocumented, "exported but not in docs/api.md's table of metrics: " + ", ".join(undocumented)


#: PromQL functions meant for counters (they read a fall as a reset) and those meant for gauges.
COUNTER_FUNCTIONS = ("rate", "irate", "increase", "resets")
GAUGE_FUNCTIONS = ("delta", "idelta", "deriv", "predict_linear")


def test_the_alert_expressions_of_api_md_query_metrics_as_exported(metrics_service: ServiceProcess) -> None:
    """docs/api.md's "What to alert on" is copied into alerting rules: an expression naming a metric
    that does not exist finds no series and never fires, with no error. Its "scans lost" alert was
    `..._lost_total` under `increase()`, a counter renamed to the gauge `fleetmap_scans_lost` long
    before: an abbreviation nobody could paste, of a metric gone, under a function for counters."""
    exported = scrape_with_every_series(metrics_service)
    types = dict(re.findall(r"^# TYPE (\S+) (\S+)$", exported, re.M))
    text = API_DOC.read_text(encoding="utf-8")
    section = text.split("What to alert on, from `/metrics` alone:", 1)[1].split("\n\n", 2)[1]
    rows = [row.split("|")[2] for row in section.splitlines()[2:] if row.startswith("|")]
    assert len(rows) >= 8, "docs/api.md: the table of what to alert on was not found"

    def kind(name: str) -> str | None:
        """The type of `name` as exported; a histogram's `_bucket`, `_sum` and `_count` count up."""
        stem = re.sub(r"_(bucket|sum|count)$", "", name)
        return types.get(name) or ("counter" if types.get(stem) == "histogram" else None)

    wrong = []
    # The code spans that are queries (the cells also name options, a class, a status code).
    for expression in (span for row in rows for span in re.findall(r"`([^`]+)`", row) if "_" in span):
        if "..." in expression:
            wrong.append(f"{expression}: an abbreviation, not an expression to paste")
        names = re.findall(r"\b(?:fleetmap|process)_\w+", expression)
        wrong += [f"{expression}: {name} is not on /metrics" for name in names if kind(name) is None]
        for function, name in re.findall(r"\b(\w+)\(\s*((?:fleetmap|process)_\w+)", expression):
            if function in COUNTER_FUNCTIONS and kind(name) not in (None, "counter"):
                wrong.append(f"{expression}: {function}() of {name}, a {kind(name)}, not a counter")
            if function in GAUGE_FUNCTIONS and kind(name) not in (None, "gauge"):
                wrong.append(f"{expression}: {function}() of {name}, a {kind(name)}, not a gauge")
    assert not wrong, "docs/api.md, What to alert on:\n" + "\n".join(wrong)


def layout_paths() -> set[Path]:
    """The paths of README.md's "Layout" table: a row's first cell names a path, then names beside it
    (`service/fleetmap/scan.py`, `config.py`; `clients/web/`, `clients/python/fleetmap_client/`)."""
    readme = (REPO_DIR / "README.md").read_text(encoding="utf-8")
    section = readme.split("\n## Layout\n", 1)[1].splitlines()
    start = next(k for k, line in enumerate(section) if line.startswith("| path"))
    paths = set()
    for row in itertools.takewhile(lambda line: line.startswith("|"), section[start + 2 :]):
        folder = Path()
        for name in re.findall(r"`([^`]+)`", row.split("|")[1]):
            if "/" in name.rstrip("/"):
                folder = Path(name).parent
            paths.add(folder / name.removeprefix(f"{folder.as_posix()}/"))
    return paths


def test_the_alert_on_refused_scans_covers_those_counted_on_no_robot() -> None:
    """A scan refused for want of its map (`--no-auto-create`, or the service holding the most maps
    scans create) or of room for its robot on it (`--max-robots-per-map`) is counted on no robot:
    no `fleetmap_scans_*` series moves, only `fleetmap_zenoh_scans_refused_total` by its reason
    (and `fleetmap_ros_scans_refused_total` for ROS 2 robots). docs/api.md's alert on refused scans
    named the robots' series alone, so a fleet grown past the map's robots, whose new robots' scans
    were all refused, fired no documented alert; nothing answers a robot over Zenoh."""
    text = API_DOC.read_text(encoding="utf-8")
    section = text.split("What to alert on, from `/metrics` alone:", 1)[1].split("\n\n", 2)[1]
    (row,) = [row for row in section.splitlines() if row.startswith("| scans lost, dropped, refused |")]
    expressions = re.findall(r"`([^`]+)`", row)
    for reason in ("no_map", "too_many_robots"):
        for metric in ("fleetmap_zenoh_scans_refused_total", "fleetmap_ros_scans_refused_total"):
            assert any(metric in e and reason in e for e in expressions), (metric, reason, row)


def test_the_readme_layout_places_every_module() -> None:
    paths = layout_paths()
    missing = sorted(p.as_posix() for p in paths if not (REPO_DIR / p).exists())
    assert not missing, f"README.md's Layout table names {missing}, which do not exist"
    package = REPO_DIR / "service" / "fleetmap"
    modules = [p for p in package.iterdir() if p.suffix == ".py" or (p / "__init__.py").exists()]
    modules += [REPO_DIR / "clients" / "web"] + [
        p.parent for p in (REPO_DIR / "clients").glob("python/*/__init__.py")
    ]
    unplaced = [
        p.relative_to(REPO_DIR).as_posix()
        for p in modules
        if not any(p.relative_to(REPO_DIR).is_relative_to(placed) for placed in paths)
    ]
    assert not unplaced, f"README.md's Layout table does not place {unplaced}"


#: How the docs give the scans a robot's ingest queue holds (the number is the group).
QUEUE_PER_ROBOT_PHRASES = (
    r"robot's (?:ingest )?queue holds ([0-9][0-9 ,]*)",
    r"per-robot ingest queue \(([0-9][0-9 ,]*) scans",
    r"ingest queue holds ([0-9][0-9 ,]*) scans per robot",
    r"robot's FIFO \(([0-9][0-9 ,]*) by default",
    r"own bounded FIFO \(([0-9][0-9 ,]*) scans",
)


def test_the_docs_give_the_scans_a_robots_queue_holds_as_the_service_has_them() -> None:
    """api.md's "Ingest before reads" said each robot's queue holds 64 scans (and that a scan
    waiting too long is dropped) long after the queue held 1024, the number every other page gives:
    a reader sizing a robot's burst took the service to drop 16 times sooner than it does."""
    from fleetmap.registry import QUEUE_PER_ROBOT

    found = []
    for doc in USER_DOCS:
        text = re.sub(r"\s+", " ", doc.read_text(encoding="utf-8"))
        for phrase in QUEUE_PER_ROBOT_PHRASES:
            found += [(doc.name, int(re.sub(r"[ ,]", "", n))) for n in re.findall(phrase, text)]
    assert len(found) >= 5, found  # the phrases still find what the pages say
    assert all(n == QUEUE_PER_ROBOT for _, n in found), found


def documented_methods(doc: Path, table_head: str) -> dict[str, str]:
    """The `name(parameters)` of each row of the doc's table that starts with `table_head`: name
    -> its parameters as written (`\\|` as `|`)."""
    text = doc.read_text(encoding="utf-8")
    table = text[text.index(table_head) :].split("\n\n", 1)[0]
    rows = re.findall(r"^\| `(\w+)\((.*?)\)` \|", table, re.M)
    return {name: parameters.replace("\\|", "|") for name, parameters in rows}


def test_the_rest_client_methods_of_clients_md_have_their_real_signatures() -> None:
    """docs/clients.md's table of `FleetmapClient` methods showed `clear_region(..., if_match=None)`
    as a parameter that may be given by position, where it is keyword-only: a caller who went by
    the table and passed the ETag sixth got a TypeError. Each row's parameters are the method's, in
    order, a `*` where the keyword-only ones start, with the defaults it has (a row may leave a
    default out, or show the choices `"a"|"b"`, the first the default; `...`: as the row above);
    and every public method has a row."""
    import inspect

    from fleetmap_client.rest import FleetmapClient

    rows = documented_methods(REPO_DIR / "docs" / "clients.md", "| method | endpoint | returns |")
    public = {name for name, _ in inspect.getmembers(FleetmapClient, inspect.isfunction)}
    missing = sorted(n for n in public - set(rows) if not n.startswith("_") and n != "close")
    assert not missing, f"docs/clients.md's FleetmapClient table lacks {missing}"
    wrong = []
    for name, written in rows.items():
        if written == "...":
            continue
        parameters = list(inspect.signature(getattr(FleetmapClient, name)).parameters.values())[1:]
        keyword_only = False
        shown = []
        for part in (p.strip() for p in written.split(",") if p.strip()):
            if part == "*":
                keyword_only = True
                continue
            parameter, _, default = part.partition("=")
            shown.append((parameter, keyword_only, default.split("|")[0] or None))
        real = [(p.name, p.kind is p.KEYWORD_ONLY, p.default) for p in parameters]
        if [s[:2] for s in shown] != [r[:2] for r in real]:
            wrong.append(f"{name}({written}) is {name}{inspect.signature(getattr(FleetmapClient, name))}")
            continue
        for (parameter, _, default), (_, _, real_default) in zip(shown, real, strict=True):
            if default is not None and ast.literal_eval(default) != real_default:
                wrong.append(f"{name}: {parameter}'s default is {real_default!r}, not {default}")
    assert not wrong, "docs/clients.md:\n" + "\n".join(wrong)


def _number(text: str) -> float:
    """A number as the docs write it: `16 384`, `100,000`, `4 194 304`."""
    return float(re.sub(r"[ ,]", "", text))


def test_the_limits_tables_give_the_services_limits() -> None:
    """docs/security.md's table of input checks said a binary scan must be "version 1" long after
    the service read version 2 (the one with a session id, which `ScanPublisher` sends): a reader
    writing a robot in another language from that table would think session ids unreadable. The
    limits the tables of security.md and protocol.md state are the code's, and so are the sessions
    a robot's bookkeeping remembers, as docs/clients.md gives them for `flush_ended`."""
    from fleetmap.codec import DEFAULT_LIMITS, VERSION, VERSION_SESSION
    from fleetmap.config import MapConfig
    from fleetmap.registry import QUEUE_BYTES, QUEUE_PER_ROBOT, QUEUE_TOTAL
    from fleetmap.robot_state import MAX_SESSIONS
    from fleetmap.robot_state import MAX_SESSIONS_PUSHED_OUT as PUSHED_OUT

    limits = DEFAULT_LIMITS
    security = re.sub(r"\s+", " ", (REPO_DIR / "docs" / "security.md").read_text(encoding="utf-8"))
    protocol = re.sub(r"\s+", " ", (REPO_DIR / "docs" / "protocol.md").read_text(encoding="utf-8"))
    clients = re.sub(r"\s+", " ", (REPO_DIR / "docs" / "clients.md").read_text(encoding="utf-8"))
    number = r"([0-9][0-9 ,]*[0-9]|[0-9])"
    checks = [
        (security, rf"`--world-bound` metres \(default {number}\)", limits.world_bound),
        (security, rf"`--max-beams` \(default {number}\)", limits.max_beams),
        (security, rf"`--max-range` \(default {number} m\)", limits.max_range),
        (security, rf"a scan: at most 4 MiB \({number} bytes\)", limits.max_payload_bytes),
        (protocol, rf"\| payload size \| 4 MiB \({number} bytes\)", limits.max_payload_bytes),
        (protocol, rf"\| beams per scan \| {number} \(`--max-beams`", limits.max_beams),
        (protocol, rf"\| sensor pose \| .{{0,20}} ≤ {number} m \(`--world-bound`\)", limits.world_bound),
        (protocol, rf"\| trusted range \| {number} m \(`--max-range`\)", limits.max_range),
        (protocol, rf"\| sessions remembered \| {number} per robot", MAX_SESSIONS),
        (protocol, rf"\| sessions remembered \| [^|]*, and {number} more pushed out", PUSHED_OUT),
        # `flush_ended` of a session the robot has had too many others since: clients.md said 16
        # (and 8 after a restart) long after the service remembered 136, saved across restarts.
        (clients, rf"the robot has had more than {number} sessions since", MAX_SESSIONS + PUSHED_OUT),
        (clients, rf"it remembers a robot's {number} sessions heard last", MAX_SESSIONS),
        (clients, rf"heard last and {number} more pushed out by them", PUSHED_OUT),
        (protocol, rf"\| queued scans \| {number} per robot", QUEUE_PER_ROBOT),
        (protocol, rf"\| queued scans \| [^|]*, {number} in total", QUEUE_TOTAL),
        (protocol, rf"\| queued scans \| [^|]*, {number} MiB of decoded beams", QUEUE_BYTES / 2**20),
        (protocol, rf"\| tiles per map \| [^|]*\(default {number}\)", MapConfig().max_tiles),
    ]
    wrong = []
    for text, pattern, value in checks:
        found = re.findall(pattern, text)
        if len(found) != 1 or _number(found[0]) != value:
            wrong.append(f"{pattern}: the docs give {found}, the code {value}")
    layout = re.findall(r"\| binary layout \| magic, (versions? .*?), known flags", security)
    versions = {int(v) for v in re.findall(r"[0-9]+", layout[0])} if len(layout) == 1 else set()
    if versions != {VERSION, VERSION_SESSION}:
        wrong.append(f"security.md: the binary layout versions are {VERSION}, {VERSION_SESSION}: {layout}")
    assert not wrong, "\n".join(wrong)


def test_the_docs_give_every_503s_retry_after() -> None:
    """docs/api.md's "Errors" said every 503 carries `Retry-After` 5 for event streams, uploads
    and downloads, "else 1", and listed no 503 for a connection past `--max-http-connections`:
    that one, which the HTTP server answers itself, says 5, so a client tuned to the page retried
    five times too soon. The row names each 503 that says 5, and the numbers are the code's."""
    from fleetmap import http_limits
    from fleetmap.api import errors, events, routes_snapshot

    text = re.sub(r"\s+", " ", API_DOC.read_text(encoding="utf-8"))
    found = re.findall(
        r"Every 503 carries `Retry-After` \(seconds: ([0-9]+) for ([^)]*), else ([0-9]+)\)", text
    )
    assert len(found) == 1, found
    longer, which, otherwise = found[0]
    assert int(otherwise) == errors.RETRY_AFTER_SECONDS
    for seconds, named in (
        (events.RETRY_AFTER_SECONDS, "event streams"),
        (routes_snapshot.UPLOAD_RETRY_AFTER_SECONDS, "uploads and downloads"),
        (http_limits.RETRY_AFTER_SECONDS, "connections"),
    ):
        assert named in which and seconds == int(longer), (named, seconds, found)
    assert "`--max-http-connections`" in text.split("| 503 |", 1)[1].split("| 507 |", 1)[0]


#: Units of the defaults of docs/api.md's `ApiSettings` table, in the field's unit (seconds, bytes).
SETTING_UNITS = {"": 1, "s": 1, "MiB": 1 << 20}


def test_the_api_settings_table_gives_every_field_its_default() -> None:
    """docs/api.md's "Limits and settings" table is what someone embedding the app
    (`create_app(registry, ApiSettings(...))`) or sizing a deployment reads: every field of
    `ApiSettings` has a row, and each default written as a number is the field's."""
    import dataclasses

    from fleetmap.api.app import ApiSettings

    text = API_DOC.read_text(encoding="utf-8")
    table = text[text.index("| `ApiSettings` field |") :].split("\n\n", 1)[0]
    defaults = {f.name: f.default for f in dataclasses.fields(ApiSettings)}
    rows = re.findall(r"^\| ((?:`\w+`(?:, )?)+) \| ([^|]*) \|", table, re.M)
    listed = [name for names, _ in rows for name in re.findall(r"`(\w+)`", names)]
    assert sorted(listed) == sorted(defaults), f"fields {sorted(set(defaults) ^ set(listed))}"
    checked, wrong = 0, []
    for names, written in rows:
        fields = re.findall(r"`(\w+)`", names)
        values = re.sub(r"\(.*?\)", "", written).split(", ")
        if len(values) != len(fields):
            values = [written] * len(fields)  # one default for all, or none written as a number
        for name, value in zip(fields, values, strict=True):
            number = re.fullmatch(r"\s*([0-9][0-9 ]*(?:\.[0-9]+)?)\s*(s|MiB)?\s*", value)
            if number is None:
                continue
            checked += 1
            if float(number[1].replace(" ", "")) * SETTING_UNITS[number[2] or ""] != defaults[name]:
                wrong.append(f"{name}: the table says {value.strip()}, the default is {defaults[name]!r}")
    assert checked >= 18, checked  # the pattern still reads the numbers of the table
    assert not wrong, "docs/api.md, Limits and settings:\n" + "\n".join(wrong)


def test_the_map_configuration_table_gives_every_field_its_default() -> None:
    """docs/api.md's table of `PUT /maps/{map_id}`'s body is where a configuration is looked up:
    every field of `MapConfig` has a row, and each default written as a number or a JSON object of
    numbers is the field's. `beam` had no row: its parameters' defaults and limits were nowhere."""
    from fleetmap.config import MapConfig

    text = API_DOC.read_text(encoding="utf-8")
    start = text.index("### `PUT /maps/{map_id}`")
    table = text[text.index("| field | default | meaning |", start) :].split("\n\n", 1)[0]
    rows = dict(re.findall(r"^\| `(\w+)` \| ([^|]*) \|", table, re.M))
    assert sorted(rows) == sorted(MapConfig.model_fields), (
        f"fields {sorted(set(rows) ^ set(MapConfig.model_fields))}"
    )
    defaults = MapConfig()
    checked, wrong = 0, []
    for name, written in rows.items():
        value = getattr(defaults, name)
        shown = written.strip().strip("`")
        try:
            given = json.loads(shown)
        except ValueError:
            continue
        if isinstance(given, dict):
            if any(not isinstance(v, int | float) for v in given.values()):
                continue
            actual: object = {k: getattr(value, k) for k in given}
        else:
            actual = value
        checked += 1
        if given != actual:
            wrong.append(f"{name}: the table says {shown}, the default is {actual!r}")
    assert checked >= 6, checked  # the pattern still reads the table
    assert not wrong, "docs/api.md, PUT /maps/{map_id}:\n" + "\n".join(wrong)


def heading_anchors(doc: Path) -> set[str]:
    """The anchors GitHub gives the headings of `doc` (outside code blocks, whose `# comments` are
    no headings): lower case, punctuation but `-` and `_` left out, spaces as `-`, a repeated one
    numbered `-1`, `-2`, ..."""
    text = re.sub(r"^```.*?^```", "", doc.read_text(encoding="utf-8"), flags=re.M | re.S)
    anchors: set[str] = set()
    for heading in re.findall(r"^#{1,6} (.*)$", text, re.M):
        slug = re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")
        anchor, n = slug, 0
        while anchor in anchors:
            n += 1
            anchor = f"{slug}-{n}"
        anchors.add(anchor)
    return anchors


def test_every_link_of_the_docs_leads_somewhere() -> None:
    """A reader follows the pages' links ([docs/protocol.md](protocol.md#sessions)): each relative
    link names a file of the repository, and its `#anchor`, in a Markdown file, a heading there.
    A heading renamed leaves the links to it pointing at the top of the page, with no error."""
    wrong = []
    for doc in USER_DOCS:
        text = re.sub(r"^```.*?^```", "", doc.read_text(encoding="utf-8"), flags=re.M | re.S)
        for link in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"[a-z]+:", link):  # https:, mailto:
                continue
            path, _, anchor = link.partition("#")
            target = (doc.parent / path).resolve() if path else doc
            if not target.exists():
                wrong.append(f"{doc.name}: ({link}): no file {path}")
            elif anchor and target.suffix == ".md" and anchor not in heading_anchors(target):
                wrong.append(f"{doc.name}: ({link}): no heading #{anchor} in {target.name}")
    assert not wrong, "\n".join(wrong)


def test_every_file_architecture_md_names_exists() -> None:
    """docs/architecture.md is read with the code beside it: every file it names in a code span
    (`zenoh_ingest.py`, `api/events.py`, `clients/web/`'s `tiles.js`) is one of the repository's
    (found by the end of its path), so a module renamed or split leaves no name to search for
    in vain."""
    text = (REPO_DIR / "docs" / "architecture.md").read_text(encoding="utf-8")
    files = {
        p.relative_to(REPO_DIR).as_posix()
        for top in ("service", "clients", "tests", "scripts")
        for p in (REPO_DIR / top).rglob("*")
        if p.suffix in (".py", ".js")
    }
    named = set(re.findall(r"`([\w/]+\.(?:py|js))`", text))
    assert len(named) >= 50, named  # the pattern still finds the page's file names
    missing = sorted(n for n in named if not any(f == n or f.endswith(f"/{n}") for f in files))
    assert not missing, f"docs/architecture.md names files that do not exist: {missing}"


def test_the_threads_table_of_architecture_md_lists_every_thread_the_service_names() -> None:
    """docs/architecture.md's "Threads and locks" table is where a reader of a thread dump or a
    lock nesting looks a thread up: every `fleetmap-*` thread the service's code starts has a row
    (`fleetmap-sighup`, SIGHUP's token reload, had none)."""
    text = (REPO_DIR / "docs" / "architecture.md").read_text(encoding="utf-8")
    table = text.split("| thread in `fleetmap serve` |", 1)[1].split("\n\n", 1)[0]
    listed = set(re.findall(r"^\| `(fleetmap-[\w<>-]+)`", table, re.M))
    started = {
        re.sub(r"\{\w+\}", "<k>", name)
        for path in (REPO_DIR / "service" / "fleetmap").rglob("*.py")
        for name in re.findall(r"name=f?\"(fleetmap-[\w{}-]+)\"", path.read_text(encoding="utf-8"))
    }
    assert len(started) >= 7, started  # the pattern still finds the threads' names
    assert not started - listed, f"docs/architecture.md's threads table lacks {sorted(started - listed)}"
