"""The committed openapi/openapi.json is exactly what the app generates, and the spec is complete:
every operation summarised, typed, with its errors documented as `ErrorResponse`."""

from __future__ import annotations

import difflib
import importlib.util
import json
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import httpx
import pytest
from service_process import ServiceProcess

ROOT = Path(__file__).resolve().parents[1]
COMMITTED = ROOT / "openapi" / "openapi.json"


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """One service (default options) for the module's tests that ask the live service, in place of
    conftest's one per test: each makes maps of its own, if any, and none stops or reconfigures it."""
    with ServiceProcess(tmp_path_factory.mktemp("api-openapi")) as svc:
        yield svc


def _export_script() -> ModuleType:
    spec = importlib.util.spec_from_file_location("export_openapi", ROOT / "scripts" / "export_openapi.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_committed_spec_matches_the_app() -> None:
    generated = _export_script().spec_text()
    committed = COMMITTED.read_text(encoding="utf-8")
    if generated != committed:
        diff = "".join(
            list(
                difflib.unified_diff(
                    committed.splitlines(keepends=True),
                    generated.splitlines(keepends=True),
                    "openapi/openapi.json (committed)",
                    "generated from the app",
                )
            )[:60]
        )
        raise AssertionError(
            "openapi/openapi.json is out of date with the API: run\n"
            "    .venv/bin/python scripts/export_openapi.py\n"
            f"and commit the result. First differences:\n{diff}"
        )


def test_spec_is_complete_and_typed() -> None:
    def no_constants(name: str) -> None:
        raise AssertionError(f"the spec holds {name}, which is not JSON")

    spec = json.loads(COMMITTED.read_text(encoding="utf-8"), parse_constant=no_constants)
    assert spec["info"]["title"] == "fleetmap"
    schemas = spec["components"]["schemas"]
    names = "MapConfig MapInfo ScanMessage ScanResult CellsResponse RegionJson TilesEvent RobotsEvent"
    assert {*names.split(), "ErrorResponse"} <= set(schemas)
    operations = [(path, method, op) for path, item in spec["paths"].items() for method, op in item.items()]
    assert len(operations) >= 14
    for path, method, op in operations:
        where = f"{method.upper()} {path}"
        assert op.get("summary") and op.get("description"), where
        assert op.get("tags"), where
        assert "200" in op["responses"] or "201" in op["responses"] or "204" in op["responses"], where
        for status, response in op["responses"].items():
            if status.startswith("4"):
                ref = response["content"]["application/json"]["schema"]["$ref"]
                assert ref == "#/components/schemas/ErrorResponse", where
    # The tile endpoint documents the zoom convention, quoted from tile_render.
    tiles = spec["paths"]["/maps/{map_id}/tiles/{z}/{x}/{y}.png"]["get"]["description"]
    assert "At zoom 0 one tile pixel is one cell" in tiles and "If-None-Match" in tiles
    # Scans accept the wire schema (JSON) and the binary encoding.
    body = spec["paths"]["/maps/{map_id}/scans"]["post"]["requestBody"]["content"]
    assert body["application/json"]["schema"]["$ref"] == "#/components/schemas/ScanMessage"
    assert "application/x-fleetmap-scan" in body


def test_every_503_declares_its_retry_after() -> None:
    """Every 503 carries `Retry-After` (docs/api.md, "Errors"), and a generated client reads the
    headers it may use from the spec: the spec declared it on none."""
    spec = json.loads(COMMITTED.read_text(encoding="utf-8"))
    answers = [
        (f"{method.upper()} {path}", op["responses"]["503"])
        for path, item in spec["paths"].items()
        for method, op in item.items()
        if "503" in op["responses"]
    ]
    assert len(answers) >= 8
    for where, answer in answers:
        assert answer.get("headers", {}).get("Retry-After", {}).get("schema") == {"type": "integer"}, where


def test_every_operation_with_a_body_documents_its_413_and_415() -> None:
    """Every request body is held to a size (16 MiB, a snapshot's its own: 413) and refused when sent
    compressed (415), whatever the route (docs/api.md, "Errors"); `PUT /maps/{map_id}` answered a
    17 MiB configuration 413 where its spec listed no 413, so a client checking answers against the
    spec (Schemathesis' status check, a generated client's typed errors) took it for a mistake of
    the service. (The body limit's 413 on a route is tested live in tests/test_upload_spool.py.)"""
    spec = json.loads(COMMITTED.read_text(encoding="utf-8"))
    with_body = [
        (f"{method.upper()} {path}", op["responses"])
        for path, item in spec["paths"].items()
        for method, op in item.items()
        if "requestBody" in op
    ]
    assert len(with_body) >= 6
    undocumented = [
        f"{where}: {status}"
        for where, responses in with_body
        for status in ("413", "415")
        if status not in responses
    ]
    assert not undocumented, undocumented


def test_the_snapshot_uploads_415_says_what_the_route_refuses(tmp_path: Path) -> None:
    """A snapshot upload is read from its bytes whatever its Content-Type (the import's is checked):
    the spec's shared 415 said "a zip: application/zip" for both, so a client checking answers
    against the spec took the service's 201 for a body sent as text/plain for a mistake."""
    spec = json.loads(COMMITTED.read_text(encoding="utf-8"))
    snapshot = spec["paths"]["/maps/{map_id}/snapshot"]["put"]["responses"]["415"]["description"]
    imported = spec["paths"]["/maps/{map_id}/import"]["put"]["responses"]["415"]["description"]
    assert "Content-Encoding" in snapshot and "not checked" in snapshot
    assert "application/zip" in imported and "not checked" not in imported
    with ServiceProcess(tmp_path, ["--in-memory"]) as svc:
        assert httpx.put(f"{svc.base_url}/maps/a", json={"resolution": 0.1}).status_code == 201
        body = httpx.get(f"{svc.base_url}/maps/a/snapshot").content
        for headers in ({"content-type": "text/plain"}, {}):
            put = httpx.put(f"{svc.base_url}/maps/b/snapshot", content=body, headers=headers)
            assert put.status_code in (200, 201), put.text
        refused = httpx.put(
            f"{svc.base_url}/maps/b/snapshot", content=body, headers={"content-encoding": "gzip"}
        )
        assert refused.status_code == 415, refused.text
        text = {"content-type": "text/plain"}
        wrong = httpx.put(f"{svc.base_url}/maps/c/import", content=body, headers=text)
        assert wrong.status_code == 415, wrong.text


def test_the_scan_uploads_415_names_the_types_it_reads() -> None:
    """A scan sent as `text/plain` is a 415 (it was a 422 "unknown encoding", as for a bad scan):
    the spec's 415 of `POST .../scans` names the two media types the route reads, not the shared
    "JSON: application/json; a zip: application/zip"."""
    spec = json.loads(COMMITTED.read_text(encoding="utf-8"))
    scans = spec["paths"]["/maps/{map_id}/scans"]["post"]["responses"]["415"]["description"]
    assert "application/json" in scans and "application/x-fleetmap-scan" in scans
    assert "application/zip" not in scans


def test_docs_describe_every_operation() -> None:
    """docs/api.md has a section for every path of the spec (so a new endpoint gets documented)."""
    spec = json.loads(COMMITTED.read_text(encoding="utf-8"))
    docs = (ROOT / "docs" / "api.md").read_text(encoding="utf-8")
    for path, item in spec["paths"].items():
        for method in item:
            operation = f"{method.upper()} {path}"
            assert operation in docs, f"docs/api.md does not describe {operation}"


def test_every_operation_documents_the_403s_the_service_answers(service: ServiceProcess) -> None:
    """Without tokens the service answers 403 to any request whose `Host` names another machine (DNS
    rebinding), and with or without them to a write a page of another site started, signing in and
    out included; the spec gave a 403 only to writes that need a token, and none to reads, to
    `/healthz` or to `POST` / `DELETE /session`, which a generated client then took for undocumented."""
    paths = json.loads(COMMITTED.read_text(encoding="utf-8"))["paths"]
    url = service.base_url
    assert httpx.get(f"{url}/healthz", headers={"Host": "evil.example"}).status_code == 403
    cross_site = {"Origin": "http://evil.example", "Sec-Fetch-Site": "cross-site"}
    assert httpx.post(f"{url}/session", headers=cross_site).status_code == 403
    assert httpx.delete(f"{url}/session", headers=cross_site).status_code == 403
    undocumented = [
        f"{method.upper()} {path}"
        for path, operations in paths.items()
        for method, operation in operations.items()
        if "403" not in operation["responses"]
    ]
    assert not undocumented, f"no 403 in the spec for {undocumented}"
    assert "Host" in paths["/healthz"]["get"]["responses"]["403"]["description"]
    assert "another site" in paths["/session"]["post"]["responses"]["403"]["description"]


def test_every_412_declares_the_maps_etag_and_every_201_its_location(service: ServiceProcess) -> None:
    """A failed condition's 412 carries the map's current `ETag` (to send again), and a PUT that made
    its map answers 201 with its `Location`: both were sent, and the spec declared neither, so a
    generated client could not read them."""
    paths = json.loads(COMMITTED.read_text(encoding="utf-8"))["paths"]
    answers = {
        (f"{method.upper()} {path}", status): operation["responses"][status]
        for path, operations in paths.items()
        for method, operation in operations.items()
        for status in ("412", "201")
        if status in operation["responses"]
    }
    assert len([key for key in answers if key[1] == "412"]) >= 5
    assert len([key for key in answers if key[1] == "201"]) >= 3
    for (where, status), answer in answers.items():
        header = "ETag" if status == "412" else "Location"
        assert answer.get("headers", {}).get(header, {}).get("schema") == {"type": "string"}, where
    url = service.base_url
    made = httpx.put(f"{url}/maps/spec-headers", json={})
    assert made.status_code == 201 and made.headers["location"] == "/maps/spec-headers"
    refused = httpx.put(f"{url}/maps/spec-headers", json={}, headers={"If-None-Match": "*"})
    assert refused.status_code == 412 and refused.headers["etag"] == made.headers["etag"]


def test_the_spec_says_a_maps_layers_are_a_non_empty_set() -> None:
    """`PUT /maps/{map_id}` refuses no layers and a layer twice (422), but the spec's `layers` was a
    plain array of layer names: a client or form generated from it sent `[]` or a repeated layer
    as valid. The spec says what the service takes: at least one item, each once."""
    spec = json.loads(COMMITTED.read_text(encoding="utf-8"))
    layers = spec["components"]["schemas"]["MapConfig"]["properties"]["layers"]
    assert layers.get("minItems") == 1 and layers.get("uniqueItems") is True, layers
    assert layers["items"]["enum"] == ["occupancy", "counts", "tsdf"]


def test_the_spec_promises_a_weak_etag_on_json_answers_only(service: ServiceProcess) -> None:
    """A region answered as `.npy` or PNG carries no ETag (only JSON answers are hashed,
    `JsonETags`), but the spec declared one "on answers up to 1048576 bytes" of these operations,
    whatever their format: a generated client expected a validator on a 160 KB `.npy` region, which
    never came. The declaration now says it is a JSON answer's."""
    paths = json.loads(COMMITTED.read_text(encoding="utf-8"))["paths"]
    region = paths["/maps/{map_id}/region"]["get"]["responses"]["200"]
    assert {"application/json", "application/octet-stream"} <= set(region["content"])
    assert "JSON answer" in region["headers"]["ETag"]["description"]
    url = service.base_url
    assert httpx.put(f"{url}/maps/spec-etags", json={}).status_code == 201
    window = {"xmin": 0, "ymin": 0, "xmax": 1, "ymax": 1}
    npy = httpx.get(f"{url}/maps/spec-etags/region", params=window)
    assert npy.status_code == 200 and npy.headers["content-type"] == "application/octet-stream"
    assert "etag" not in npy.headers  # the live behaviour the declaration must describe
    as_json = httpx.get(f"{url}/maps/spec-etags/region", params={**window, "format": "json"})
    assert as_json.status_code == 200 and as_json.headers["etag"].startswith('W/"')
