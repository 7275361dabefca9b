"""Write Waymo v2 component tables: ``{root}/{split}/{component}/{segment}.parquet`` via fsspec.

The writer is the mirror of the reader: every column of the component is present (missing ones
are filled with nulls of the official type), columns are in the official order with the official
arrow types (from :mod:`drivetrack.waymo.schema`), and files are BROTLI-compressed like the real
release. Tables with unknown or mistyped columns, or rows of another segment, are refused with an
error naming the component, the column and what was found.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from drivetrack.waymo.schema import KEY_SEGMENT, Component, component as _component, types_compatible

__all__ = ["component_url", "build_table", "write_component", "list_array", "fixed_list_array"]

#: BROTLI level used by default: level 3 writes float range images ~5x faster than level 5 for
#: ~5 % more bytes (the official release does not document its level; readers ignore it).
DEFAULT_BROTLI_LEVEL = 3


def component_url(root: str, split: str, component: str, segment: str) -> str:
    """``{root}/{split}/{component}/{segment}.parquet`` (``root`` a local path or fsspec URL)."""
    return f"{str(root).rstrip('/')}/{split}/{component}/{segment}.parquet"


_NUMPY_TYPES = {"float": np.float32, "double": np.float64, "int8": np.int8, "int32": np.int32,
                "int64": np.int64, "bool": np.bool_}


def list_array(rows: Sequence[np.ndarray | None], value_type: pa.DataType) -> pa.Array:
    """``list<value_type>`` array from per-row 1-D numpy arrays (``None`` = null row), no copies
    through Python objects: one offsets array plus one flat values array."""
    n = len(rows)
    lengths = np.array([0 if r is None else np.asarray(r).size for r in rows], dtype=np.int64)
    offsets = np.zeros(n + 1, dtype=np.int32)
    np.cumsum(lengths, out=offsets[1:])
    present = [np.asarray(r).ravel() for r in rows if r is not None]
    np_type = _NUMPY_TYPES[str(value_type)]
    flat = (np.concatenate(present).astype(np_type, copy=False) if present
            else np.zeros(0, dtype=np_type))
    mask = pa.array([r is None for r in rows], type=pa.bool_())
    return pa.ListArray.from_arrays(pa.array(offsets, type=pa.int32()),
                                    pa.array(flat, type=value_type), mask=mask)


def fixed_list_array(values: np.ndarray, list_type: pa.DataType) -> pa.Array:
    """``fixed_size_list`` array from a numpy array ``[n, list_size]``."""
    values = np.asarray(values)
    size = list_type.list_size
    if values.ndim != 2 or values.shape[1] != size:
        raise ValueError(f"expected values of shape [n, {size}], got {values.shape}")
    flat = pa.array(values.reshape(-1).astype(_NUMPY_TYPES[str(list_type.value_type)], copy=False),
                    type=list_type.value_type)
    return pa.FixedSizeListArray.from_arrays(flat, size)


def _as_array(comp: Component, name: str, values, expected: pa.DataType) -> pa.Array:
    if isinstance(values, pa.ChunkedArray):
        values = values.combine_chunks()
    if isinstance(values, pa.Array):
        if not types_compatible(expected, values.type):
            raise TypeError(f"component {comp.name!r}: column {name!r} has arrow type "
                            f"{values.type}, expected {expected}")
        return values.cast(expected) if not values.type.equals(expected) else values
    if pa.types.is_fixed_size_list(expected) and isinstance(values, np.ndarray):
        return fixed_list_array(values, expected)
    try:
        return pa.array(values, type=expected)
    except (pa.ArrowInvalid, pa.ArrowTypeError, TypeError, ValueError) as exc:
        raise TypeError(f"component {comp.name!r}: column {name!r} cannot be converted to "
                        f"{expected}: {exc}") from exc


def _nulls(comp: Component, name: str, n: int, type_: pa.DataType) -> pa.Array:
    if pa.types.is_fixed_size_list(type_) and n:
        raise ValueError(
            f"component {comp.name!r}: column {name!r} ({type_}) is missing; null fixed-size "
            f"lists cannot be read back from parquet by pyarrow, so give its values")
    return pa.nulls(n, type=type_)


def build_table(component: str | Component, columns: Mapping[str, object] | pa.Table) -> pa.Table:
    """A table with exactly the official columns, order and types of ``component``.

    Args:
        component: a component name (``"lidar_box"``) or :class:`Component`.
        columns: a ``pa.Table`` or a mapping column name -> values (pyarrow array, numpy array,
            or list). Columns the component has but ``columns`` lacks become all-null, except
            fixed-size lists (transforms, shapes): pyarrow cannot read null fixed-size lists
            back from parquet, so those must be given, without nulls.
    Raises:
        KeyError: an unknown column (named, with the component).
        TypeError: a column whose type is not the official one (named, expected and found).
        ValueError: columns of different lengths; a missing or null fixed-size-list column.
    """
    comp = component if isinstance(component, Component) else _component(component)
    if isinstance(columns, pa.Table):
        columns = {name: columns.column(name) for name in columns.column_names}
    known = comp.by_name
    unknown = [name for name in columns if name not in known]
    if unknown:
        raise KeyError(f"component {comp.name!r} has no column(s) {unknown}; "
                       f"expected names like {comp.columns[0].name!r}")
    arrays = {name: _as_array(comp, name, values, known[name].type) for name, values in columns.items()}
    lengths = {len(a) for a in arrays.values()}
    if len(lengths) > 1:
        raise ValueError(f"component {comp.name!r}: columns have different lengths "
                         f"{ {n: len(a) for n, a in arrays.items()} }")
    n = lengths.pop() if lengths else 0
    for name, arr in arrays.items():
        if pa.types.is_fixed_size_list(arr.type) and arr.null_count:
            raise ValueError(f"component {comp.name!r}: column {name!r} has {arr.null_count} null "
                             f"row(s); null fixed-size lists cannot be read back from parquet")
    full = [arrays[c.name] if c.name in arrays else _nulls(comp, c.name, n, c.type)
            for c in comp.columns]
    return pa.Table.from_arrays(full, schema=comp.arrow_schema())


def write_component(columns: Mapping[str, object] | pa.Table, root: str, split: str,
                    component: str, segment: str, *, compression_level: int | None = DEFAULT_BROTLI_LEVEL,
                    storage_options: dict | None = None) -> str:
    """Write one component table of one segment; returns the URL written.

    The file goes to ``{root}/{split}/{component}/{segment}.parquet`` through fsspec (parents are
    created), BROTLI-compressed. Every row's ``key.segment_context_name`` must equal ``segment``.
    """
    import fsspec

    comp = _component(component)
    table = build_table(comp, columns)
    seg_col = table.column(KEY_SEGMENT)
    if seg_col.null_count:
        raise ValueError(f"component {comp.name!r}, segment {segment!r}: {KEY_SEGMENT} has "
                         f"{seg_col.null_count} null value(s)")
    found = set(seg_col.to_pylist())
    if found - {segment}:
        raise ValueError(f"component {comp.name!r}: rows of segment(s) {sorted(found - {segment})} "
                         f"in the file of segment {segment!r}")
    url = component_url(root, split, comp.name, segment)
    fs, path = fsspec.core.url_to_fs(url, **(storage_options or {}))
    fs.makedirs(path.rsplit("/", 1)[0], exist_ok=True)
    with fs.open(path, "wb") as f:
        pq.write_table(table, f, compression="BROTLI", compression_level=compression_level)
    return url
