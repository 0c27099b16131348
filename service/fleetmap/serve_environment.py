"""`fleetmap serve`'s options as environment variables: `FLEETMAP_` and the option's name in
capitals with `-` as `_` (`--data-dir` is `FLEETMAP_DATA_DIR`, `--insecure` is `FLEETMAP_INSECURE=1`,
lists separated by spaces). The variables set are parsed as their options on a command line before
the real one, which therefore wins (`environment_first`); the parser itself is `serve_options`."""

from __future__ import annotations

import argparse
import difflib
import logging
import os
import sys
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

from fleetmap.auth import TOKENS_ENV
from fleetmap.log_format import LOG_FORMATS, plain_line

#: Prefix of the environment variables that give `serve` options (FLEETMAP_DATA_DIR, ...).
ENV_PREFIX = "FLEETMAP_"
#: FLEETMAP_ variables fleetmap reads that name no option: the tokens (`fleetmap.auth`) and the web
#: viewer's folder (`fleetmap.api.app.WEB_DIR_ENV`, spelled out: importing it loads FastAPI for
#: every command; tests/test_operations.py checks the two agree).
OTHER_VARIABLES = frozenset({TOKENS_ENV, "FLEETMAP_WEB_DIR"})
#: FLEETMAP_ variables of fleetmap's clients, which `serve` does not read, and what each is: a
#: warning says so rather than name the closest variable of `serve` (the client's token,
#: `fleetmap_client.rest.TOKEN_ENV`, spelled out to load no client here: was "did you mean
#: $FLEETMAP_TOKENS?", a variable of another format; tests/test_operations.py checks the names agree).
CLIENT_VARIABLES = {
    "FLEETMAP_TOKEN": (
        "the Python client's API token (fleetmap_client.rest), not a variable of `fleetmap serve`, "
        "whose tokens are --auth-tokens FILE or $FLEETMAP_TOKENS"
    ),
}
#: What a FLEETMAP_* variable of an on/off option (--insecure, ...) may say.
_ENV_TRUE = {"1", "true", "yes", "on"}
_ENV_FALSE = {"0", "false", "no", "off", ""}


def env_name(action: argparse.Action) -> str:
    """The environment variable of an option: `--data-dir` -> `FLEETMAP_DATA_DIR`."""
    return ENV_PREFIX + action.option_strings[-1].lstrip("-").replace("-", "_").upper()


def environment_first(parser: argparse.ArgumentParser) -> Callable[..., Any]:
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
                if isinstance(action, RepeatedOption):
                    values = getattr(namespace, action.dest)
                    setattr(namespace, action.dest, _FromEnvironment(values))
        try:
            namespace, extras = parse(args, namespace)
        except argparse.ArgumentError as exc:
            one_line_error(parser, str(exc), _log_format_asked(args, namespace))
        if problem:
            line = plain_line(f"{parser.prog}: error: {problem}", namespace.log_format, logging.ERROR)
            parser.exit(2, line + "\n")
        namespace.environment_warnings = unknown_variables(parser)
        return namespace, extras

    return parse_known_args


def one_line_error(parser: argparse.ArgumentParser, message: str, log_format: str = "text") -> NoReturn:
    """Exit 2 with `message` as one line naming the command and its help (as a JSON log object with
    `log_format` json), rather than argparse's usage first (`serve`'s took 15 lines above the
    error, which a service manager's log shows out of order)."""
    line = f"{parser.prog}: error: {message} (see {parser.prog} --help)"
    parser.exit(2, plain_line(line, log_format, logging.ERROR) + "\n")


def _log_format_asked(args: Sequence[str] | None, namespace: Any) -> str:
    """The log format a command line `args` that its parser refused asks for: its last valid
    `--log-format`, else the one `namespace` holds (its variable's), else text. A value its option
    refused (`--log-format json --http nowhere`, `FLEETMAP_LOG_FORMAT=json ... --workers 0`) was
    refused in a text line, among the JSON lines a log pipeline reads."""
    asked = getattr(namespace, "log_format", None) or "text"
    words = list(sys.argv[1:] if args is None else args)
    for word, following in zip(words, [*words[1:], None], strict=True):
        value = following if word == "--log-format" else word.partition("=")[2]
        if (word == "--log-format" or word.startswith("--log-format=")) and value in LOG_FORMATS:
            asked = value
    return str(asked)


def unknown_variables(parser: argparse.ArgumentParser) -> list[str]:
    """A warning for each FLEETMAP_ variable set that names no option of `parser` and nothing else
    fleetmap reads (`OTHER_VARIABLES`), with the closest option's variable when one is close: such a
    variable is ignored, and a typo in one (FLEETMAP_DATADIR) otherwise went unnoticed while the
    maps went to the default folder. Warnings, not errors: other programs may have FLEETMAP_
    variables of their own in the same environment."""
    known = {env_name(action) for action in parser._actions if action.option_strings}
    warnings = []
    for variable in sorted(v for v in os.environ if v.startswith(ENV_PREFIX)):
        if variable in known or variable in OTHER_VARIABLES:
            continue
        if variable in CLIENT_VARIABLES:
            warnings.append(f"${variable} is {CLIENT_VARIABLES[variable]}: ignored")
            continue
        close = difflib.get_close_matches(variable, sorted(known | OTHER_VARIABLES), n=1, cutoff=0.8)
        hint = f" (did you mean ${close[0]}?)" if close else ""
        warnings.append(f"${variable} is not a variable of `{parser.prog}`{hint}: ignored")
    return warnings


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
    """The values a repeatable option got from its FLEETMAP_ variable (see `RepeatedOption`)."""


class RepeatedOption(argparse.Action):
    """An option that may be given several times, each with one or more values, all kept in order
    (`--ros-publish-map a --ros-publish-map b c`: a, b, c). Its variable gives values separated by
    spaces; the command line's first occurrence replaces those (the command line wins, as for every
    option) rather than adding to them. Every list option of `fleetmap serve` is one: argparse's
    own kept the last occurrence alone, silently (`--zenoh-listen tcp/a --zenoh-listen tls/b`
    listened on tls/b only)."""

    def __call__(
        self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any, option: Any = None
    ) -> None:
        current = getattr(namespace, self.dest, None)
        kept = [] if current is None or isinstance(current, _FromEnvironment) else list(current)
        setattr(namespace, self.dest, kept + list(values))
