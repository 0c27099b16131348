"""Waiting for a `MapRegistry` to have nothing left to do, for tests that check what it did."""

from __future__ import annotations

import time

from fleetmap.registry import MapRegistry


def wait_idle(registry: MapRegistry, timeout: float = 10.0) -> bool:
    """Wait until `registry`'s queue is empty, no scan is in flight and every applied scan is durable
    (its journal flushed). False if `timeout` seconds passed first. The service itself never waits
    so: it answers each scan's caller when that scan is integrated."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if registry.queue.idle():
            if registry.durable is not None:
                registry.durable.writer.flush()
            return True
        time.sleep(0.005)
    return False
