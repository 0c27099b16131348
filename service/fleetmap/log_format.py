"""How `fleetmap serve` writes its log: `--log-format text` (the default) or `json`.

`text` is one line per message, `TIME LEVEL LOGGER: MESSAGE`, as a person reads it. `json` is one
JSON object per line, for a log pipeline (journald, Docker's and Kubernetes' log drivers, Loki,
Elasticsearch), with these keys:

- `time`: when, ISO 8601 in UTC with milliseconds (`2026-01-31T12:00:00.123Z`);
- `level`: `DEBUG`, `INFO`, `WARNING`, `ERROR` or `CRITICAL`;
- `logger`: who wrote it (`fleetmap.ingest`, `fleetmap.registry`, `uvicorn.access`, ...);
- `message`: the same sentence the text format writes;
- `exception`: the traceback, when the line reports one;
- the line's structured fields, when it has them: `map_id`, `robot_id` (and `seq`) for lines about a
  map or a robot; `client`, `method`, `path`, `status` for an access-log line (`--access-log`).

A line about a map or robot passes them as `extra={"map_id": ..., "robot_id": ...}` (`fields` of
`RateLimitedLog.warning`); the text format leaves them out (they are in its message already).

uvicorn's own lines (its errors and warnings, and the access log) go through the same handler, in
either format (`UVICORN_LOG_CONFIG`), so stderr carries one format only: uvicorn's own configuration
wrote `WARNING:  message` lines without a time among fleetmap's, and its access log to stdout.
The ready line on stdout and the one-line error of a bad option (`plain_line`) are JSON objects
too in `json`.
"""

from __future__ import annotations

import asyncio
import json
import logging
import sys
import threading
from datetime import UTC, datetime
from types import TracebackType
from typing import Any

LOG_FORMATS = ("text", "json")
#: The text format (`--log-format text`).
TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
#: What every LogRecord has; anything else on a record is a structured field (`extra=`). uvicorn adds
#: `color_message` (its message with terminal colours) to some records: not a field.
_RECORD_ATTRIBUTES = frozenset(vars(logging.LogRecord("", 0, "", 0, "", (), None))) | {
    "message",
    "asctime",
    "color_message",
    "taskName",
}
#: The arguments of uvicorn's access-log records (`'%s - "%s %s HTTP/%s" %d'`), as fields.
_ACCESS_FIELDS = ("client", "method", "path", "http_version", "status")


def _iso_utc(created: float) -> str:
    return datetime.fromtimestamp(created, UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def fields_of(record: logging.LogRecord) -> dict[str, Any]:
    """The structured fields of `record`: its `extra=` values, and the request of an access-log line."""
    found = {k: v for k, v in vars(record).items() if k not in _RECORD_ATTRIBUTES}
    if record.name == "uvicorn.access" and isinstance(record.args, tuple) and len(record.args) == 5:
        found.update(zip(_ACCESS_FIELDS, record.args, strict=True))
    return found


class JsonFormatter(logging.Formatter):
    """One JSON object per record, on one line (see the module's docstring for its keys)."""

    def format(self, record: logging.LogRecord) -> str:
        line: dict[str, Any] = {
            "time": _iso_utc(record.created),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        line.update(fields_of(record))
        if record.exc_info:
            line["exception"] = self.formatException(record.exc_info)
        elif record.exc_text:
            line["exception"] = record.exc_text
        if record.stack_info:
            line["stack"] = self.formatStack(record.stack_info)
        # ASCII only (non-ASCII escaped): valid JSON whatever encoding the stream has; json escapes
        # newlines, so a traceback never splits the line.
        return json.dumps(line, default=str)


def formatter(log_format: str) -> logging.Formatter:
    """The formatter of `--log-format` `log_format` ("text" or "json")."""
    return JsonFormatter() if log_format == "json" else logging.Formatter(TEXT_FORMAT)


def configure_logging(level: str, log_format: str) -> None:
    """Send every log record of the process at `level` or above to stderr in `log_format`. With
    json, Python's warnings and uncaught exceptions (any thread) are log records too, so nothing
    else writes a traceback of its own to stderr."""
    handler = logging.StreamHandler()
    handler.setFormatter(formatter(log_format))
    logging.basicConfig(level=getattr(logging, level.upper()), handlers=[handler])
    if log_format != "json":
        return
    logging.captureWarnings(True)
    crash_log = logging.getLogger("fleetmap")

    def main_thread_hook(kind: type[BaseException], exc: BaseException, tb: TracebackType | None) -> None:
        crash_log.critical("uncaught exception", exc_info=(kind, exc, tb))

    def thread_hook(args: threading.ExceptHookArgs) -> None:
        if args.exc_type is SystemExit:
            return
        name = args.thread.name if args.thread else "?"
        exc_info = (args.exc_type, args.exc_value, args.exc_traceback)
        # exc_value may be None (threading's documentation), which logging formats as well; its
        # stubs take only a complete exception triple.
        crash_log.error("uncaught exception in thread %s", name, exc_info=exc_info)  # type: ignore[arg-type]

    sys.excepthook = main_thread_hook
    threading.excepthook = thread_hook


class ShutdownCutoffLog(logging.Filter):
    """uvicorn's lines about the requests it cancels when its graceful shutdown runs out, made fit
    for a routine restart: "Cancel N running task(s), timeout graceful shutdown exceeded", an ERROR
    even when N is 0 (a slow client still reading a finished answer), becomes a WARNING that says
    what happens; "Exception in ASGI application" with the cancellation's traceback, an ERROR per
    request, is dropped: `api.errors.ShutdownCutoff` logged that request as a WARNING line."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str) and record.msg.startswith("Cancel %s running task(s)"):
            record.levelno, record.levelname = logging.WARNING, "WARNING"
            record.msg = "shutdown: the HTTP connections still open are closed (%s request(s) cut off)"
            return True
        exc = record.exc_info[1] if record.exc_info else None
        return not isinstance(exc, asyncio.CancelledError)


#: `uvicorn.Config(log_config=...)`: uvicorn's loggers keep no handler of their own and hand their
#: records to the process's (`configure_logging`), so its errors and access lines have the format
#: of every other line, on the same stream. (No `root` key: dictConfig leaves the root's handler.)
UVICORN_LOG_CONFIG: dict[str, Any] = {
    "version": 1,
    "disable_existing_loggers": False,
    "filters": {"shutdown_cutoff": {"()": ShutdownCutoffLog}},
    "loggers": {
        "uvicorn": {"handlers": [], "propagate": True},
        "uvicorn.error": {"handlers": [], "propagate": True, "filters": ["shutdown_cutoff"]},
        "uvicorn.access": {"handlers": [], "propagate": True},
    },
}


def plain_line(message: str, log_format: str, level: int = logging.INFO, **fields: Any) -> str:
    """A line `fleetmap serve` prints itself, outside its log: the ready line on stdout, or the
    one-line error of a bad option (before the log is set up). `message` itself in text; in json, a
    log object (logger `fleetmap.server`) with `fields`, so a stream that carries stdout and stderr
    together (Docker, Kubernetes, journald) holds JSON only."""
    if log_format != "json":
        return message
    record = logging.LogRecord("fleetmap.server", level, __file__, 0, message, (), None)
    record.__dict__.update(fields)
    return JsonFormatter().format(record)
