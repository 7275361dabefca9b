"""numba kernel of the back-face normals (:func:`drivetrack.visibility.facing.cloud_normals`).

Shapes: m cloud points, k neighbours; metres, box frame.
"""
from __future__ import annotations

import numpy as np

from drivetrack.numba_compat import njit

__all__ = ["shifted_neighbourhoods"]


@njit(cache=True, nogil=True)
def _shifted_kernel(cloud, index, normal, centroid, eigen, tolerance_m, sigmas, min_cos, choice):
    m, k = index.shape
    for i in range(m):
        best, best_variation = index[i, 0], np.inf
        for a in range(k):
            j = index[i, a]
            if a > 0:
                # its plane must pass through the point, within the tolerance ...
                off = abs(normal[j, 0] * (cloud[i, 0] - centroid[j, 0]) + normal[j, 1] * (cloud[i, 1] - centroid[j, 1])
                          + normal[j, 2] * (cloud[i, 2] - centroid[j, 2]))
                if off > max(tolerance_m, sigmas * np.sqrt(max(eigen[j, 0], 0.0))):
                    continue
                # ... and lean the way the point's own neighbourhood does
                cos = normal[j, 0] * normal[i, 0] + normal[j, 1] * normal[i, 1] + normal[j, 2] * normal[i, 2]
                if abs(cos) < min_cos:
                    continue
            variation = eigen[j, 0] / max(eigen[j, 0] + eigen[j, 1] + eigen[j, 2], 1e-300)
            if variation < best_variation:
                best, best_variation = j, variation
        choice[i] = best


def shifted_neighbourhoods(cloud: np.ndarray, index: np.ndarray, normal: np.ndarray, centroid: np.ndarray,
                           eigen: np.ndarray, tolerance_m: float, sigmas: float, max_tilt_deg: float) -> np.ndarray:
    """int64 [m]: for each point of ``cloud`` float64 [m, 3] the neighbour (an index into
    ``cloud``) whose neighbourhood's plane to take (see
    :func:`drivetrack.visibility.facing.cloud_normals`).

    ``index`` int [m, k]: each point's k nearest (itself first); ``normal``, ``centroid`` float64
    [m, 3] and ``eigen`` float64 [m, 3] (ascending, square metres): each neighbourhood's plane
    (``drivetrack.refine.kernel.plane_fits``). Among the neighbourhoods of a point's neighbours,
    its own always and the others when their plane passes within ``max(tolerance_m, sigmas *
    sqrt(l1))`` of the point and their normal lies within ``max_tilt_deg`` of the point's own
    neighbourhood's (either sign), the flattest (smallest ``l1 / (l1 + l2 + l3)``) wins.
    """
    choice = np.empty(cloud.shape[0], dtype=np.int64)
    _shifted_kernel(np.ascontiguousarray(cloud, dtype=np.float64), np.ascontiguousarray(index, dtype=np.int64),
                    np.ascontiguousarray(normal, dtype=np.float64), np.ascontiguousarray(centroid, dtype=np.float64),
                    np.ascontiguousarray(eigen, dtype=np.float64), float(tolerance_m), float(sigmas),
                    float(np.cos(np.radians(max_tilt_deg))), choice)
    return choice
