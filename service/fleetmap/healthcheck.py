"""`python -m fleetmap.healthcheck [PID]`: the Docker image's HEALTHCHECK. Exits 0 when the
service's `/healthz` answers 200 at the address of its API, else 1 (Docker's "unhealthy").

The address is the one the service was given, read as `fleetmap serve` reads it: the last `--http`
of the command line of process PID (default 1: the container's `fleetmap serve`), else
$FLEETMAP_HTTP, else :8000. The check polled the port of $FLEETMAP_HTTP alone, so `docker run IMAGE
--http 0.0.0.0:9000` (README.md: arguments after the image name are added to the command) left the
container unhealthy for good; then 127.0.0.1 whatever the host, so a service that listens on one
address (`--http 192.168.1.10:8000` with host networking, `--http [::]:8000`, which the service
binds to IPv6 alone) was unhealthy for good too. Only the standard library is imported: Docker runs
this every 10 s.
"""

from __future__ import annotations

import os
import sys
import urllib.request
from collections.abc import Mapping, Sequence

#: The port of the API when neither `--http` nor $FLEETMAP_HTTP names one (the image sets the latter).
DEFAULT_PORT = "8000"

#: Where to reach a service that listens on every address of a family: its loopback address.
_LOOPBACK_OF_WILDCARD = {"": "127.0.0.1", "0.0.0.0": "127.0.0.1", "::": "::1"}


def api_address(command: Sequence[str], environ: Mapping[str, str]) -> tuple[str, str]:
    """(host, port) at which this machine reaches the API that `command` (a `fleetmap serve` command
    line, `--http HOST:PORT`, `--http [IPV6]:PORT` or `--http=...`) serves in `environ`: the command
    line wins over $FLEETMAP_HTTP, and its last `--http` over earlier ones, as in `fleetmap serve`.
    The host is the one given, or the loopback address of its family where it names every address
    (`0.0.0.0`, `::`, none). An IPv6 host is returned without brackets."""
    http = environ.get("FLEETMAP_HTTP") or f":{DEFAULT_PORT}"
    for index, word in enumerate(command):
        if word == "--http" and index + 1 < len(command):
            http = command[index + 1]
        elif word.startswith("--http="):
            http = word.split("=", 1)[1]
    host, _, port = http.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    return _LOOPBACK_OF_WILDCARD.get(host, host), port


def service_command(pid: str) -> list[str]:
    """The command line of process `pid` (empty when it cannot be read: no such process)."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as cmdline:
            return cmdline.read().decode(errors="replace").split("\0")
    except OSError:
        return []


def main(argv: Sequence[str]) -> int:
    """Check the service of process `argv[0]` (default 1); 0 healthy, 1 not, with the reason on stderr."""
    host, port = api_address(service_command(argv[0] if argv else "1"), os.environ)
    url = f"http://{f'[{host}]' if ':' in host else host}:{port}/healthz"
    # No proxy: urlopen's default opener sent the check to $HTTP_PROXY (set in a container for its
    # outbound traffic), which cannot reach the container's own 127.0.0.1: unhealthy for good.
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
    try:
        with opener.open(url, timeout=2) as answer:
            return 0 if answer.status == 200 else 1
    except (OSError, ValueError) as exc:  # refused, timed out, an HTTP error status, a bad port
        print(f"fleetmap healthcheck: {url}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
