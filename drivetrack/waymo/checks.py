"""Numeric validation of the columns read from a Waymo v2 component (issue 13 item 7).

:func:`check_content` runs on every table :class:`drivetrack.waymo.components.ComponentFile`
reads: transforms finite and rigid (:data:`RIGID_TOLERANCE`), no inf in number columns, finite
lists of numbers, range images whose shape matches their values. Errors are the file's
:class:`drivetrack.waymo.components.WaymoFormatError` (``f.error``), naming the row's keys.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from drivetrack.geometry import matrix_from_flat
from drivetrack.waymo.columns import fixed_numpy, list_parts, scalar_numpy, valid_mask

__all__ = ["RIGID_TOLERANCE", "check_content"]

#: A transform is rigid when max |R^T R - I| <= RIGID_TOLERANCE, det(R) > 0 and its last row is
#: [0, 0, 0, 1] within RIGID_TOLERANCE. Transforms written as float64 from a float32 rotation are
#: orthonormal to ~1e-7; a scaled or sheared rotation is off by far more.
RIGID_TOLERANCE = 1e-6



def check_content(f, table: pa.Table) -> None:
    """Bad numbers in the columns read: NaN or inf in a transform, a transform that is not
    rigid (:data:`RIGID_TOLERANCE`), inf in a number column, NaN or inf in a list of numbers
    that is no range image, and empty range images or shape/values mismatches.

    NaN in a number column is a missing value (like null): the code that uses the column
    decides. Range-image values are data (a non-finite range is no return, dropped and
    counted by the lidar reader); per-pixel poses are checked where they are used.
    """
    for name in table.column_names:
        col_type = f.comp.by_name[name].type
        if name.endswith(".transform"):
            _check_transforms(f, table, name)
        elif name.endswith(".values") and pa.types.is_list(col_type) \
                and name[: -len(".values")] + ".shape" in f.comp.by_name:
            shape_name = name[: -len(".values")] + ".shape"
            if shape_name in table.column_names:
                _check_range_image(f, table, name, shape_name)
        elif pa.types.is_floating(col_type):
            values = scalar_numpy(table[name], np.float64, np.nan)
            bad = np.flatnonzero(np.isinf(values))
            if bad.size:
                i = int(bad[0])
                raise f.error("infinite value", column=name, expected="a finite number or null",
                                 found=f"{values[i]} at {f.row_keys(table, i)}")
        elif (pa.types.is_list(col_type) or pa.types.is_large_list(col_type)) \
                and pa.types.is_floating(col_type.value_type):
            offsets, flat, valid = list_parts(table[name])
            bad = np.flatnonzero(~np.isfinite(np.asarray(flat, np.float64)))
            if bad.size:
                i = int(np.searchsorted(offsets, bad[0], "right") - 1)
                raise f.error("NaN or infinite value in a list of numbers", column=name,
                                 expected="finite numbers",
                                 found=f"{flat[bad[0]]} at {f.row_keys(table, i)}")

def _check_transforms(f, table: pa.Table, name: str) -> None:
    """Every non-null row of a 4x4 transform column is finite and rigid (vectorised)."""
    flat, valid = fixed_numpy(table[name], 16)
    nan = np.isnan(flat).any(axis=1) & valid
    if nan.any():
        i = int(np.flatnonzero(nan)[0])
        raise f.error("NaN in a transform", column=name, expected="16 finite values",
                         found=f"{flat[i].tolist()} at {f.row_keys(table, i)}")
    inf = np.isinf(flat).any(axis=1) & valid
    if inf.any():
        i = int(np.flatnonzero(inf)[0])
        raise f.error("infinite value in a transform", column=name,
                         expected="16 finite values",
                         found=f"{flat[i].tolist()} at {f.row_keys(table, i)}")
    rows = np.flatnonzero(valid)
    if not rows.size:
        return
    dst_from_src = matrix_from_flat(flat[rows])                              # [N, 4, 4]
    rotation = dst_from_src[:, :3, :3]
    orthonormal_error = np.abs(np.einsum("nji,njk->nik", rotation, rotation)
                               - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(rotation)
    last_row_error = np.abs(dst_from_src[:, 3, :] - [0.0, 0.0, 0.0, 1.0]).max(axis=1)
    bad = (orthonormal_error > RIGID_TOLERANCE) | (det <= 0) | (last_row_error > RIGID_TOLERANCE)
    if bad.any():
        j = int(np.flatnonzero(bad)[0])
        i = int(rows[j])
        raise f.error(
            "transform is not rigid", column=name,
            expected=f"a rotation with max |R^T R - I| <= {RIGID_TOLERANCE:g}, det(R) > 0 and "
                     f"last row [0, 0, 0, 1]",
            found=f"max |R^T R - I| = {orthonormal_error[j]:.3g}, det(R) = {det[j]:.6g}, last "
                  f"row {dst_from_src[j, 3].tolist()} at {f.row_keys(table, i)}")

def _check_range_image(f, table: pa.Table, values_name: str, shape_name: str) -> None:
    values = table[values_name]
    has_values = valid_mask(values)
    lengths = pc.fill_null(pc.list_value_length(values), 0).to_numpy().astype(np.int64)
    shape, _ = fixed_numpy(table[shape_name], 3)
    has_shape = ~np.isnan(shape).any(axis=1)
    expected = np.where(has_shape, np.prod(np.nan_to_num(shape, nan=-1), axis=1), -1)
    empty = has_values & (lengths == 0)
    if empty.any():
        i = int(np.flatnonzero(empty)[0])
        raise f.error("empty range image", column=values_name,
                         expected="H*W*C > 0 values",
                         found=f"0 values with shape {shape[i].tolist()} at "
                               f"{f.row_keys(table, i)}")
    mismatch = (has_values | has_shape) & ((expected != lengths) | (shape < 1).any(axis=1))
    if mismatch.any():
        i = int(np.flatnonzero(mismatch)[0])
        raise f.error("range image shape does not match its values", column=shape_name,
                         expected=f"H*W*C = {int(lengths[i])} values" if has_values[i] else
                         "no shape for a null range image",
                         found=f"shape {shape[i].tolist()} at {f.row_keys(table, i)}")

