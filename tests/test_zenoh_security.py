"""Zenoh transport security with the real service: TLS, mutual TLS and user / password.

Each test starts `python -m fleetmap.server` with a Zenoh configuration file taken from the examples
in docs/security.md (only the certificate paths, the port and the users file substituted), so the
documented files are the ones proven to work. Certificates are generated here with the `openssl`
command line (a CA, the service's certificate for 127.0.0.1, a robot's client certificate, and a
second, untrusted CA with its own client certificate).

A robot publishing through `fleetmap_client.publisher.ScanPublisher` with the matching robot example
gets every scan integrated (checked over REST). Intruders (wrong CA, no CA, plain TCP to the TLS port,
no client certificate, a certificate from another CA, no / wrong credentials) cannot open a session,
neither with a raw `zenoh.open` nor with `ScanPublisher`; nothing of theirs reaches the service
(`zenoh.messages_received` counts exactly the good robot's scans), the service keeps serving the good
robot afterwards and shuts down cleanly.
"""

from __future__ import annotations

import base64
import json
import re
import shutil
import socket
import ssl
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
import zenoh
from fleetmap_client.publisher import ScanPublisher
from robot_process import scans_for
from service_process import REPO_DIR, ServiceProcess, free_port, wait_for
from test_docker import dockerfile_env, dockerfile_instructions, image_file

from fleetmap.scan import Scan

OPENSSL = shutil.which("openssl")
pytestmark = pytest.mark.skipif(
    OPENSSL is None, reason="the openssl command line (not found) generates the test certificates"
)

SECURITY_DOC = REPO_DIR / "docs" / "security.md"
#: The example files docs/security.md must contain (a ```json5 block whose first line is `// NAME`).
DOC_EXAMPLES = (
    "service-tls.json5", "robot-tls.json5", "service-mtls.json5", "robot-mtls.json5",
    "service-usrpwd.json5", "robot-usrpwd.json5",
)  # fmt: skip
#: What the examples name, replaced by the test's own paths and endpoints.
DOC_TLS_DIR = "/etc/fleetmap/tls/"
DOC_USERS_FILE = "/etc/fleetmap/zenoh-users.txt"
DOC_SERVICE_LISTEN = "tls/0.0.0.0:7447"
DOC_ROBOT_CONNECT = "tls/fleetmap.example.com:7447"
DOC_ROBOT_USER, DOC_ROBOT_PASSWORD = "robot-7", "correct-horse-battery-staple"

MAP_ID = "secure"
ROBOT_ID = "robot-7"
#: How long an intruder is given to (fail to) connect. A trusted robot connects in milliseconds.
INTRUDER_SECONDS = 3.0


# -- certificates ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Pki:
    """Generated key material, named as in docs/security.md (`ca.pem`, `service.key`, ...)."""

    dir: Path

    def path(self, name: str) -> str:
        return str(self.dir / name)


def _openssl(*args: str, cwd: Path) -> None:
    result = subprocess.run([str(OPENSSL), *args], cwd=cwd, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, f"openssl {' '.join(args)} failed:\n{result.stderr}"


def _make_ca(d: Path, name: str) -> None:
    _openssl(
        "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-days", "2",
        "-keyout", f"{name}.key", "-out", f"{name}.pem", "-subj", f"/CN=fleetmap test {name}",
        "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign",
        cwd=d,
    )  # fmt: skip


def _make_leaf(d: Path, name: str, ca: str, usage: str, san: str, serial: int) -> None:
    _openssl(
        "req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
        "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj", f"/CN={name}", cwd=d,
    )  # fmt: skip
    (d / f"{name}.ext").write_text(
        "basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n"
        f"extendedKeyUsage={usage}\nsubjectAltName={san}\n"
    )
    _openssl(
        "x509", "-req", "-in", f"{name}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}.key",
        "-set_serial", str(serial), "-days", "2", "-out", f"{name}.pem", "-extfile", f"{name}.ext", cwd=d,
    )  # fmt: skip


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    """ca (trusted), other-ca (not trusted), service (server cert for 127.0.0.1 / localhost, by ca),
    robot-7 (client cert by ca), rogue (client cert by other-ca)."""
    d = tmp_path_factory.mktemp("pki")
    _make_ca(d, "ca")
    _make_ca(d, "other-ca")
    _make_leaf(d, "service", "ca", "serverAuth", "IP:127.0.0.1,DNS:localhost", 1001)
    _make_leaf(d, "robot-7", "ca", "clientAuth", "DNS:robot-7", 1002)
    _make_leaf(d, "rogue", "other-ca", "clientAuth", "DNS:rogue", 1003)
    return Pki(d)


# -- the documented configuration files ----------------------------------------------------------------


def doc_examples() -> dict[str, str]:
    """The ```json5 blocks of docs/security.md by the file name on their first line (`// NAME`)."""
    blocks = re.findall(r"```json5\n(.*?)```", SECURITY_DOC.read_text(), flags=re.S)
    examples = {}
    for block in blocks:
        first = block.splitlines()[0].strip()
        assert first.startswith("// "), f"a json5 example in {SECURITY_DOC.name} must start with '// NAME'"
        examples[first[3:]] = block
    return examples


def doc_config(name: str, pki: Pki, port: int, out_dir: Path, users_file: Path | None = None) -> Path:
    """The example `name` of docs/security.md with the test's certificate directory, endpoint and
    users file, written to `out_dir/name`. Fails if the example no longer names what it replaces."""
    text = doc_examples()[name]
    replacements = {
        DOC_TLS_DIR: str(pki.dir) + "/",
        DOC_SERVICE_LISTEN: f"tls/127.0.0.1:{port}",
        DOC_ROBOT_CONNECT: f"tls/127.0.0.1:{port}",
    }
    if users_file is not None:
        replacements[DOC_USERS_FILE] = str(users_file)
    for old, new in replacements.items():
        if old in text:
            text = text.replace(old, new)
    assert DOC_TLS_DIR not in text and "0.0.0.0" not in text and "example.com" not in text, text
    path = out_dir / name
    path.write_text(text)
    return path


def modified(path: Path, **changes: Any) -> zenoh.Config:
    """The configuration file at `path` with some keys replaced (`changes`: key with '/' as '__')."""
    cfg = zenoh.Config.from_file(str(path))
    for key, value in changes.items():
        cfg.insert_json5(key.replace("__", "/"), json.dumps(value))
    return cfg


# -- the service and robots ----------------------------------------------------------------------------


def start_service(log_dir: Path, config: Path | None, port: int) -> ServiceProcess:
    """The real service with `--zenoh-config config` (None: no such option) and NO --zenoh-listen, so
    that it listens on what the file says (as in `fleetmap serve --zenoh-config service-tls.json5`)."""
    svc = ServiceProcess(log_dir, ["--in-memory", *(["--zenoh-config", str(config)] if config else [])])
    at = svc.args.index("--zenoh-listen")
    del svc.args[at : at + 2]  # ServiceProcess always adds a plain tcp endpoint; this test must not
    svc.zenoh_endpoint = f"{'tls' if config else 'tcp'}/127.0.0.1:{port}"
    return svc.start()


@pytest.fixture
def services() -> Iterator[list[ServiceProcess]]:
    """Services a test started; each must shut down cleanly and log no traceback."""
    started: list[ServiceProcess] = []
    yield started
    for svc in started:
        code = svc.stop()
        logs = svc.logs()
        assert code == 0, f"service exited with {code}:\n{logs}"
        assert "Traceback" not in logs, logs


def scans(count: int, seed: int = 1) -> list[Scan]:
    return scans_for(sim=seed, count=count, beams=181)


def robot_stats(http: httpx.Client) -> dict[str, Any]:
    response = http.get(f"/maps/{MAP_ID}")
    if response.status_code == 404:
        return {}
    response.raise_for_status()
    return response.json()["stats"]["robots"]


def publish_and_check(http: httpx.Client, pub: ScanPublisher, batch: list[Scan], total: int) -> None:
    """Publish `batch` and wait until the service integrated `total` scans of the good robot."""
    assert all(pub.publish(scan) for scan in batch), "the trusted robot lost its connection"

    def integrated() -> int:
        return robot_stats(http).get(ROBOT_ID, {}).get("scans_integrated", 0) >= total

    wait_for(integrated, timeout=30, what=f"{total} scans of the trusted robot integrated")
    robot = robot_stats(http)[ROBOT_ID]
    assert robot["scans_integrated"] == total
    assert (robot["lost"], robot["scans_rejected"], robot["duplicates"]) == (0, 0, 0), robot


def assert_refused(intruders: dict[str, zenoh.Config]) -> None:
    """Every configuration in `intruders` fails to open a session to the service, both with a raw
    `zenoh.open` (bounded connect timeout) and as a `ScanPublisher` that keeps trying for
    INTRUDER_SECONDS and then publishes (nothing sent: never connected, its scans wait in its
    pre-open queue). Run concurrently."""

    def raw_open(cfg: zenoh.Config) -> str | None:
        cfg = zenoh.Config.from_json5(str(cfg))
        cfg.insert_json5("connect/timeout_ms", str(int(INTRUDER_SECONDS * 1000)))
        cfg.insert_json5("scouting/multicast/enabled", "false")
        try:
            session = zenoh.open(cfg)
        except zenoh.ZError as exc:
            return str(exc)
        session.close()
        return None

    with ThreadPoolExecutor(len(intruders)) as pool:
        raw = {name: pool.submit(raw_open, cfg) for name, cfg in intruders.items()}
        pubs = {
            name: ScanPublisher(MAP_ID, f"intruder-{i}", zenoh_config=cfg)
            for i, (name, cfg) in enumerate(intruders.items())
        }
        try:
            deadline = time.monotonic() + INTRUDER_SECONDS
            for name, pub in pubs.items():
                left = max(0.0, deadline - time.monotonic())
                connected = pub.wait_connected(left, require_subscriber=False)
                assert not connected, f"intruder {name!r} connected"
                for scan in scans(3, seed=9):
                    pub.publish(scan)
                assert (pub.published, pub.pending, pub.backlogged, pub.dropped) == (0, 3, 3, 0), name
                assert pub.last_connect_error, name
        finally:
            for pub in pubs.values():
                pub.close()
        for name, future in raw.items():
            error = future.result()
            assert error is not None, f"intruder {name!r} opened a Zenoh session"
            assert "Unable to connect" in error, (name, error)


def assert_nothing_else_arrived(http: httpx.Client, total: int) -> None:
    """Only the trusted robot ever reached the service: one map, one robot, and exactly its scans
    among all the scan samples the service's Zenoh session received."""
    health = http.get("/healthz").json()
    assert health["zenoh"]["messages_received"] == total, health
    assert health["zenoh"]["decode_errors"] == 0 and health["zenoh"]["invalid_keys"] == 0, health
    assert [m["id"] for m in http.get("/maps").json()["maps"]] == [MAP_ID]
    assert set(robot_stats(http)) == {ROBOT_ID}


def run_scenario(
    services: list[ServiceProcess],
    tmp_path: Path,
    service_config: Path,
    robot_config: Path,
    port: int,
    intruders: Callable[[], dict[str, zenoh.Config]],
) -> ServiceProcess:
    """The trusted robot publishes 10 scans, intruders fail, the trusted robot publishes 10 more:
    all 20 integrated, nothing else received."""
    svc = start_service(tmp_path, service_config, port)
    services.append(svc)
    with httpx.Client(base_url=svc.base_url, timeout=20.0) as http:
        health = http.get("/healthz").json()
        # Only the TLS endpoint of the file: no plain tcp listener next to it.
        assert health["zenoh"]["listen"] == [f"tls/127.0.0.1:{port}"], health
        assert health["zenoh"]["mode"] == "router"
        batch = scans(20)
        with ScanPublisher(MAP_ID, ROBOT_ID, zenoh_config=robot_config) as pub:
            assert pub.wait_connected(timeout=20), f"trusted robot: {pub.last_connect_error}\n{svc.logs()}"
            publish_and_check(http, pub, batch[:10], 10)
            assert_refused(intruders())
            assert svc.alive()
            publish_and_check(http, pub, batch[10:], 20)
        assert_nothing_else_arrived(http, 20)
    return svc


# -- tests -------------------------------------------------------------------------------------------


def test_security_doc_examples_are_valid_zenoh_configurations() -> None:
    """docs/security.md has every example the tests use, and each one is a configuration Zenoh
    accepts (unknown keys are errors in zenoh.Config)."""
    examples = doc_examples()
    assert set(DOC_EXAMPLES) <= set(examples), sorted(examples)
    for name, text in examples.items():
        cfg = zenoh.Config.from_json5(text)
        mode = json.loads(cfg.get_json("mode"))
        assert mode == ("router" if name.startswith("service") else "client"), name
        tls = json.loads(cfg.get_json("transport/link/tls"))
        if name.startswith("robot"):
            assert tls["root_ca_certificate"], name  # robots always check the service's certificate


def test_tls_trusted_robot_integrated_untrusted_clients_refused(
    pki: Pki, tmp_path: Path, services: list[ServiceProcess]
) -> None:
    """TLS: a robot trusting the CA publishes and gets every scan integrated; the listener speaks
    real TLS with the service's certificate; a client trusting another CA, one with only the
    default (WebPKI) roots, and one speaking plain TCP to the TLS port cannot connect."""
    port = free_port()
    service_cfg = doc_config("service-tls.json5", pki, port, tmp_path)
    robot_cfg = doc_config("robot-tls.json5", pki, port, tmp_path)

    def intruders() -> dict[str, zenoh.Config]:
        # The listener is real TLS: the handshake presents the service's certificate, signed by the
        # CA, valid for 127.0.0.1; another CA does not validate it.
        with socket.create_connection(("127.0.0.1", port), timeout=5) as raw:
            ctx = ssl.create_default_context(cafile=pki.path("ca.pem"))
            with ctx.wrap_socket(raw, server_hostname="127.0.0.1") as tls:
                cert = tls.getpeercert()
        assert dict(item[0] for item in cert["subject"])["commonName"] == "service"
        with socket.create_connection(("127.0.0.1", port), timeout=5) as raw:
            ctx = ssl.create_default_context(cafile=pki.path("other-ca.pem"))
            with pytest.raises(ssl.SSLCertVerificationError):
                ctx.wrap_socket(raw, server_hostname="127.0.0.1")
        return {
            "wrong CA": modified(
                robot_cfg, transport__link__tls__root_ca_certificate=pki.path("other-ca.pem")
            ),
            "no CA (system roots)": zenoh.Config.from_json5(
                json.dumps({"mode": "client", "connect": {"endpoints": [f"tls/127.0.0.1:{port}"]}})
            ),
            "plain tcp": modified(robot_cfg, connect__endpoints=[f"tcp/127.0.0.1:{port}"]),
        }

    run_scenario(services, tmp_path, service_cfg, robot_cfg, port, intruders)


def test_mutual_tls_requires_a_client_certificate_from_the_ca(
    pki: Pki, tmp_path: Path, services: list[ServiceProcess]
) -> None:
    """Mutual TLS: the robot with its certificate from the CA is integrated; a client without a
    certificate (plain TLS config), one that enables mTLS but has no certificate, and one whose
    certificate comes from another CA cannot connect."""
    port = free_port()
    service_cfg = doc_config("service-mtls.json5", pki, port, tmp_path)
    robot_cfg = doc_config("robot-mtls.json5", pki, port, tmp_path)
    tls_only = doc_config("robot-tls.json5", pki, port, tmp_path)

    def intruders() -> dict[str, zenoh.Config]:
        return {
            "no client certificate": zenoh.Config.from_file(str(tls_only)),
            "mtls without a certificate": modified(tls_only, transport__link__tls__enable_mtls=True),
            "certificate from another CA": modified(
                robot_cfg,
                transport__link__tls__connect_private_key=pki.path("rogue.key"),
                transport__link__tls__connect_certificate=pki.path("rogue.pem"),
            ),
        }

    run_scenario(services, tmp_path, service_cfg, robot_cfg, port, intruders)


def test_user_password_refuses_wrong_or_missing_credentials(
    pki: Pki, tmp_path: Path, services: list[ServiceProcess]
) -> None:
    """Zenoh user / password over TLS: the robot with its documented credentials is integrated; no
    credentials, a wrong password and an unknown user cannot connect. The password never appears in
    the service's log."""
    port = free_port()
    users = tmp_path / "zenoh-users.txt"
    users.write_text(f"{DOC_ROBOT_USER}:{DOC_ROBOT_PASSWORD}\nrobot-8:another-long-random-password\n")
    service_cfg = doc_config("service-usrpwd.json5", pki, port, tmp_path, users_file=users)
    robot_cfg = doc_config("robot-usrpwd.json5", pki, port, tmp_path)
    tls_only = doc_config("robot-tls.json5", pki, port, tmp_path)

    def intruders() -> dict[str, zenoh.Config]:
        return {
            "no credentials": zenoh.Config.from_file(str(tls_only)),
            "wrong password": modified(robot_cfg, transport__auth__usrpwd__password="correct-horse-battery"),
            "unknown user": modified(robot_cfg, transport__auth__usrpwd__user="robot-9"),
            # A valid user's password for another user name.
            "another user's password": modified(robot_cfg, transport__auth__usrpwd__user="robot-8"),
        }

    svc = run_scenario(services, tmp_path, service_cfg, robot_cfg, port, intruders)
    assert DOC_ROBOT_PASSWORD not in svc.logs()


def image_environment(tmp_path: Path, zenoh_port: int) -> dict[str, str]:
    """The Docker image's FLEETMAP_* variables (docker/Dockerfile) that shape its Zenoh session,
    runnable here: a file the image copies in is read from the repository, and the image's
    `0.0.0.0:7447` becomes 127.0.0.1:`zenoh_port` (in the values and in such files)."""
    ins = dockerfile_instructions()
    image_listen, local_listen = "0.0.0.0:7447", f"127.0.0.1:{zenoh_port}"
    found = {}
    for name, value in dockerfile_env(ins).items():
        if not name.startswith("FLEETMAP_ZENOH_"):
            continue  # the HTTP address and data directory are ServiceProcess's
        if value.startswith("/"):
            local = tmp_path / Path(value).name
            local.write_text(image_file(ins, value).read_text().replace(image_listen, local_listen))
            value = str(local)
        found[name] = value.replace(image_listen, local_listen)
    return found


def test_the_docker_image_listens_where_an_operators_tls_file_says(
    pki: Pki, tmp_path: Path, services: list[ServiceProcess], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The image's settings listen on Zenoh's port on all interfaces, and `docker run fleetmap
    --zenoh-config service-tls.json5` listens where that file says, with TLS only. The image set
    FLEETMAP_ZENOH_LISTEN=tcp/0.0.0.0:7447, which replaced the file's endpoints: plain TCP, open to
    any publisher, and nothing on the TLS endpoint the robots were given."""
    image_port, port = free_port(), free_port()
    for name, value in image_environment(tmp_path, image_port).items():
        monkeypatch.setenv(name, value)
    default = start_service(tmp_path, None, image_port)
    services.append(default)
    assert httpx.get(f"{default.base_url}/healthz").json()["zenoh"]["listen"] == [
        f"tcp/127.0.0.1:{image_port}"
    ]
    assert default.stop() == 0

    service_cfg = doc_config("service-tls.json5", pki, port, tmp_path)
    robot_cfg = doc_config("robot-tls.json5", pki, port, tmp_path)

    def intruders() -> dict[str, zenoh.Config]:
        return {
            "plain tcp, the image's port": modified(
                robot_cfg, connect__endpoints=[f"tcp/127.0.0.1:{image_port}"]
            ),
            "plain tcp, the file's port": modified(robot_cfg, connect__endpoints=[f"tcp/127.0.0.1:{port}"]),
        }

    run_scenario(services, tmp_path, service_cfg, robot_cfg, port, intruders)


def test_a_tls_key_given_in_an_endpoint_is_never_shown(pki: Pki, tmp_path: Path) -> None:
    """A TLS listener's private key may be given inline in its endpoint, after `#`
    (`listen_private_key_base64=...`), as Zenoh reads it: the whole endpoint, key included, went
    out in the start-up log line, the ready line and `GET /healthz` (open to anyone: no token), though
    docs/security.md says the service never shows its Zenoh configuration. Each configuration key
    is shown without its value now; the robot still connects and its scan is integrated."""
    key_text = Path(pki.path("service.key")).read_bytes()
    key = base64.b64encode(key_text).decode()
    cert = base64.b64encode(Path(pki.path("service.pem")).read_bytes()).decode()
    port = free_port()
    endpoint = f"tls/127.0.0.1:{port}#listen_private_key_base64={key};listen_certificate_base64={cert}"
    svc = ServiceProcess(tmp_path, ["--in-memory"])
    svc.args[svc.args.index("--zenoh-listen") + 1] = endpoint  # in place of its plain TCP one
    with svc:
        robot = zenoh.Config.from_json5(
            json.dumps({
                "mode": "client", "connect": {"endpoints": [f"tls/127.0.0.1:{port}"]},
                "transport": {"link": {"tls": {"root_ca_certificate": pki.path("ca.pem")}}},
            })
        )  # fmt: skip
        with ScanPublisher("m", "r", zenoh_config=robot) as pub:
            assert pub.wait_connected(20)
            assert pub.publish(scans_for(sim=1, plan_seed=1, count=1)[0])
            assert pub.flush(20).confirmed
        health = httpx.get(f"{svc.base_url}/healthz", timeout=10)
        logs = svc.logs()
    shown = f"tls/127.0.0.1:{port}#listen_private_key_base64=...;listen_certificate_base64=..."
    zenoh_status = health.json()["zenoh"]
    assert zenoh_status["listen"] == zenoh_status["endpoints"] == [shown]
    for text, where in ((health.text, "/healthz"), (logs, "the log")):
        assert key not in text and key[:40] not in text, f"the private key is in {where}"
    assert f"listening on {shown}" in logs and f"zenoh: {shown}" in logs


def test_a_robots_tls_key_given_in_its_endpoint_is_never_shown(tmp_path: Path) -> None:
    """A robot may give its TLS key inline too (`#connect_private_key_base64=...`): `fleetmap replay`
    printed it whole in its "waiting for the fleetmap service at ..." line and in its error (Zenoh's
    own text quoting the endpoint), and so did the publisher's repr and the endpoint checks'
    messages. Each shows the key's name without its value now."""
    secret = "U0VDUkVULUtFWS1ET05PVC1TSE9X"
    endpoint = f"tls/127.0.0.1:{free_port()}#connect_private_key_base64={secret}"
    log = tmp_path / "one.log"
    log.write_text("FLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 0.0 robot 0.0\n")
    command = [sys.executable, "-m", "fleetmap", "replay", str(log), "--map", "m", "--robot", "r",
               "--connect", endpoint, "--wait-timeout", "3"]  # fmt: skip
    result = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert result.returncode != 0 and "no fleetmap service reachable" in result.stderr, result.stderr
    assert "connect_private_key_base64=..." in result.stderr, result.stderr
    assert secret not in result.stdout + result.stderr
    with ScanPublisher("m", "r", connect=endpoint) as pub:
        assert secret not in repr(pub) and "connect_private_key_base64=..." in repr(pub)
        assert pub.endpoints == [endpoint]  # what it connects to is as given
    for bad in (endpoint.replace("tls/", "tls://"), f"tls/127.0.0.1#connect_private_key_base64={secret}"):
        with pytest.raises(ValueError) as refused:
            ScanPublisher("m", "r", connect=bad)
        assert secret not in str(refused.value), refused.value
