"""numba's ``njit``, or a no-op stand-in when numba cannot be imported.

numba is a declared dependency; the stand-in keeps the numpy reference paths importable (and the
kernels runnable, slowly, as plain Python) in environments without it. Kernel modules import
``njit`` and ``NUMBA_AVAILABLE`` from here.
"""
from __future__ import annotations

__all__ = ["NUMBA_AVAILABLE", "njit"]

try:
    from numba import njit
    NUMBA_AVAILABLE = True
except ImportError:  # pragma: no cover - exercised only in environments without numba
    NUMBA_AVAILABLE = False

    def njit(*args, **kwargs):
        def wrap(function):
            return function
        return wrap
