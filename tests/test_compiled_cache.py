"""numba's on-disk cache is dropped whenever compiled sources change (`fleetmap.kernels`)."""

from __future__ import annotations

from pathlib import Path

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
