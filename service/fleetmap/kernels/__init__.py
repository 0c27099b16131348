"""Compiled hot loops (numba `njit`, `nogil`) over plain arrays.

Coordinates here are in CELL units (metres / resolution), so cell (i, j) is the unit square
`[i, i+1) x [j, j+1)`. The Python modules around these kernels own the tile bookkeeping; the kernels
own nothing and keep no state.

Importing this package first makes sure numba has somewhere to cache compiled code
(`ensure_compiled_cache_location`), then drops numba's on-disk cache of the whole `fleetmap` package
when any compiled source changed (`drop_stale_compiled_cache`). Every module with `@njit(cache=True)`
imports this package before its kernels are defined.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import stat
import tempfile
from pathlib import Path

from fleetmap.kernels.numba_loading import load_numba_array_functions

#: Where the digest of the compiled sources is kept, next to numba's cache files.
_STAMP = "fleetmap-compiled-sources.sha256"


def drop_stale_compiled_cache(package: Path = Path(__file__).parent.parent) -> bool:
    """Delete numba's cached machine code (`*.nbi`, `*.nbc`) of `package` when the sources with
    `@njit` in them changed since the cache was written; True if it did.

    numba checks only the defining file of each cached function, so a cached kernel keeps the
    code it was compiled with of every kernel it calls in another module: after an edit or an
    upgrade that changes only the callee, the caller would run the old callee. Recompiling
    everything once (about 15 s) is the safe price.

    The cache is wherever numba keeps it for each source directory: `NUMBA_CACHE_DIR` when set,
    else the directory's `__pycache__` when writable, else the user-wide cache directory. Each of
    those directories holds its own stamp of the sources; one that cannot be written is left
    alone (numba cannot cache there either)."""
    digest = hashlib.sha256()
    sources: dict[Path, Path] = {}  # a compiled source of each directory
    for source in sorted(package.rglob("*.py")):
        text = source.read_bytes()
        if b"@njit" in text:
            digest.update(str(source.relative_to(package)).encode() + b"\0" + text)
            sources.setdefault(source.parent, source)  # numba's cache is per directory
    dropped = False
    for directory in sorted({_numba_cache_directory(source) for source in sources.values()}):
        stamp = directory / _STAMP
        try:
            if stamp.read_text() == digest.hexdigest():
                continue
        except OSError:
            pass
        try:
            for cached in directory.glob("*.nb[ic]"):
                cached.unlink(missing_ok=True)
            directory.mkdir(parents=True, exist_ok=True)
            stamp.write_text(digest.hexdigest())
        except OSError:
            continue
        dropped = True
    return dropped


def ensure_compiled_cache_location(package: Path = Path(__file__).parent.parent) -> Path | None:
    """Point numba's cache at a private directory in the temp directory when numba would find no
    place of its own for the kernels of `package`; that directory, or None when numba has one.

    numba refuses to define a `cache=True` kernel ("cannot cache function ...: no locator
    available") when `NUMBA_CACHE_DIR` is unset, the source's `__pycache__` cannot be written and
    neither can the user-wide cache directory: a container run under an arbitrary user id (as
    OpenShift and many Kubernetes set-ups do) with the package installed read-only and `HOME=/`.
    The service would not start. The fallback costs one compilation per container (about 15 s),
    which `NUMBA_CACHE_DIR` on a writable volume avoids. The temp directory is shared: a
    `fleetmap-numba-cache-<uid>` found there that another user owns or could write is not used (numba
    unpickles its cache files, so theirs would run in the service) but a fresh one of
    `tempfile.mkdtemp`, compiled anew at each start. Raises RuntimeError, with what to do, when the
    temp directory cannot be written either."""
    import numba

    source = package / "kernels" / "traversal.py"
    try:
        # numba.config sets its options from the environment at import (globals()): no stub has them.
        if numba.config.CACHE_DIR or _locator_directory(source) is not None:  # type: ignore[attr-defined]
            return None
    except (ImportError, AttributeError, TypeError):  # a numba whose locators moved: its own choice
        return None
    directory = Path(tempfile.gettempdir()) / f"fleetmap-numba-cache-{os.getuid()}"
    try:
        with contextlib.suppress(FileExistsError):  # ours from an earlier start, or not: checked next
            directory.mkdir(mode=0o700)
        if not _is_private(directory):
            directory = Path(tempfile.mkdtemp(prefix=f"{directory.name}-"))
        with tempfile.TemporaryFile(dir=directory):
            pass
    except OSError as exc:
        raise RuntimeError(
            f"numba has no writable directory for fleetmap's compiled code (not {source.parent}/__pycache__, "
            f"not the user cache directory, not {directory}: {exc.strerror}); set NUMBA_CACHE_DIR to one"
        ) from exc
    numba.config.CACHE_DIR = str(directory)  # type: ignore[attr-defined]  # (see above)
    return directory


def _is_private(directory: Path) -> bool:
    """Whether `directory` is a directory (not a link to one) of this user that no one else may write."""
    status = directory.lstat()
    return stat.S_ISDIR(status.st_mode) and status.st_uid == os.getuid() and not status.st_mode & 0o022


def _probe() -> None:
    """A function for numba's cache locators, which want one (they read only its first line)."""


def one_call_kernel_cached() -> bool:
    """Whether numba's cache holds a compiled `integrate_scan.integrate_ray_scan` (the largest kernel,
    which every map's first scans run): False on the first start after an install or an upgrade, or
    after `drop_stale_compiled_cache` dropped the cache. A cache written on another CPU counts as
    held (numba then compiles in-process, as it would anyway). Call after this package's import."""
    directory = _numba_cache_directory(Path(__file__).parent / "integrate_scan.py")
    return any(directory.glob("integrate_scan.integrate_ray_scan-*.nbi"))


def _numba_cache_directory(source: Path) -> Path:
    """The directory where numba caches the functions of `source` (`_locator_directory`), or the
    in-tree `__pycache__` when numba's locators cannot be asked."""
    try:
        found = _locator_directory(source)
    except (ImportError, AttributeError, TypeError):
        return source.parent / "__pycache__"
    return source.parent / "__pycache__" if found is None else found


def _locator_directory(source: Path) -> Path | None:
    """The first of numba's cache locators, in numba's order, that applies to `source` (numba's own
    choice; they create the directory if they can), or None when none does. Raises ImportError,
    AttributeError or TypeError for a numba whose locators are not where they are today."""
    from numba.core.caching import InTreeCacheLocator, UserProvidedCacheLocator, UserWideCacheLocator

    for locator_class in (UserProvidedCacheLocator, InTreeCacheLocator, UserWideCacheLocator):
        locator = locator_class.from_function(_probe, str(source))
        if locator is not None:
            return Path(locator.get_cache_path())
    return None


ensure_compiled_cache_location()
drop_stale_compiled_cache()
load_numba_array_functions()
