"""The test harness's ports (tests/service_process.py): the xdist workers of one run never pick the
same one, so that two services starting at once cannot be given one port (CI 2026-11-29: a service
failed to start, "Address already in use")."""

from __future__ import annotations

import pytest
import service_process


def test_xdist_workers_pick_ports_from_parts_of_the_range_that_do_not_overlap(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    parts = []
    for k in range(3):
        monkeypatch.setenv("PYTEST_XDIST_WORKER", f"gw{k}")
        monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", "3")
        parts.append(service_process._port_range())
        low, high = parts[-1]
        assert all(low <= service_process.free_port() < high for _ in range(20))
    assert parts[0][0] == service_process._PORTS[0] and parts[-1][1] <= service_process._PORTS[1]
    assert all(a[1] <= b[0] for a, b in zip(parts, parts[1:], strict=False)), parts
    monkeypatch.delenv("PYTEST_XDIST_WORKER")
    assert service_process._port_range() == service_process._PORTS  # one process: the whole range
