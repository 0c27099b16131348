"""glibc's malloc arenas, limited by the service itself (`fleetmap.malloc_arenas`): counted by glibc's
own `malloc_info` in real processes whose threads allocate at once."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from service_process import ServiceProcess, wait_for

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's arenas: Linux only")

#: glibc's malloc, free and `malloc_info` (as text: `malloc_info()`) in a probe process.
LIBC = r"""
import ctypes, ctypes.util, os, tempfile
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.malloc.restype = ctypes.c_void_p
libc.malloc.argtypes = [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
libc.fopen.restype = ctypes.c_void_p
libc.fopen.argtypes = [ctypes.c_char_p, ctypes.c_char_p]
libc.malloc_info.argtypes = [ctypes.c_int, ctypes.c_void_p]
libc.fclose.argtypes = [ctypes.c_void_p]
def malloc_info():
    path = tempfile.mktemp()
    f = libc.fopen(path.encode(), b"w")
    libc.malloc_info(0, f)
    libc.fclose(f)
    info = open(path).read()
    os.unlink(path)
    return info
"""

#: A process that (maybe) limits its arenas, then has 12 threads each allocate with glibc's malloc
#: while all are alive (a thread's first malloc takes an arena of its own while under the limit),
#: and prints what `limit_malloc_arenas` returned and the arenas `malloc_info` lists.
PROBE = r"""
import json, sys, threading
from fleetmap.malloc_arenas import limit_malloc_arenas
limited = limit_malloc_arenas() if sys.argv[1] == "limit" else None
barrier = threading.Barrier(12)
def allocate():
    blocks = [libc.malloc(1000) for _ in range(100)]
    barrier.wait()  # every thread holds its blocks (and its arena) until all have allocated
    for block in blocks:
        libc.free(block)
threads = [threading.Thread(target=allocate) for _ in range(12)]
for t in threads:
    t.start()
for t in threads:
    t.join()
print(json.dumps({"limited": limited, "arenas": malloc_info().count("<heap nr=")}))
"""


def probe(
    mode: str, env_extra: dict[str, str] | None = None, script: str = PROBE, unset: str = "MALLOC_ARENA_MAX"
) -> dict[str, object]:
    """What a probe `script` (after LIBC) prints last, run with `mode`, without `unset` in its
    environment unless `env_extra` sets it."""
    env = {k: v for k, v in os.environ.items() if k != unset} | (env_extra or {})
    service_dir = str(Path(__file__).resolve().parents[1] / "service")
    env["PYTHONPATH"] = os.pathsep.join([service_dir, env.get("PYTHONPATH", "")])
    out = subprocess.run(
        [sys.executable, "-c", LIBC + script, mode], env=env, capture_output=True, text=True, timeout=60,
        check=True,
    ).stdout  # fmt: skip
    return json.loads(out.strip().splitlines()[-1])


def test_limiting_leaves_two_arenas_where_threads_took_one_each() -> None:
    free = probe("free")
    limited = probe("limit")
    assert free["arenas"] > 2, f"without the limit the 12 threads should have taken several arenas: {free}"
    assert limited == {"limited": True, "arenas": 2}, limited


def test_malloc_arena_max_in_the_environment_wins() -> None:
    """An operator's `MALLOC_ARENA_MAX` stands: the service does not override it."""
    got = probe("limit", {"MALLOC_ARENA_MAX": "4"})
    assert got["limited"] is False
    assert got["arenas"] == 4, got


def test_the_service_limits_its_arenas_at_start(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The real service process makes the calls before its threads exist (its log says so at debug)."""
    monkeypatch.delenv("MALLOC_ARENA_MAX", raising=False)
    monkeypatch.delenv("MALLOC_MMAP_THRESHOLD_", raising=False)
    with ServiceProcess(tmp_path, ["--in-memory", "--log-level", "debug"]) as service:
        wait_for(lambda: "malloc arenas limited to 2" in service.logs(), 10, 0.1, "the arena line")
        assert "malloc mmap threshold fixed at 1 MiB" in service.logs()


#: A process that (maybe) fixes its mmap threshold, frees a mapped block of 20 MiB (which raises
#: glibc's threshold past 2 MiB unless it is fixed), then holds a block of 2 MiB and prints what
#: `fix_mmap_threshold` returned and how many more blocks `malloc_info` counts as mapped with it
#: held (1: the 2 MiB one; 0: it came from the heap).
MMAP_PROBE = r"""
import json, sys
from fleetmap.malloc_arenas import fix_mmap_threshold
fixed = fix_mmap_threshold() if sys.argv[1] == "fix" else None
def mapped():
    return int(malloc_info().rsplit('<total type="mmap" count="', 1)[1].split('"', 1)[0])
libc.free(libc.malloc(20 << 20))
before = mapped()
block = libc.malloc(2 << 20)
print(json.dumps({"fixed": fixed, "mapped": mapped() - before}))
"""


def mmap_probe(mode: str, env_extra: dict[str, str] | None = None) -> dict[str, object]:
    return probe(mode, env_extra, MMAP_PROBE, "MALLOC_MMAP_THRESHOLD_")


def test_a_fixed_mmap_threshold_maps_blocks_glibc_would_take_from_the_heap() -> None:
    """Once a 20 MiB block was freed, glibc takes a 2 MiB one from the heap (its threshold moved up);
    with the service's fixed threshold it maps it, and gives it back to the system when freed. An
    operator's `MALLOC_MMAP_THRESHOLD_` stands."""
    assert mmap_probe("free") == {"fixed": None, "mapped": 0}
    assert mmap_probe("fix") == {"fixed": True, "mapped": 1}
    assert mmap_probe("fix", {"MALLOC_MMAP_THRESHOLD_": str(64 << 20)}) == {"fixed": False, "mapped": 0}
