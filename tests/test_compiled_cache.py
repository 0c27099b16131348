"""numba's on-disk cache is dropped whenever compiled sources change (`fleetmap.kernels`)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numba
import pytest

from fleetmap.kernels import drop_stale_compiled_cache


def _cached(package: Path) -> set[str]:
    return {p.name for p in package.rglob("__pycache__/*.nb[ic]")}


def test_cache_is_dropped_when_a_compiled_source_changes_and_only_then(tmp_path: Path) -> None:
    """A caller cached with an old callee from another module must not survive the callee's change:
    any change to a file with `@njit` drops every cached kernel of the package; other files and
    an unchanged tree keep them."""
    (tmp_path / "sub").mkdir()
    callee = tmp_path / "sub" / "callee.py"
    callee.write_text("@njit\ndef f(): return 1\n")
    (tmp_path / "caller.py").write_text("@njit\ndef g(): return f()\n")
    (tmp_path / "api.py").write_text("def h(): return 3\n")

    def cache_some() -> None:
        for d in (tmp_path / "__pycache__", tmp_path / "sub" / "__pycache__"):
            d.mkdir(exist_ok=True)
        (tmp_path / "__pycache__" / "caller.g-1.py311.nbi").write_bytes(b"index")
        (tmp_path / "sub" / "__pycache__" / "callee.f-1.py311.1.nbc").write_bytes(b"code")

    cache_some()
    assert drop_stale_compiled_cache(tmp_path)  # no stamp yet: unknown sources
    assert _cached(tmp_path) == set()
    cache_some()
    assert not drop_stale_compiled_cache(tmp_path)
    (tmp_path / "api.py").write_text("def h(): return 4\n")  # no @njit: not compiled code
    assert not drop_stale_compiled_cache(tmp_path)
    assert _cached(tmp_path) == {"caller.g-1.py311.nbi", "callee.f-1.py311.1.nbc"}
    callee.write_text("@njit\ndef f(): return 2\n")
    assert drop_stale_compiled_cache(tmp_path)
    assert _cached(tmp_path) == set()


def test_installed_package_has_a_current_stamp() -> None:
    """Importing fleetmap's kernels leaves the stamp of the current sources, so the next import
    keeps the cache."""
    assert not drop_stale_compiled_cache()


def test_cache_under_numba_cache_dir_is_dropped_too(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With `NUMBA_CACHE_DIR` set (common in containers), numba caches outside the package: the
    stale cache there is dropped as well. numba itself writes the cache here, in a subprocess."""
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "mod.py").write_text("from numba import njit\n\n@njit(cache=True)\ndef f():\n    return 1\n")
    cache_dir = tmp_path / "numba-cache"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir), "PYTHONPATH": str(tmp_path)}

    def compile_and_cache() -> set[str]:
        subprocess.run([sys.executable, "-c", "import pkg.mod; pkg.mod.f()"], env=env, check=True)
        return {p.name for p in cache_dir.rglob("*.nb[ic]")}

    monkeypatch.setattr(numba.config, "CACHE_DIR", str(cache_dir))
    assert compile_and_cache()  # numba cached f under NUMBA_CACHE_DIR
    assert drop_stale_compiled_cache(package)  # no stamp there yet
    assert not set(cache_dir.rglob("*.nb[ic]"))
    cached = compile_and_cache()
    assert not drop_stale_compiled_cache(package)  # unchanged sources: kept
    assert {p.name for p in cache_dir.rglob("*.nb[ic]")} == cached
    (package / "mod.py").write_text("from numba import njit\n\n@njit(cache=True)\ndef f():\n    return 2\n")
    assert drop_stale_compiled_cache(package)
    assert not set(cache_dir.rglob("*.nb[ic]"))
    assert not list(package.rglob("__pycache__/*.nb[ic]"))  # and nothing was cached in the tree
