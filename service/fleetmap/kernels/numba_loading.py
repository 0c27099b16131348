"""numba's array functions loaded without its BLAS probe, which costs every process 0.17 s.

numba loads its NumPy implementations (`numba.np.arraymath`) when a process first compiles or loads
a kernel, and that module asks, once, whether SciPy's BLAS can be imported: `import
scipy.linalg.cython_blas`, which imports all of `scipy.linalg`. fleetmap's kernels use no BLAS
(no `np.dot`, no `np.linalg`), and the answer only decides whether a compiled `np.dot` of two vectors
calls BLAS or numba's own loop. A service start took 1.4 s of CPU, 0.17 s of it this import, and
the tests start some 600 such processes.
"""

from __future__ import annotations

import sys


def load_numba_array_functions() -> None:
    """Import `numba.np.arraymath` with SciPy's BLAS module hidden for that import only, unless
    numba has loaded it already or SciPy's linear algebra is loaded anyway (then the probe is free).
    Later imports of SciPy, and numba's `np.linalg` (which checks for BLAS when it compiles), are
    not affected."""
    if "numba.np.arraymath" in sys.modules or "scipy.linalg" in sys.modules:
        return
    hidden = "scipy.linalg.cython_blas"
    sys.modules[hidden] = None  # type: ignore[assignment]  # None: "import" raises ImportError
    try:
        import numba.np.arraymath  # noqa: F401
    finally:
        del sys.modules[hidden]
