"""The live API against its own committed spec, with inputs generated from the spec (Schemathesis).

For every operation (except the endless event stream): schema-valid and schema-violating requests
are sent to a real server, and each answer must not be a 5xx, must have a documented status code and
content type, and a body that matches the documented schema. Path map ids are the existing map
"warehouse" (so the requests reach the map logic, not only the 404) or generated ones.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)
from test_api_support import RunningApi, fan_scan, running_api

from fleetmap.codec import encode_json

SPEC = Path(__file__).resolve().parents[1] / "openapi" / "openapi.json"
SCHEMA = schemathesis.openapi.from_dict(json.loads(SPEC.read_text()))
OPERATIONS = [result.ok() for result in SCHEMA.get_all_operations()]
CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance]


@schemathesis.serializer("application/zip")
def _zip_body(ctx: object, value: object) -> bytes:
    """Map snapshots are uploaded as zip files: send generated binary bodies as they are."""
    return value if isinstance(value, bytes) else str(value).encode()


@pytest.fixture(scope="module")
def api() -> Iterator[RunningApi]:
    with running_api() as running:
        assert running.client.put("/maps/warehouse", json={"resolution": 0.05}).status_code == 201
        scan = encode_json(fan_scan(0.0, 0.0, 0.0, [1.0] * 61), 0)
        headers = {"content-type": "application/json"}
        r = running.client.post("/maps/warehouse/scans?robot_id=robot1", content=scan, headers=headers)
        assert r.status_code == 200
        yield running


def test_spec_has_every_operation() -> None:
    paths = {(op.method.upper(), op.path) for op in OPERATIONS}
    reads = ["/healthz", "/metrics", "/maps", "/maps/{map_id}", "/maps/{map_id}/tiles/{z}/{x}/{y}.png"]
    reads += [f"/maps/{{map_id}}/{name}" for name in ("cell", "region", "surface", "export", "events")]
    assert {("GET", path) for path in reads} <= paths
    writes = [("PUT", "/maps/{map_id}"), ("DELETE", "/maps/{map_id}"), ("POST", "/maps/{map_id}/scans")]
    assert {*writes, ("POST", "/maps/{map_id}/cells"), ("POST", "/maps/{map_id}/raycast")} <= paths


def _has_inputs(op: schemathesis.APIOperation) -> bool:
    return bool(op.definition.raw.get("parameters") or op.definition.raw.get("requestBody"))


#: (operation, mode): schema-valid requests for every operation, schema-violating ones for those that
#: take any input. The event stream never ends, so it is tested in test_api.py instead.
CASES = [
    pytest.param(op, mode, id=f"{op.method.upper()} {op.path} {mode.value}")
    for op in OPERATIONS
    if not op.path.endswith("/events")
    for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE)
    if mode == GenerationMode.POSITIVE or _has_inputs(op)
]


@pytest.mark.parametrize(("operation", "mode"), CASES)
def test_generated_requests_get_documented_answers(
    api: RunningApi, operation: schemathesis.APIOperation, mode: GenerationMode
) -> None:
    @settings(
        max_examples=12,
        deadline=None,
        database=None,
        suppress_health_check=list(HealthCheck),
    )
    @given(case=operation.as_strategy(generation_mode=mode), existing=st.booleans())
    def run(case: schemathesis.Case, existing: bool) -> None:
        if existing and case.path_parameters and "map_id" in case.path_parameters and case.method != "DELETE":
            case.path_parameters["map_id"] = "warehouse"
        response = case.call(base_url=api.base_url, timeout=30)
        case.validate_response(response, checks=CHECKS)

    run()
