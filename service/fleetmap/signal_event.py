"""What a signal handler may safely do: set a `threading.Event` (`SignalEvent`: the stop request of
`fleetmap serve`, `fleetmap demo` and `fleetmap sim`), or wake a thread that does the signal's work
(`SignalWakeups`: SIGHUP's reload in `fleetmap serve`); and SIGHUP held while a command starts
(`HANGUPS`)."""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable
from types import FrameType
from typing import Any

#: What `signal.signal` takes and returns: a handler, `SIG_DFL` / `SIG_IGN`, or None.
Handler = Callable[[int, FrameType | None], Any] | int | signal.Handlers | None


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


class HeldSignal:
    """A signal noted, not acted on, from `hold` until the command says what it means (`release`).

    Why: `fleetmap serve` reloads its token file on SIGHUP and `fleetmap demo` stops on it, but
    each could install its handler only after importing its modules (pydantic, FastAPI, numba: 2-3 s
    on a busy machine). A SIGHUP in that window (a service manager's reload right after the start,
    a terminal closed at once) took the default action: the process ended, exit 129, its start cut
    short. `fleetmap`'s entry point holds SIGHUP before any of those imports."""

    def __init__(self, signum: signal.Signals) -> None:
        self.signum = signum
        self.holding = False
        self._arrived = False

    def hold(self) -> None:
        """Note the signal from now on instead of acting on it; main thread only."""
        signal.signal(self.signum, self._note)
        self.holding = True

    def _note(self, _signum: int, _frame: FrameType | None) -> None:
        self._arrived = True

    def release(self, handler: Handler) -> Handler:
        """Install `handler` for the signal (`SIG_DFL`: its default action) and, when it came while
        held, deliver it once now (so a held SIGHUP ends a command that does not take it, as it
        would have); returns the handler replaced. Main thread only."""
        previous = signal.signal(self.signum, handler)
        arrived, self._arrived, self.holding = self._arrived, False, False
        if arrived:
            signal.raise_signal(self.signum)
        return previous


#: SIGHUP, held by `fleetmap`'s entry point (`fleetmap.__main__.main`) until the command runs.
HANGUPS = HeldSignal(signal.SIGHUP)
