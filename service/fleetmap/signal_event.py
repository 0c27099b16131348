"""A `threading.Event` that a signal handler may set: the stop request of `fleetmap serve`,
`fleetmap demo` and `fleetmap sim`."""

from __future__ import annotations

import threading


class SignalEvent(threading.Event):
    """`threading.Event` plus `set_in_handler`, for signal handlers.

    Why: `Event.set` holds the event's lock, which is not re-entrant, and Python runs a signal's
    handler in the main thread between any two bytecodes, those of a handler included. A second
    signal arriving while the first one's handler was inside `set` ran `set` again in the same
    thread, which waited for the lock its own caller held: for ever, waking only to run the next
    signal's handler on top. `fleetmap serve`, sent SIGTERM every 5 ms while it shut down, died
    of a RecursionError that way (CI, 2026-11-28)."""

    def __init__(self) -> None:
        super().__init__()
        self._setting = False

    def set_in_handler(self) -> None:
        """`set`, from a signal handler: a handler that runs while another is inside this call (or
        after it) returns at once; the outer call sets the event."""
        if self._setting:
            return
        self._setting = True
        self.set()
