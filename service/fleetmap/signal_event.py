"""What a signal handler may safely do: set a `threading.Event` (`SignalEvent`: the stop request of
`fleetmap serve`, `fleetmap demo` and `fleetmap sim`), or wake a thread that does the signal's work
(`SignalWakeups`: SIGHUP's reload in `fleetmap serve`)."""

from __future__ import annotations

import os
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


class SignalWakeups:
    """Wake-ups a signal handler sends to a thread that does the signal's work: SIGHUP's reload of
    the token file in `fleetmap serve`.

    Why: a handler runs in the main thread (the HTTP server's event loop) between any two bytecodes,
    those of a handler included. SIGHUP's reload read the token file and logged inside the handler:
    a burst of SIGHUPs nested handlers until a RecursionError, and the exceptions came out of
    whatever the main thread was running (asyncio logged them from a socket's read callback). Here
    the handler only writes a byte to a non-blocking pipe (no lock, no allocation that can fail
    half-way); the thread reads all the bytes waiting at once and does the work once for them. So
    every signal is followed by at least one run of the work that starts after it, and a burst of
    signals costs a few runs."""

    def __init__(self) -> None:
        self._read, self._write = os.pipe()
        os.set_blocking(self._write, False)

    def notify_in_handler(self) -> None:
        """Wake the waiting thread; safe in a signal handler, and nested in one."""
        # (A plain try, not contextlib.suppress: as few Python frames as can be inside a handler.)
        try:  # noqa: SIM105
            os.write(self._write, b"\0")
        except OSError:
            pass  # the pipe is full (a wake-up is pending already) or closed (the process is ending)

    def wait(self) -> bool:
        """Block until at least one wake-up was sent, and take every one sent so far; False once
        `close` was called (the thread should end)."""
        try:
            taken = os.read(self._read, 65536)
        except OSError:
            return False
        if not taken:  # closed: no wake-up can come any more
            os.close(self._read)
        return bool(taken)

    def close(self) -> None:
        """End `wait` in the waiting thread (it returns False). Call once, after the handler is
        replaced."""
        os.close(self._write)
