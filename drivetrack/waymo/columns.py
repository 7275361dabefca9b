"""Arrow columns of Waymo v2 components as numpy arrays, in bulk (no per-row Python loops
except over range-image rows, which are views).

Used by :mod:`drivetrack.waymo.components` (content checks), :mod:`drivetrack.waymo.reader`
(scene assembly) and :mod:`drivetrack.waymo.summary`. Nulls become NaN (or a given fill value).
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from drivetrack.geometry import matrix_from_flat

__all__ = ["as_array", "valid_mask", "fixed_numpy", "scalar_numpy", "list_parts",
           "transforms_from_column", "range_images_from_columns"]


def as_array(column) -> pa.Array:
    if isinstance(column, pa.ChunkedArray):
        if column.num_chunks == 1:
            return column.chunk(0)
        return column.combine_chunks() if column.num_chunks else pa.array([], column.type)
    return column


def valid_mask(column) -> np.ndarray:
    """bool [N], True where the row is not null."""
    arr = as_array(column)
    if arr.null_count == 0:
        return np.ones(len(arr), dtype=bool)
    return pc.is_valid(arr).to_numpy(zero_copy_only=False)


def fixed_numpy(column, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(float64 [N, size] with NaN for nulls, bool [N] row valid) of a fixed_size_list column."""
    arr = as_array(column)
    n = len(arr)
    if n == 0:
        return np.zeros((0, size)), np.zeros(0, dtype=bool)
    child = arr.values.slice(arr.offset * size, n * size)
    flat = child.to_numpy(zero_copy_only=False).astype(np.float64, copy=False).reshape(n, size)
    valid = valid_mask(arr)
    if not valid.all():
        flat = flat.copy()
        flat[~valid] = np.nan
    return flat, valid


def scalar_numpy(column, dtype, fill) -> np.ndarray:
    arr = as_array(column)
    if arr.null_count:
        arr = pc.fill_null(arr, fill)
    return arr.to_numpy(zero_copy_only=False).astype(dtype, copy=False)


def list_parts(column) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(offsets int64 [N + 1], flat values, valid bool [N]) of a list / large_list column."""
    arr = as_array(column)
    offsets = arr.offsets.to_numpy().astype(np.int64, copy=False)
    values = arr.values.to_numpy(zero_copy_only=False)
    return offsets, values, valid_mask(arr)


def transforms_from_column(column) -> np.ndarray:
    """float64 [N, 4, 4] from a ``fixed_size_list<double>[16]`` column (row-major); NaN for nulls."""
    flat, _ = fixed_numpy(column, 16)
    return matrix_from_flat(flat)


def range_images_from_columns(values, shape) -> list[np.ndarray | None]:
    """Per row, a read-only view float/int [H, W, C] of a range image, or None for a null row.

    Args:
        values: ``list<float>`` (or int32) column, row-major ``[H, W, C]`` (channel innermost).
        shape: ``fixed_size_list<int32>[3]`` column.
    The views share the column's memory (no copy, no per-pixel loop). Shapes are trusted: check
    them first (:func:`read_component` does).
    """
    offsets, flat, valid = list_parts(values)
    dims, has_shape = fixed_numpy(shape, 3)
    out: list[np.ndarray | None] = []
    for i in range(len(valid)):
        if not (valid[i] and has_shape[i]):
            out.append(None)
            continue
        h, w, c = (int(d) for d in dims[i])
        view = flat[offsets[i]: offsets[i + 1]].reshape(h, w, c)
        view.flags.writeable = False
        out.append(view)
    return out

