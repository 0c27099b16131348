"""`SignalEvent.set_in_handler`: a signal whose handler runs while another handler is inside `set`.

Python runs a handler between two bytecodes of the main thread, a handler's own included, so the
interleaving CI met by chance (SIGTERM every 5 ms while the service stopped: RecursionError) is made
certain here: the event's condition is wrapped so that the signal is raised while `set` holds the
event's lock (a private attribute of `threading.Event`, touched by this test only). Each case runs in
a child interpreter, because the unsafe one never returns."""

from __future__ import annotations

import subprocess
import sys

_PROGRAM = """
import signal, sys, threading
from fleetmap.signal_event import SignalEvent

event = SignalEvent()
safe = sys.argv[1] == "set_in_handler"
set_event = event.set_in_handler if safe else event.set
nested = []


def handler(signum, frame):
    nested.append(signum)
    set_event()


class RaisingCondition:
    # The event's own condition, raising SIGUSR1 while `set` holds its lock.
    def __init__(self, inner):
        self.inner = inner

    def __enter__(self):
        return self.inner.__enter__()

    def __exit__(self, *exc):
        return self.inner.__exit__(*exc)

    def notify_all(self):
        signal.raise_signal(signal.SIGUSR1)  # its handler runs before the next bytecode
        self.inner.notify_all()


signal.signal(signal.SIGUSR1, handler)
event._cond = RaisingCondition(event._cond)
set_event()
print("set" if event.is_set() and nested == [signal.SIGUSR1] else f"not set, {nested}", flush=True)
"""


def _run(method: str, timeout: float) -> subprocess.CompletedProcess[str] | None:
    try:
        return subprocess.run(
            [sys.executable, "-c", _PROGRAM, method], capture_output=True, text=True, timeout=timeout
        )
    except subprocess.TimeoutExpired:
        return None


def test_a_handler_that_sets_the_event_inside_set_in_handler_returns() -> None:
    done = _run("set_in_handler", timeout=60)
    assert done is not None, "set_in_handler hung with a signal arriving inside it"
    assert done.returncode == 0 and done.stdout.strip() == "set", done.stderr


def test_the_same_with_event_set_hangs() -> None:
    """What `set_in_handler` is for: with plain `Event.set`, the nested handler waits for the lock its
    own caller holds, for ever (so the case above could fail)."""
    assert _run("set", timeout=5) is None
