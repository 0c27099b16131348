"""The Docker files name real things. No Docker engine runs on these machines, so the images cannot be
built here; instead this checks that every command, option, port and path the Dockerfile and the
compose file rely on exists in the project, so they cannot silently rot."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import yaml
import zenoh

REPO = Path(__file__).resolve().parents[1]
DOCKERFILE = REPO / "docker" / "Dockerfile"
COMPOSE = REPO / "docker" / "compose.yaml"


def fleetmap_help(*command: str) -> str:
    out = subprocess.run(
        [sys.executable, "-m", "fleetmap.cli", *command, "--help"], capture_output=True, text=True, check=True
    )
    return out.stdout


def options_of(argv: list[str]) -> list[str]:
    return [a.split("=", 1)[0] for a in argv if a.startswith("--")]


def dockerfile_instructions() -> dict[str, list[str]]:
    found: dict[str, list[str]] = {}
    text = re.sub(r"\\\n\s*", " ", DOCKERFILE.read_text())  # continuation lines joined
    for line in text.splitlines():
        m = re.match(r"^([A-Z]+)\s+(.*)$", line)
        if m:
            found.setdefault(m.group(1), []).append(m.group(2))
    return found


def test_dockerfile_copies_paths_that_exist_and_runs_real_options() -> None:
    ins = dockerfile_instructions()
    for copy in ins["COPY"]:
        *sources, _dest = copy.split()
        for src in sources:
            assert (REPO / src).exists(), f"Dockerfile copies {src}, which does not exist"
    entry = json.loads(ins["ENTRYPOINT"][0])  # exec form: a shell as PID 1 would not pass SIGTERM on
    assert entry[:2] == ["fleetmap", "serve"]
    serve_help = fleetmap_help("serve")
    for option in options_of(entry):
        assert option in serve_help, f"ENTRYPOINT uses {option}, which fleetmap serve does not have"
    env = dockerfile_env(ins)
    for name in env:
        if name.startswith("FLEETMAP_"):
            option = "--" + name.removeprefix("FLEETMAP_").lower().replace("_", "-")
            assert option in serve_help, f"ENV {name} names {option}, which fleetmap serve does not have"
    ports = {int(p) for line in ins["EXPOSE"] for p in line.split()}
    assert {8000, 7447} <= ports
    assert env["FLEETMAP_HTTP"] == "0.0.0.0:8000"
    # Zenoh on all interfaces through the image's own configuration file, which an operator's
    # --zenoh-config replaces whole; FLEETMAP_ZENOH_LISTEN would replace that file's endpoints
    # (tests/test_zenoh_security.py runs the image's settings with a TLS file).
    assert "FLEETMAP_ZENOH_LISTEN" not in env and "FLEETMAP_ZENOH_CONNECT" not in env
    # No MALLOC_ARENA_MAX: the service limits its malloc arenas itself (fleetmap.malloc_arenas), and
    # one set here would override that for every deployment of the image.
    assert "MALLOC_ARENA_MAX" not in env
    zenoh_config = zenoh.Config.from_file(str(image_file(ins, env["FLEETMAP_ZENOH_CONFIG"])))
    assert json.loads(zenoh_config.get_json("listen/endpoints")) == ["tcp/0.0.0.0:7447"]
    assert json.loads(ins["VOLUME"][0]) == [env["FLEETMAP_DATA_DIR"]], "the data directory must be the volume"
    (health,) = ins["HEALTHCHECK"]
    assert "fleetmap.healthcheck" in health, (
        "polls /healthz (test_the_image_health_check_follows_the_api_port)"
    )
    assert "--start-period=" in health, "a journal replay at start is not unhealthy"


def dockerfile_env(ins: dict[str, list[str]]) -> dict[str, str]:
    """The Dockerfile's `ENV NAME=VALUE` lines."""
    return dict(line.split("=", 1) for line in ins.get("ENV", []))


def image_file(ins: dict[str, list[str]], path: str) -> Path:
    """The repository file a `COPY SOURCE DEST` line puts at `path` in the image (DEST a file)."""
    for copy in ins["COPY"]:
        *sources, dest = copy.split()
        if dest == path and len(sources) == 1:
            return REPO / sources[0]
    raise AssertionError(f"the Dockerfile copies nothing to {path}")


def test_dockerfile_runs_as_non_root_and_stops_cleanly() -> None:
    ins = dockerfile_instructions()
    users = ins.get("USER", [])
    assert users and users[-1] not in ("root", "0"), "the service must not run as root"
    assert ins.get("STOPSIGNAL") == ["SIGTERM"], "fleetmap serve snapshots on SIGTERM"
    # Any user id (Kubernetes' runAsUser) finds the compiled code the build warmed, in one place.
    cache = dockerfile_env(ins).get("NUMBA_CACHE_DIR")
    assert cache and any(cache in run and "g+rwX" in run for run in ins["RUN"]), (
        "a cache every user id can use"
    )
    assert any("warm_up()" in run for run in ins["RUN"]), "warm the kernels the service runs"
    grace = yaml.safe_load(COMPOSE.read_text())["services"]["fleetmap"].get("stop_grace_period", "10s")
    assert grace.endswith("s") and int(grace[:-1]) >= 30, "docker's default 10 s can cut the final snapshot"


def test_compose_services_use_real_commands_and_ports() -> None:
    compose = yaml.safe_load(COMPOSE.read_text())
    services = compose["services"]
    serve_help = fleetmap_help("serve")
    for option in options_of(services["fleetmap"]["command"]):
        assert option in serve_help
    # Published on this host's loopback only: the service runs --insecure (no API tokens) and its
    # Zenoh port takes any robot's scans. "8000:8000" published both on every interface of the
    # host (Docker's default), where docs/security.md says the demo runs on a private network.
    if "--insecure" in services["fleetmap"]["command"]:
        assert {"127.0.0.1:8000:8000", "127.0.0.1:7447:7447"} == set(services["fleetmap"]["ports"])
    else:
        assert {"8000:8000", "7447:7447"} <= set(services["fleetmap"]["ports"])
    robots = services["robots"]["entrypoint"]
    assert robots[:2] == ["fleetmap", "sim"]
    sim_help = fleetmap_help("sim")
    for option in options_of(robots):
        assert option in sim_help, f"compose runs fleetmap sim {option}, which does not exist"
    connect = robots[robots.index("--connect") + 1]
    assert connect == "tcp/fleetmap:7447", "robots must reach the service by its compose name and Zenoh port"
    for name, service in services.items():
        build = service.get("build")
        if build:
            assert (COMPOSE.parent / build["context"] / build["dockerfile"]).resolve() == DOCKERFILE
            # The image's HEALTHCHECK polls /healthz on 127.0.0.1:8000: only `fleetmap serve` answers.
            if service.get("entrypoint", ["fleetmap", "serve"])[:2] != ["fleetmap", "serve"]:
                assert service.get("healthcheck", {}).get("disable") is True, (
                    f"compose service {name} runs no service, so the image's health check calls it unhealthy"
                )


def test_readme_documents_the_docker_commands() -> None:
    readme = (REPO / "README.md").read_text()
    assert "docker compose -f docker/compose.yaml up" in readme
    first = shlex.split("docker build -f docker/Dockerfile -t fleetmap .")
    assert " ".join(first) in readme


def test_the_image_health_check_follows_the_api_port(tmp_path: Path) -> None:
    """The image's HEALTHCHECK command, run as Docker runs it, but on the test's service rather than
    PID 1: it passes against a real service on the port its --http names (given after the image
    name, which the README says is added to the command), else the one FLEETMAP_HTTP names, and
    fails where nothing answers. It polled 127.0.0.1:8000 whatever FLEETMAP_HTTP said, so an
    operator who moved the API had a container unhealthy for good; then FLEETMAP_HTTP's port,
    whatever --http said."""
    from service_process import ServiceProcess, free_port

    (health,) = dockerfile_instructions()["HEALTHCHECK"]
    command = json.loads(health.split(" CMD ", 1)[1])  # exec form: no shell in between
    assert command == ["python", "-m", "fleetmap.healthcheck"]

    # A proxy for the container's outbound traffic, which cannot reach its 127.0.0.1 (nothing
    # listens there): the check went through it and failed.
    proxy = f"http://127.0.0.1:{free_port()}"

    def check(pid: int, http: str | None) -> subprocess.CompletedProcess[str]:
        env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO / "service"), "HTTP_PROXY": proxy}
        env |= {"http_proxy": proxy}
        env |= {"FLEETMAP_HTTP": http} if http is not None else {}
        run = [sys.executable, *command[1:], str(pid)]
        return subprocess.run(run, env=env, capture_output=True, text=True, timeout=30)

    nobody = free_port()
    with ServiceProcess(tmp_path, ["--in-memory"]) as svc:  # started with --http 127.0.0.1:PORT
        assert svc.proc is not None
        for http in (None, "0.0.0.0:8000", f"0.0.0.0:{nobody}"):  # the command line wins
            done = check(svc.proc.pid, http)
            assert done.returncode == 0, (http, done.stderr)
        # As the image runs it: the port of the variable, for a command line without --http.
        answering = check(os.getpid(), f"0.0.0.0:{svc.port}")
        assert answering.returncode == 0, answering.stderr
    refused = check(os.getpid(), f"0.0.0.0:{nobody}")
    assert refused.returncode == 1 and f"http://127.0.0.1:{nobody}/healthz" in refused.stderr, refused.stderr

    # A service on one address, not on all: IPv6 loopback alone (`[::]` binds IPv6 alone too). The
    # check polled 127.0.0.1, which nothing answers: unhealthy for good.
    ipv6 = ServiceProcess(tmp_path, ["--in-memory", "--http", f"[::1]:{nobody}"])
    ipv6.base_url = f"http://[::1]:{nobody}"  # where the start waits for /healthz
    with ipv6:
        assert ipv6.proc is not None
        for http in (None, f"127.0.0.1:{ipv6.port}"):  # the command line's last --http wins
            done = check(ipv6.proc.pid, http)
            assert done.returncode == 0, (http, done.stderr)
        answering = check(os.getpid(), f"[::1]:{nobody}")
        assert answering.returncode == 0, answering.stderr
    gone = check(os.getpid(), f"[::]:{nobody}")  # every IPv6 address: polled at ::1
    assert gone.returncode == 1 and f"http://[::1]:{nobody}/healthz" in gone.stderr, gone.stderr
