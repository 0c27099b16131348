"""Compiled hot loops (numba `njit`, `nogil`) over plain arrays.

Coordinates here are in CELL units (metres / resolution), so cell (i, j) is the unit square
`[i, i+1) x [j, j+1)`. The Python modules around these kernels own the tile bookkeeping; the kernels
own nothing and keep no state.
"""
