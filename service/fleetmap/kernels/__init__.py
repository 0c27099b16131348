"""Compiled hot loops (numba `njit`, `nogil`) over plain arrays.

Coordinates here are in CELL units (metres / resolution), so cell (i, j) is the unit square
`[i, i+1) x [j, j+1)`. The Python modules around these kernels own the tile bookkeeping; the kernels
own nothing and keep no state.

Importing this package first drops numba's on-disk cache of the whole `fleetmap` package when any
compiled source changed (`drop_stale_compiled_cache`).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

#: Where the digest of the compiled sources is kept, next to numba's cache files.
_STAMP = "fleetmap-compiled-sources.sha256"


def drop_stale_compiled_cache(package: Path = Path(__file__).parent.parent) -> bool:
    """Delete numba's cached machine code (`__pycache__/*.nbi, *.nbc`) under `package` when the
    sources with `@njit` in them changed since the cache was written; True if it did.

    numba checks only the defining file of each cached function, so a cached kernel keeps the
    code it was compiled with of every kernel it calls in another module: after an edit or an
    upgrade that changes only the callee, the caller would run the old callee. Recompiling
    everything once (about 10 s) is the safe price. A read-only install is left alone (numba
    cannot cache there either)."""
    digest = hashlib.sha256()
    for source in sorted(package.rglob("*.py")):
        text = source.read_bytes()
        if b"@njit" in text:
            digest.update(str(source.relative_to(package)).encode() + b"\0" + text)
    stamp = package / "__pycache__" / _STAMP
    try:
        if stamp.read_text() == digest.hexdigest():
            return False
    except OSError:
        pass
    try:
        for cached in package.rglob("__pycache__/*.nb[ic]"):
            cached.unlink(missing_ok=True)
        stamp.parent.mkdir(exist_ok=True)
        stamp.write_text(digest.hexdigest())
    except OSError:
        return False
    return True


drop_stale_compiled_cache()
