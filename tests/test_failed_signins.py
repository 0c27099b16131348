"""The failed sign-ins' count (`fleetmap.failed_signins.SignInLimiter`) on its own, with a clock the
test moves: the window counts from an address's first failure, and memory stays bounded however
many addresses fail. test_auth_session.py checks the limit on the real service."""

from __future__ import annotations

import tracemalloc

import pytest

from fleetmap.failed_signins import SignInLimiter


class Clock:
    """A clock the test sets."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_an_address_is_refused_from_its_nth_failure_until_its_window_has_passed() -> None:
    clock = Clock()
    limiter = SignInLimiter(max_failures=3, window=60.0, clock=clock)
    for _ in range(2):
        limiter.failed("a")
        assert limiter.retry_after("a") is None
    clock.now += 10
    limiter.failed("a")
    assert limiter.retry_after("a") == pytest.approx(50.0)  # 60 s from the first failure
    assert limiter.retry_after("b") is None  # another address
    clock.now += 49.5
    assert limiter.retry_after("a") == pytest.approx(0.5)
    clock.now += 0.5
    assert limiter.retry_after("a") is None and len(limiter) == 0  # passed: forgotten
    limiter.failed("a")
    assert limiter.retry_after("a") is None  # a new window, one failure in it


def test_memory_is_bounded_however_many_addresses_fail() -> None:
    clock = Clock()
    limiter = SignInLimiter(max_failures=2, window=60.0, max_clients=100, clock=clock)
    for n in range(10_000):
        limiter.failed(f"10.0.{n // 256}.{n % 256}")
        limiter.failed(f"10.0.{n // 256}.{n % 256}")
    assert len(limiter) == 100
    # The addresses that failed most recently are the ones kept, and refused.
    assert limiter.retry_after("10.0.39.15") is not None  # n = 9999
    assert limiter.retry_after("10.0.0.0") is None  # forgotten
    # Addresses whose window has passed make room for a new one before any still counting goes.
    clock.now += 61
    limiter.failed("192.0.2.1")
    assert len(limiter) == 1


def test_each_address_tracked_takes_what_the_docs_say() -> None:
    """docs/security.md: at most 10,000 addresses, about 200 bytes each (2 MB in all), an IPv6
    network's longer name included. It said 150 bytes: 240 to 250 were measured, the address's
    name, its entry and its count's object with a `__dict__` of its own."""
    limiter = SignInLimiter(max_failures=3)
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for n in range(limiter.max_clients):  # each name made for its request, as the service does
            limiter.failed(f"2001:db8:{n >> 16:x}:{n & 0xFFFF:x}::/64")
        held = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert len(limiter) == limiter.max_clients
    assert held / len(limiter) < 225, held / len(limiter)


def test_nonsense_settings_are_refused() -> None:
    for kwargs in ({"max_failures": 0}, {"window": 0.0}, {"max_clients": 0}):
        with pytest.raises(ValueError):
            SignInLimiter(**kwargs)
