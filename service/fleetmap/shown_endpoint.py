"""Zenoh endpoints as the service shows them: in its log, its ready line and `GET /healthz`.

An endpoint may carry link configuration after `#` (`tls/0.0.0.0:7447#listen_private_key_base64=...;
listen_certificate_base64=...`, `tls/router:7447#connect_private_key_file=...`), which Zenoh reads as
it reads the same keys of a configuration file: a TLS private key given inline, or where the key
files are. The service never shows its Zenoh configuration (docs/security.md, "What is logged"),
and `/healthz` answers anyone: the key went out whole in the start-up log line, the ready line and
`/healthz`'s `listen`, `connect` and `endpoints`. Shown, each key of that part keeps its name and
loses its value; the address, which is what robots connect to, stays as given.
"""

from __future__ import annotations

from collections.abc import Iterable

#: What stands for a configuration value left out.
HIDDEN = "..."


def shown_endpoint(endpoint: str) -> str:
    """`endpoint` with the value of each key of its configuration part (after `#`, `key=value`
    pairs separated by `;`) replaced by `HIDDEN`; an endpoint without one is returned as it is."""
    locator, hash_sign, config = endpoint.partition("#")
    if not hash_sign:
        return endpoint
    keys = [pair.partition("=")[0] for pair in config.split(";") if pair]
    return f"{locator}#" + ";".join(f"{key}={HIDDEN}" for key in keys)


def shown_endpoints(endpoints: Iterable[str]) -> list[str]:
    """`shown_endpoint` of each of `endpoints`, in order."""
    return [shown_endpoint(endpoint) for endpoint in endpoints]


__all__ = ["HIDDEN", "shown_endpoint", "shown_endpoints"]
