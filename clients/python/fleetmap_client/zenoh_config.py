"""The Zenoh configuration of a robot's session: `client_config`, and the connection settings it
fills in (client mode, the service's endpoint, one attempt's timeout, the reconnection periods).
`ScanPublisher` opens its session with it (`publisher.py`); a program that opens its own Zenoh
session to the service may use it too (docs/clients.md)."""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import zenoh

from fleetmap.wire import (
    CONNECT_RETRY,
    DEFAULT_ENDPOINT,
    check_endpoint_form,
    shown_config_path,
    zenoh_error_text,
)

#: Where `fleetmap serve` listens by default.
DEFAULT_CONNECT = (DEFAULT_ENDPOINT,)

#: How long one connection attempt of the background opener may take. Zenoh retries within an
#: attempt; between attempts the opener checks whether the publisher was closed.
CONNECT_ATTEMPT_MS = 1000
#: The client session's connection retry (`connect/retry`, unless the configuration sets it:
#: `fleetmap.wire.CONNECT_RETRY`, the service's too): the first wait after a failed attempt, the
#: longest, and the factor between. Zenoh's own (1000 ms, 4000 ms, 2)
#: tries again 1, 3, 7, 11, 15 ... s after losing the service, so a robot met a service that came
#: back up to 4 s after it listened, and none at all that lived less than that: while short-lived
#: services came and went, robots of tests/test_crash_exactly_once.py stayed unconnected for 37 s,
#: past what their caches held. Bounded at 0.5 s, a robot is connected again within about half a
#: second of the service listening; an attempt costs one TCP connection.
RECONNECT_PERIOD_INIT_MS = int(CONNECT_RETRY["period_init_ms"])
RECONNECT_PERIOD_MAX_MS = int(CONNECT_RETRY["period_max_ms"])
RECONNECT_PERIOD_FACTOR = float(CONNECT_RETRY["period_increase_factor"])


def client_config(
    connect: Sequence[str] | str | None = None, zenoh_config: zenoh.Config | str | Path | None = None
) -> zenoh.Config:
    """The Zenoh configuration of a robot's session.

    Starts from `zenoh_config` (a `zenoh.Config`, or the path of a JSON5 configuration file) or an
    empty configuration, then fills in what it leaves unset: mode `client`, connect endpoints
    (`connect`, else `DEFAULT_CONNECT`; an explicit `connect` always wins), `connect/timeout_ms` of
    one attempt (`CONNECT_ATTEMPT_MS`), `connect/retry` (`RECONNECT_PERIOD_INIT_MS` growing by
    `RECONNECT_PERIOD_FACTOR` to at most `RECONNECT_PERIOD_MAX_MS` between attempts, also when Zenoh
    reconnects a lost session; a configuration that sets any key of `connect/retry` keeps Zenoh's
    defaults for the others) and multicast scouting off. Endpoints set per mode in the file count
    for the session's mode only: none for it, and the default is filled in. Raises ValueError for
    a bad file or endpoint list, TypeError for a `zenoh_config` of another type (a dict).
    """
    if zenoh_config is None:
        cfg = zenoh.Config()
    elif isinstance(zenoh_config, zenoh.Config):
        # zenoh.open does not consume a Config, but copy anyway so our insertions stay ours.
        cfg = zenoh.Config.from_json5(str(zenoh_config))
    elif not isinstance(zenoh_config, str | os.PathLike):
        # Anything else was taken for a file name: a dict of settings failed with "cannot read Zenoh
        # configuration {'mode': 'client'}: No such file or directory".
        raise TypeError(
            "zenoh_config must be a zenoh.Config or the path of a JSON5 file, "
            f"not {type(zenoh_config).__name__} (for settings in a dict: "
            "zenoh.Config.from_json5(json.dumps(settings)))"
        )
    else:
        try:
            cfg = zenoh.Config.from_file(os.fspath(zenoh_config))
        except (zenoh.ZError, OSError) as exc:
            message = zenoh_error_text(exc)
            shown = shown_config_path(os.fspath(zenoh_config))
            raise ValueError(f"cannot read Zenoh configuration {shown}: {message}") from None
    if config_value(cfg, "mode") is None:
        cfg.insert_json5("mode", '"client"')
    if connect is not None or not connect_endpoints(cfg):
        # One endpoint given as a string is that endpoint, not a list of its characters.
        if isinstance(connect, str):
            endpoints = [connect]
        else:
            endpoints = list(DEFAULT_CONNECT if connect is None else connect)
        if not endpoints or not all(isinstance(e, str) and e for e in endpoints):
            raise ValueError(f"connect must be a non-empty list of Zenoh endpoints, got {connect!r}")
        for endpoint in endpoints:
            check_endpoint_form(endpoint)
        try:
            cfg.insert_json5("connect/endpoints", _json_list(endpoints))
        except zenoh.ZError as exc:
            raise ValueError(f"invalid Zenoh endpoint in {endpoints}: {zenoh_error_text(exc)}") from None
    if config_value(cfg, "connect/timeout_ms") is None:
        cfg.insert_json5("connect/timeout_ms", str(CONNECT_ATTEMPT_MS))
    if config_value(cfg, "connect/retry") is None:
        # Zenoh takes the block whole (its keys cannot be inserted one by one into an unset one).
        cfg.insert_json5("connect/retry", json.dumps(CONNECT_RETRY))
    if config_value(cfg, "scouting/multicast/enabled") is None:
        cfg.insert_json5("scouting/multicast/enabled", "false")
    return cfg


def config_value(cfg: zenoh.Config, key: str) -> Any:
    """A configuration value as Python (None when unset)."""
    return json.loads(cfg.get_json(key))


def connect_endpoints(cfg: zenoh.Config) -> list[str]:
    """The endpoints a session of `cfg` connects to: `connect/endpoints`, a list, or Zenoh's
    per-mode form (`{client: [...], peer: [...], router: [...]}`) read for the configuration's
    mode (`client` when unset). Empty when it sets none for that mode."""
    endpoints = config_value(cfg, "connect/endpoints")
    if isinstance(endpoints, dict):
        # Its keys were taken for endpoints ("waiting for the fleetmap service at peer, client").
        endpoints = endpoints.get(config_value(cfg, "mode") or "client")
    return list(endpoints or [])


def _json_list(items: Sequence[str]) -> str:
    return json.dumps(list(items))


__all__ = [
    "CONNECT_ATTEMPT_MS", "DEFAULT_CONNECT", "RECONNECT_PERIOD_FACTOR", "RECONNECT_PERIOD_INIT_MS",
    "RECONNECT_PERIOD_MAX_MS", "client_config", "config_value", "connect_endpoints",
]  # fmt: skip
