"""numba's on-disk cache is dropped whenever compiled sources change (`fleetmap.kernels`)."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numba
import pytest

import fleetmap
from fleetmap.kernels import drop_stale_compiled_cache, ensure_compiled_cache_location

if TYPE_CHECKING:
    from service_process import ServiceProcess


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


#: Run in a fresh interpreter: the service's warm-up, then what a robot's first scans make the
#: service run (plan and apply into a new map, then into its existing tiles, for both sensor models,
#: with the default configuration; the journal's encoding). Prints the compiled kernels that only
#: the scans loaded.
#: `loaded()`, for scripts run in a fresh interpreter: every compiled kernel a loaded fleetmap module
#: names, with the number of signatures it has loaded (or compiled).
LOADED_KERNELS = """
import sys
from numba.core.registry import CPUDispatcher

def loaded():
    return {
        f"{name}.{attr}": len(obj.overloads)
        for name, module in list(sys.modules.items()) if name.startswith("fleetmap")
        for attr, obj in vars(module).items() if isinstance(obj, CPUDispatcher)
    }
"""

_FIRST_SCANS_AFTER_WARM_UP = (
    LOADED_KERNELS
    + """
import numpy as np
from fleetmap.warm_up import warm_up
from fleetmap.config import MapConfig
from fleetmap.grid_map import GridMap
from fleetmap.scan import Scan
from fleetmap.storage_format import scan_to_blob

warm_up()
before = loaded()
rng = np.random.default_rng(0)
for sensor_model in ("ray", "beam"):
    gmap = GridMap(MapConfig(sensor_model=sensor_model))
    for x in (0.0, 0.5):
        ranges = rng.uniform(1.0, 20.0, 1081)
        ranges[::50] = np.inf
        scan = Scan.from_fan((x, 0.0, 0.1), -2.35, 4.7 / 1081, ranges.tolist(), 0.1, 30.0)
        assert gmap.apply(gmap.plan(scan)).cell_updates > 0
        assert scan_to_blob(scan)
after = loaded()
print(sorted(k for k, n in after.items() if n > before.get(k, 0)))
import sys
print("scipy.linalg" in sys.modules)  # numba's BLAS probe imports it (numba_loading)
import scipy.linalg.cython_blas  # hidden from that probe only: importable later
"""
)


def test_warm_up_loads_every_kernel_a_robots_first_scans_need() -> None:
    """The service warms its kernels up before it listens, so that the first scans do not wait for
    numba to load (about 50 ms) or compile (10 s) them. Ingest plans and applies; `integrate`'s one
    compiled call, which creates its own tiles, does not reach those kernels, so the warm-up must
    run both paths. Checked in a fresh interpreter: nothing the first scans run is loaded late."""
    out = subprocess.run(
        [sys.executable, "-c", _FIRST_SCANS_AFTER_WARM_UP], capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr
    late, blas_probed = out.stdout.split()
    assert late == "[]", f"kernels loaded only by the first scans: {late}"
    # A start without numba's BLAS probe (`kernels.numba_loading`): it imported all of scipy.linalg
    # into every process that loads a kernel, 0.17 s of CPU each, for BLAS no kernel calls.
    assert blas_probed == "False", "loading the kernels imported scipy.linalg"


def _package_numba_cannot_cache(tmp_path: Path) -> tuple[Path, dict[str, str]]:
    """A copy of the fleetmap package where no numba cache locator applies, and the environment for
    it: every `__pycache__` is a file, and the user cache directory lies under a file, as in a
    container run under an arbitrary user id with the package installed read-only and HOME=/
    (this test runs as root, for whom no directory is read-only, so files stand in for them)."""
    root = tmp_path / "site"
    shutil.copytree(
        Path(fleetmap.__file__).parent, root / "fleetmap", ignore=shutil.ignore_patterns("__pycache__")
    )
    for directory in [root / "fleetmap", *(p for p in (root / "fleetmap").rglob("*") if p.is_dir())]:
        (directory / "__pycache__").write_text("not a directory")
    (tmp_path / "home").write_text("not a directory")
    (tmp_path / "tmp").mkdir()
    env = {key: value for key, value in os.environ.items() if key != "NUMBA_CACHE_DIR"}
    env.update(
        PYTHONPATH=str(root),
        HOME=str(tmp_path / "home"),
        XDG_CACHE_HOME=str(tmp_path / "home" / "cache"),
        TMPDIR=str(tmp_path / "tmp"),
        PYTHONDONTWRITEBYTECODE="1",
    )
    return root, env


def test_kernels_load_where_numba_has_no_cache_directory_of_its_own(tmp_path: Path) -> None:
    """Without the fallback numba refuses to define the kernels ("no locator available") and the
    service cannot start; with it the compiled code is cached in a private temp directory."""
    root, env = _package_numba_cannot_cache(tmp_path)
    script = (
        "import numba, fleetmap.grid_map, fleetmap.storage_format, fleetmap.sim\n"
        "from fleetmap.kernels.traversal import cell_count\n"
        "assert cell_count(0.5, 0.5, 3.5, 2.5, 0) > 0\n"
        "print(numba.config.CACHE_DIR)\n"
    )
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    fallback = tmp_path / "tmp" / f"fleetmap-numba-cache-{os.getuid()}"
    assert out.stdout.strip() == str(fallback)
    assert list(fallback.rglob("*.nbi")), "numba cached nothing in the fallback directory"
    assert not list(root.rglob("*.nb[ic]"))


def test_no_writable_directory_for_compiled_code_is_one_clear_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    root, env = _package_numba_cannot_cache(tmp_path)
    for key in ("HOME", "XDG_CACHE_HOME"):
        monkeypatch.setenv(key, env[key])
    monkeypatch.setattr(numba.config, "CACHE_DIR", "")
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "home" / "tmp"))  # under a file
    with pytest.raises(RuntimeError, match="set NUMBA_CACHE_DIR"):
        ensure_compiled_cache_location(root / "fleetmap")
    assert numba.config.CACHE_DIR == ""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    assert (
        ensure_compiled_cache_location(root / "fleetmap")
        == tmp_path / "tmp" / f"fleetmap-numba-cache-{os.getuid()}"
    )
    assert ensure_compiled_cache_location(root / "fleetmap") is None  # numba now has a place


@pytest.mark.parametrize("owner", ["another user", "this user, writable by all", "a file in its place"])
def test_the_fallback_never_uses_a_cache_directory_others_can_write(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, owner: str
) -> None:
    """numba loads its cache files with pickle: a fallback directory made beforehand in the shared
    temp directory by someone else (or left writable to everyone) would run their code in the
    service. Such a directory is left alone for a fresh private one."""
    root, env = _package_numba_cannot_cache(tmp_path)
    for key in ("HOME", "XDG_CACHE_HOME"):
        monkeypatch.setenv(key, env[key])
    monkeypatch.setattr(numba.config, "CACHE_DIR", "")
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    planted = tmp_path / "tmp" / f"fleetmap-numba-cache-{os.getuid()}"
    if owner == "a file in its place":  # would stop the service from starting, were it not replaced
        planted.write_text("")
    else:
        planted.mkdir()
        planted.chmod(0o777)
    if owner == "another user":
        if os.getuid() != 0:
            pytest.skip("only root can give a directory to another user (CI runs the tests as root)")
        os.chown(planted, os.getuid() + 1, -1)
    chosen = ensure_compiled_cache_location(root / "fleetmap")
    assert chosen is not None and chosen != planted
    status = chosen.stat()
    assert (status.st_uid, status.st_mode & 0o077) == (os.getuid(), 0)
    assert str(chosen) == numba.config.CACHE_DIR


def _resident_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError(f"no VmRSS for process {pid}")


#: A `sitecustomize` (on PYTHONPATH) through which the kernels' compile child, and it alone, prints a
#: line: numba warns there on some machines. The service must log it in its own format.
CHILD_SAYS = "a warning printed by the compile child"
_SITECUSTOMIZE = f"""
import sys
if "fleetmap.warm_up" in sys.orig_argv:
    print({CHILD_SAYS!r}, file=sys.stderr, flush=True)
"""


def _printing_child_env(tmp_path: Path) -> dict[str, str]:
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(_SITECUSTOMIZE)
    return {"PYTHONPATH": os.pathsep.join([str(site), *filter(None, [os.environ.get("PYTHONPATH")])])}


def test_a_first_start_compiles_in_a_child_and_keeps_none_of_the_compilers_memory(tmp_path: Path) -> None:
    """The first start on an empty cache compiles the kernels in a child process, and then holds about
    what a start that loaded them holds: compiled in the service's own process, LLVM kept ~210 MB
    more for the process's whole life. The second start on the same cache loads them. What the
    child printed is in the service's log as one record of its format (JSON here): a plain-text
    line would break a log collector."""
    from service_process import ServiceProcess

    env = {"NUMBA_CACHE_DIR": str(tmp_path / "numba-cache"), **_printing_child_env(tmp_path)}
    starts = []
    for name in ("cold", "warm"):
        (tmp_path / name).mkdir()
        args = ["--in-memory", "--log-format", "json"]
        with ServiceProcess(tmp_path / name, args, startup_timeout=600, env=env) as service:
            assert service.proc is not None
            starts.append((_resident_mb(service.proc.pid), service.logs()))
    (cold_mb, cold_log), (warm_mb, warm_log) = starts
    assert cold_mb < warm_mb + 80, f"first start {cold_mb:.0f} MB resident, second {warm_mb:.0f} MB"
    records = [json.loads(line) for line in cold_log.splitlines()]  # every line one JSON object
    messages = [str(record["message"]) for record in records]
    # Before the address, a first start says why it takes up to minutes.
    said = "compiling the engine's kernels in a child process (the first start after an install: about 15 s"
    assert any(message.startswith(said) for message in messages), cold_log
    printed = [r for r in records if CHILD_SAYS in str(r["message"])]
    assert [(r["level"], r["message"]) for r in printed] == [
        ("WARNING", f"the kernels' compilation in a child process printed:\n{CHILD_SAYS}")
    ], cold_log
    assert "failed" not in cold_log
    assert "loading the engine's compiled kernels" in warm_log and "child process" not in warm_log, warm_log


def _children(pid: int) -> list[int]:
    return [int(child) for child in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


def _compile_children(pid: int) -> list[int]:
    """The children of `pid` that run `fleetmap.warm_up` (the first start's compile)."""
    found = []
    for child in _children(pid):
        try:
            if "fleetmap.warm_up" in Path(f"/proc/{child}/cmdline").read_text():
                found.append(child)
        except OSError:  # gone meanwhile
            continue
    return found


@contextlib.contextmanager
def _first_start(
    tmp_path: Path, new_session: bool = False
) -> Iterator[tuple[subprocess.Popen[bytes], ServiceProcess, int]]:
    """A service started on an empty numba cache (`tmp_path / "numba-cache"`) and not waited for: it,
    its `ServiceProcess` (command line and log) and its compile child's pid, once that runs. With
    `new_session`, the service leads a process group of its own, as a terminal's foreground job.
    The service is killed on the way out if it still runs."""
    from service_process import ServiceProcess, wait_for

    service = ServiceProcess(tmp_path)  # its command line and log file; started here, not waited for
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}
    with (
        open(service.log_path, "wb") as log,
        subprocess.Popen(
            service.args, stdout=log, stderr=log, env=env, start_new_session=new_session
        ) as proc,
    ):
        try:
            # The compile child, not a passing one (the C library's `ldconfig -p` of ctypes, if any).
            wait_for(lambda: _compile_children(proc.pid), 120, what="the compile child")
            (child,) = _compile_children(proc.pid)
            yield proc, service, child
        finally:
            if proc.poll() is None:
                proc.kill()


def test_a_service_stopped_during_its_first_compile_ends_the_compile_and_exits_cleanly(
    tmp_path: Path,
) -> None:
    """`kill` (or `docker stop`) signals the service, not its process group: the compile child goes on
    compiling. The service must end it and exit at once, not wait out the compilation (15 s to
    minutes) and then restore and serve for nothing; the child must not outlive it."""
    with _first_start(tmp_path) as (proc, service, child):
        proc.send_signal(signal.SIGTERM)  # the service alone
        assert proc.wait(60) == 0, service.logs()
    assert not Path(f"/proc/{child}").exists(), "the compile child outlived the service"
    logs = service.logs()
    assert "the kernels' compilation was cut short" in logs and "stopped before serving" in logs, logs
    assert "compiling them here" not in logs and "fleetmap serving" not in logs, logs
    cache = tmp_path / "numba-cache"
    assert not list(cache.rglob("integrate_scan.integrate_ray_scan-*.nbi")), "the compilation ran to its end"


def test_ctrl_c_during_the_first_compile_stops_the_service_without_a_traceback(tmp_path: Path) -> None:
    """Ctrl-C in a terminal signals its whole foreground process group: the compile child, interrupted
    inside numba, printed a KeyboardInterrupt traceback of some 300 lines, which the service logged
    as a warning before "stopped before serving" (a first `make demo` stopped while it compiled)."""
    with _first_start(tmp_path, new_session=True) as (proc, service, child):
        time.sleep(1.5)  # the child is compiling now, well past its interpreter's start
        os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C does
        assert proc.wait(60) == 0, service.logs()
    assert not Path(f"/proc/{child}").exists(), "the compile child outlived the service"
    logs = service.logs()
    assert "stopped before serving" in logs, logs
    assert "Traceback" not in logs and "KeyboardInterrupt" not in logs and "printed" not in logs, logs


def test_a_service_killed_during_its_first_compile_leaves_no_compile_child(tmp_path: Path) -> None:
    """SIGKILL (or the OOM killer) gives the service no chance to end its compile child, which went
    on compiling, orphaned, for up to minutes, beside the compile of the service started next. The
    child now gets SIGTERM from the kernel when the service dies."""
    from service_process import wait_for

    with _first_start(tmp_path) as (proc, _, child):
        proc.kill()
    try:
        wait_for(lambda: not _alive(child), 20, what="the compile child gone with the service")
    finally:
        if _alive(child):
            os.kill(child, signal.SIGKILL)


def _alive(pid: int) -> bool:
    """Whether process `pid` runs (a zombie, ended and not yet reaped, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False
