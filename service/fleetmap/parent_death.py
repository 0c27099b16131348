"""A child process that ends with its parent: the service started by `fleetmap demo`, and the
kernels' compile child started by `fleetmap serve` (`warm_up.compile_in_child`).

Why: a parent stops its children when it stops cleanly, but one killed outright (SIGKILL, the OOM
killer, a crash) cannot, and its children lived on: the demo's service holding the ports and the
data directory the next `make demo` found in use, a compile child compiling for minutes beside the
restarted service's own compile. Linux's prctl(PR_SET_PDEATHSIG) has the kernel send the child a
signal when the parent dies, however it dies."""

from __future__ import annotations

import ctypes
import os
import signal
import sys

#: prctl(2)'s option: the signal a process gets when its parent dies.
_PR_SET_PDEATHSIG = 1


def end_with_parent(parent: int) -> None:
    """Called in the child (before exec, or at its start): SIGTERM it when `parent` dies, and now if
    `parent` is gone already (it died before the call took effect). Elsewhere than Linux, nothing.

    The kernel sends the signal when the THREAD that started the child ends: start the child from a
    thread that lives as long as the parent (the main thread)."""
    if not sys.platform.startswith("linux"):
        return
    ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM))
    if os.getppid() != parent:
        os.kill(os.getpid(), signal.SIGTERM)
