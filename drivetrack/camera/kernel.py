"""numba forms of the camera model for the fused kernels (track stage, sparse depth maps).

:func:`camera_parameters` packs a :class:`~drivetrack.camera.model.CameraModel` into one float64
array; :func:`pixel_from_camera_point` projects one camera-frame point exactly as
:meth:`CameraModel.pixels_from_camera` does (same float64 operations in the same order, so
kernels and the numpy reference agree bit for bit). Compiled on first use and cached on disk.
"""
from __future__ import annotations

import numpy as np

from drivetrack.camera.model import MAX_TRUSTED_DISTORTION, MIN_TRUSTED_DISTORTION
from drivetrack.numba_compat import njit

__all__ = ["camera_parameters", "pixel_from_camera_point"]


def camera_parameters(model) -> np.ndarray:
    """float64 [11]: (f_u, f_v, c_u, c_v, k1, k2, k3, p1, p2, width, height) of a CameraModel."""
    return np.array([model.f_u, model.f_v, model.c_u, model.c_v, model.k1, model.k2, model.k3,
                     model.p1, model.p2, model.width, model.height], dtype=np.float64)


@njit(cache=True, nogil=True, inline="always")
def pixel_from_camera_point(x, y, z, f_u, f_v, c_u, c_v, k1, k2, k3, p1, p2):
    """(pixel x, pixel y, valid) of camera-frame point (x, y, z) metres, as
    ``CameraModel.pixels_from_camera``: valid iff x > 1e-6 and the distortion factor is trusted;
    NaN pixels when not valid."""
    if not x > 1e-6:
        return np.nan, np.nan, False
    u = -y / x
    v = -z / x
    r2 = u * u + v * v
    d = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    if not (d >= MIN_TRUSTED_DISTORTION and d <= MAX_TRUSTED_DISTORTION):
        return np.nan, np.nan, False
    u_d = u * d + 2.0 * p1 * u * v + p2 * (r2 + 2.0 * u * u)
    v_d = v * d + p1 * (r2 + 2.0 * v * v) + 2.0 * p2 * u * v
    return f_u * u_d + c_u, f_v * v_d + c_v, True
