"""Solve of the symmetric positive definite normal equations, with BLAS held to one thread."""
from __future__ import annotations

import numpy as np


_BLAS_CONTROLLER = None


def _single_threaded_blas():
    """A context in which BLAS/LAPACK run on one thread (threadpoolctl; the controller, which
    inspects the loaded libraries, is built once)."""
    global _BLAS_CONTROLLER
    from threadpoolctl import ThreadpoolController

    if _BLAS_CONTROLLER is None:
        _BLAS_CONTROLLER = ThreadpoolController()
    return _BLAS_CONTROLLER.limit(limits=1, user_api="blas")


def _solve_spd(hessian: np.ndarray, rhs: np.ndarray, use_kernel: bool) -> np.ndarray:
    """float64 [n]: ``hessian^-1 rhs`` for the symmetric positive definite normal equations; all NaN
    when the factorisation fails.

    Short clips give dense matrices (every frame pairs with every other): LAPACK's Cholesky on
    one thread (240 unknowns: 0.6 ms; threaded, its CPU cost was 10-25x that on the loaded 2-core
    machine). Long clips give matrices whose rows are zero left of their first coupled frame:
    with the numba kernels, the envelope Cholesky of ``drivetrack.refine.kernel.cholesky_solve`` when the
    envelope holds less than half the lower triangle (1200 unknowns, band 160: 20 ms vs LAPACK's
    39 ms)."""
    n = hessian.shape[0]
    if use_kernel and n > 1:
        first = np.argmax(hessian != 0.0, axis=1)               # first non-zero of each row (<= i)
        envelope = float(np.sum(np.arange(n) - first + 1))
        if envelope < 0.5 * n * (n + 1) / 2:
            from drivetrack.refine import kernel

            return kernel.cholesky_solve(hessian, rhs)
    import scipy.linalg

    with _single_threaded_blas():
        try:
            return scipy.linalg.cho_solve(scipy.linalg.cho_factor(hessian, lower=True, check_finite=False), rhs,
                                          check_finite=False)
        except (np.linalg.LinAlgError, ValueError):
            return np.full(rhs.shape, np.nan)
