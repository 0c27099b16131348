"""Failed sign-ins per client address, counted within a window, in bounded memory: the policy
`fleetmap.api.signin_limit` applies to `POST /session` (its docstring says why and how).

Kept apart from the web framework: `fleetmap serve` names these defaults in its options before it
loads the REST API.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

#: Failed sign-ins from one address within the window before its sign-ins are refused (429).
DEFAULT_MAX_FAILURES = 10
#: Seconds, from an address's first failure, within which its failures are counted.
DEFAULT_WINDOW = 60.0
#: Client addresses tracked at once (about 200 bytes each, the address's name included).
DEFAULT_MAX_CLIENTS = 10_000


@dataclass(slots=True)  # no `__dict__` of its own: 40 bytes less an address (250 were measured)
class _Failures:
    """An address's failures in its current window."""

    first: float  # when the window's first failure came (the clock's time)
    count: int


class SignInLimiter:
    """Failed sign-ins per client address within `window` seconds of each address's first, for at
    most `max_clients` addresses (`fleetmap.api.signin_limit` says the policy). Used on the event
    loop only: not thread-safe."""

    def __init__(
        self,
        max_failures: int = DEFAULT_MAX_FAILURES,
        window: float = DEFAULT_WINDOW,
        max_clients: int = DEFAULT_MAX_CLIENTS,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if max_failures < 1 or window <= 0 or max_clients < 1:
            raise ValueError("max_failures, window and max_clients must be positive")
        self.max_failures = max_failures
        self.window = window
        self.max_clients = max_clients
        self.clock = clock
        #: Address -> its failures, the least recently failed first.
        self._failures: OrderedDict[str, _Failures] = OrderedDict()

    def __len__(self) -> int:
        """How many addresses are tracked."""
        return len(self._failures)

    def retry_after(self, address: str) -> float | None:
        """Seconds until `address` may sign in again, or None if it may now."""
        failures = self._current(address)
        if failures is None or failures.count < self.max_failures:
            return None
        return failures.first + self.window - self.clock()

    def failed(self, address: str) -> None:
        """Count a failed sign-in from `address`."""
        failures = self._current(address)
        if failures is None:
            now = self.clock()
            # The least recently failed first: drop those whose window has passed, then, past the
            # cap, the least recently failed whatever its window.
            while self._failures and now - next(iter(self._failures.values())).first >= self.window:
                self._failures.popitem(last=False)
            self._failures[address] = _Failures(first=now, count=1)
            while len(self._failures) > self.max_clients:
                self._failures.popitem(last=False)
        else:
            failures.count += 1
            self._failures.move_to_end(address)

    def _current(self, address: str) -> _Failures | None:
        """`address`'s failures in a window still running (one that has passed is dropped)."""
        failures = self._failures.get(address)
        if failures is not None and self.clock() - failures.first >= self.window:
            del self._failures[address]
            return None
        return failures
