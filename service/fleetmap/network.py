"""Which hosts only this machine reaches: the check behind binding the REST API without tokens
(`fleetmap.server`) and the warning about Zenoh endpoints open to the network
(`fleetmap.zenoh_ingest.unauthenticated_endpoints`)."""

from __future__ import annotations

import ipaddress


def is_loopback_host(host: str) -> bool:
    """Whether only this machine reaches `host`: a loopback address, or `localhost` (what the REST
    API may bind without tokens, `fleetmap.server`, and a Zenoh endpoint is not warned of)."""
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


__all__ = ["is_loopback_host"]
