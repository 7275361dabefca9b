"""Read Waymo Open Dataset v2 (perception, parquet) without TensorFlow.

Layout: ``{root}/{split}/{component}/{segment}.parquet``, reached through fsspec, so ``root`` may
be a local path, ``file://``, ``s3://`` (s3fs) or ``gs://`` (gcsfs, when installed). Pass
credentials and endpoints in ``storage_options`` (e.g. ``{"endpoint_url": ..., "key": ...}``).

Three layers:

- :func:`read_component` reads one component file: only the requested columns (plus the key
  columns), each validated against the official type (:func:`schema.types_compatible`), rows
  filtered to the segment, content checked (NaN in transforms, range-image shapes, duplicate
  keys). Every problem raises :class:`WaymoFormatError` naming the file URL, segment, component,
  column, and the expected and found value.
- Decoders turn arrow columns into numpy in bulk: :func:`transforms_from_column`,
  :func:`range_images_from_columns`, :func:`lidar_points`, :func:`camera_projection_at`.
- :func:`load_scene` joins the components on their key columns (never on row order) into a
  :class:`drivetrack.scene.Scene`.

Column names come from :mod:`drivetrack.waymo.schema` only.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Iterator, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from drivetrack.geometry import (CameraModel, invert_rigid, matrix_from_flat, rotation_from_rpy,
                                 transform_points)
from drivetrack.names import InvalidNameError, check_name
from drivetrack.scene import Boxes, CameraFrames, LidarReturns, Scene
from drivetrack.waymo import lidar as beam
from drivetrack.waymo import capture_time
from drivetrack.waymo.schema import (COMPONENTS, KEY_SEGMENT, KEY_TIMESTAMP, LaserName,
                                     component as get_component, types_compatible)

__all__ = [
    "WaymoFormatError", "component_url", "list_segments", "read_component",
    "transforms_from_column", "range_images_from_columns", "lidar_points", "camera_projection_at",
    "load_scene", "segment_summary",
]

#: A transform is rigid when max |R^T R - I| <= RIGID_TOLERANCE, det(R) > 0 and its last row is
#: [0, 0, 0, 1] within RIGID_TOLERANCE. Transforms written as float64 from a float32 rotation are
#: orthonormal to ~1e-7; a scaled or sheared rotation is off by far more.
RIGID_TOLERANCE = 1e-6

#: Rows decoded at once when streaming range-image components (bounds memory: one TOP row of
#: both returns is about 5 MB of float32).
LIDAR_BATCH_ROWS = 16


class WaymoFormatError(ValueError):
    """A Waymo v2 file does not match the official format.

    Attributes ``url``, ``segment``, ``component``, ``column``, ``expected``, ``found`` hold the
    details the message spells out.
    """

    def __init__(self, problem: str, *, url: str, segment: str, component: str, column,
                 expected=None, found=None):
        self.problem, self.url, self.segment, self.component = problem, url, segment, component
        self.column, self.expected, self.found = column, expected, found
        where = f"file {url}, segment {segment!r}, component {component!r}, column {column!r}"
        detail = ""
        if expected is not None or found is not None:
            detail = f"; expected {expected}, found {found}"
        super().__init__(f"{problem} ({where}{detail})")


# --------------------------------------------------------------------------------------------
# Storage


def _filesystem(root: str, storage_options: dict | None):
    import fsspec.core

    fs, path = fsspec.core.url_to_fs(str(root), **(storage_options or {}))
    return fs, path.rstrip("/")


def _url(fs, path: str) -> str:
    return fs.unstrip_protocol(path) if "://" not in path else path


def _check_names(split: str, segment: str | None = None) -> None:
    """Refuse split and segment names that cannot be part of a path (before any path is built)."""
    check_name("split", split, "the split argument")
    if segment is not None:
        check_name("segment", segment, f"split {split!r}")


def component_url(root: str, split: str, component: str, segment: str,
                  storage_options: dict | None = None) -> str:
    """Full URL of ``{root}/{split}/{component}/{segment}.parquet``."""
    _check_names(split, segment)
    fs, base = _filesystem(root, storage_options)
    return _url(fs, f"{base}/{split}/{component}/{segment}.parquet")


def list_segments(root: str, split: str, storage_options: dict | None = None) -> list[str]:
    """Sorted segment names present in any known component directory of ``split``.

    Raises FileNotFoundError naming the URL when the split directory does not exist, and
    :class:`drivetrack.names.InvalidNameError` naming the file when a file name is no valid
    segment id (it would become part of output paths). Files starting with ``.`` are skipped.
    """
    _check_names(split)
    fs, base = _filesystem(root, storage_options)
    split_path = f"{base}/{split}"
    if not fs.isdir(split_path):
        raise FileNotFoundError(f"no split directory {_url(fs, split_path)}")
    segments: set[str] = set()
    for name in COMPONENTS:
        comp_path = f"{split_path}/{name}"
        if not fs.isdir(comp_path):
            continue
        for entry in fs.ls(comp_path, detail=False):
            leaf = entry.rstrip("/").rsplit("/", 1)[-1]
            if leaf.endswith(".parquet") and not leaf.startswith("."):
                segments.add(check_name("segment", leaf[: -len(".parquet")],
                                        f"file {_url(fs, comp_path + '/' + leaf)}"))
    return sorted(segments)


class _ComponentFile:
    """One opened, schema-checked component file of one segment."""

    def __init__(self, fs, base: str, split: str, component: str, segment: str):
        _check_names(split, segment)
        self.comp = get_component(component)
        self.segment = segment
        self.path = f"{base}/{split}/{component}/{segment}.parquet"
        self.url = _url(fs, self.path)
        try:
            self._handle = fs.open(self.path, "rb")
        except FileNotFoundError:
            raise self.error("missing component file", column=list(self.comp.keys),
                             expected="a parquet file", found="no such file") from None
        try:
            self.parquet = pq.ParquetFile(self._handle)
            self.schema = self.parquet.schema_arrow
        except (pa.ArrowException, OSError) as exc:
            self.close()
            raise self.error("truncated or corrupt parquet file", column="(file footer)",
                             expected="a readable parquet file", found=str(exc)) from None

    def close(self):
        self._handle.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def error(self, problem: str, column, expected=None, found=None) -> WaymoFormatError:
        return WaymoFormatError(problem, url=self.url, segment=self.segment,
                                component=self.comp.name, column=column, expected=expected,
                                found=found)

    def columns(self, wanted: Sequence[str] | None) -> list[str]:
        """Key columns + ``wanted`` (default: every official column), validated."""
        names = list(self.comp.keys)
        for name in (wanted if wanted is not None else [c.name for c in self.comp.columns]):
            if name not in names:
                names.append(name)
        official = self.comp.by_name
        for name in names:
            if name not in official:
                raise self.error("not a column of the official schema", column=name,
                                 expected=f"one of {sorted(official)}", found=name)
            idx = self.schema.get_field_index(name)
            if idx < 0:
                raise self.error("missing column", column=name, expected=str(official[name].type),
                                 found="no such column")
            found = self.schema.field(idx).type
            if not types_compatible(official[name].type, found):
                raise self.error("wrong column type", column=name,
                                 expected=str(official[name].type), found=str(found))
        return names

    def read_keys(self) -> pa.Table:
        """The key columns of this segment's rows; checks presence and uniqueness."""
        keys = self.columns([])
        table = self._read(keys)
        table = self._filter(table)
        if table.num_rows == 0:
            raise self.error("segment absent from the component file", column=KEY_SEGMENT,
                             expected=repr(self.segment), found="no rows with that value")
        self._check_unique(table)
        return table

    def _read(self, columns: list[str]) -> pa.Table:
        try:
            return self.parquet.read(columns=columns)
        except (pa.ArrowException, OSError) as exc:
            raise self._read_error(exc, columns) from None

    def _read_error(self, exc: Exception, columns: list[str]) -> WaymoFormatError:
        """Name the failing column where possible (pyarrow reads them all at once)."""
        if "Expected all lists to be of size" in str(exc):
            # apache/arrow#35692: pyarrow < 23 cannot read null rows of a fixed_size_list column.
            for name in columns:
                if pa.types.is_fixed_size_list(self.schema.field(name).type):
                    try:
                        self.parquet.read(columns=[name])
                    except pa.ArrowException:
                        return self.error(
                            "null rows in a fixed_size_list column (this pyarrow cannot read "
                            "them, apache/arrow#35692)", column=name,
                            expected=str(self.comp.by_name[name].type) + " without null rows",
                            found=str(exc))
        return self.error("truncated or corrupt parquet file", column=columns,
                          expected="readable column chunks", found=str(exc))

    def _filter(self, data):
        mask = pc.fill_null(pc.equal(data[KEY_SEGMENT], self.segment), False)
        if pc.all(mask).as_py() is not False and data.num_rows:
            return data  # the usual case: one segment per file; filtering would copy it all
        return data.filter(mask)

    def _check_unique(self, keys: pa.Table) -> None:
        names = list(self.comp.keys)
        counts = keys.select(names).group_by(names).aggregate([([], "count_all")])
        dup = counts.filter(pc.greater(counts["count_all"], 1))
        if dup.num_rows:
            first = {n: dup[n][0].as_py() for n in names}
            raise self.error("duplicate key", column=names, expected="unique keys",
                             found=f"{dup['count_all'][0].as_py()} rows with {first}")

    def iter_batches(self, columns: list[str], batch_rows: int) -> Iterator[pa.Table]:
        """Validated tables of at most ``batch_rows`` rows of this segment (columns checked)."""
        try:
            for batch in self.parquet.iter_batches(batch_size=batch_rows, columns=columns):
                table = self._filter(pa.Table.from_batches([batch]))
                if table.num_rows:
                    self.check_content(table)
                    yield table
        except (pa.ArrowException, OSError) as exc:
            raise self._read_error(exc, columns) from None

    def read(self, columns: list[str]) -> pa.Table:
        table = self._filter(self._read(columns))
        if table.num_rows == 0:
            raise self.error("segment absent from the component file", column=KEY_SEGMENT,
                             expected=repr(self.segment), found="no rows with that value")
        self._check_unique(table)
        self.check_content(table)
        return table

    def row_keys(self, table: pa.Table, i: int) -> dict:
        return {n: table[n][i].as_py() for n in self.comp.keys if n != KEY_SEGMENT}

    def check_content(self, table: pa.Table) -> None:
        """Bad numbers in the columns read: NaN or inf in a transform, a transform that is not
        rigid (:data:`RIGID_TOLERANCE`), inf in a number column, NaN or inf in a list of numbers
        that is no range image, and empty range images or shape/values mismatches.

        NaN in a number column is a missing value (like null): the code that uses the column
        decides. Range-image values are data (a non-finite range is no return, dropped and
        counted by the lidar reader); per-pixel poses are checked where they are used.
        """
        for name in table.column_names:
            col_type = self.comp.by_name[name].type
            if name.endswith(".transform"):
                self._check_transforms(table, name)
            elif name.endswith(".values") and pa.types.is_list(col_type) \
                    and name[: -len(".values")] + ".shape" in self.comp.by_name:
                shape_name = name[: -len(".values")] + ".shape"
                if shape_name in table.column_names:
                    self._check_range_image(table, name, shape_name)
            elif pa.types.is_floating(col_type):
                values = _scalar_numpy(table[name], np.float64, np.nan)
                bad = np.flatnonzero(np.isinf(values))
                if bad.size:
                    i = int(bad[0])
                    raise self.error("infinite value", column=name, expected="a finite number or null",
                                     found=f"{values[i]} at {self.row_keys(table, i)}")
            elif (pa.types.is_list(col_type) or pa.types.is_large_list(col_type)) \
                    and pa.types.is_floating(col_type.value_type):
                offsets, flat, valid = _list_parts(table[name])
                bad = np.flatnonzero(~np.isfinite(np.asarray(flat, np.float64)))
                if bad.size:
                    i = int(np.searchsorted(offsets, bad[0], "right") - 1)
                    raise self.error("NaN or infinite value in a list of numbers", column=name,
                                     expected="finite numbers",
                                     found=f"{flat[bad[0]]} at {self.row_keys(table, i)}")

    def _check_transforms(self, table: pa.Table, name: str) -> None:
        """Every non-null row of a 4x4 transform column is finite and rigid (vectorised)."""
        flat, valid = _fixed_numpy(table[name], 16)
        nan = np.isnan(flat).any(axis=1) & valid
        if nan.any():
            i = int(np.flatnonzero(nan)[0])
            raise self.error("NaN in a transform", column=name, expected="16 finite values",
                             found=f"{flat[i].tolist()} at {self.row_keys(table, i)}")
        inf = np.isinf(flat).any(axis=1) & valid
        if inf.any():
            i = int(np.flatnonzero(inf)[0])
            raise self.error("infinite value in a transform", column=name,
                             expected="16 finite values",
                             found=f"{flat[i].tolist()} at {self.row_keys(table, i)}")
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
            raise self.error(
                "transform is not rigid", column=name,
                expected=f"a rotation with max |R^T R - I| <= {RIGID_TOLERANCE:g}, det(R) > 0 and "
                         f"last row [0, 0, 0, 1]",
                found=f"max |R^T R - I| = {orthonormal_error[j]:.3g}, det(R) = {det[j]:.6g}, last "
                      f"row {dst_from_src[j, 3].tolist()} at {self.row_keys(table, i)}")

    def _check_range_image(self, table: pa.Table, values_name: str, shape_name: str) -> None:
        values = table[values_name]
        has_values = _valid_mask(values)
        lengths = pc.fill_null(pc.list_value_length(values), 0).to_numpy().astype(np.int64)
        shape, _ = _fixed_numpy(table[shape_name], 3)
        has_shape = ~np.isnan(shape).any(axis=1)
        expected = np.where(has_shape, np.prod(np.nan_to_num(shape, nan=-1), axis=1), -1)
        empty = has_values & (lengths == 0)
        if empty.any():
            i = int(np.flatnonzero(empty)[0])
            raise self.error("empty range image", column=values_name,
                             expected="H*W*C > 0 values",
                             found=f"0 values with shape {shape[i].tolist()} at "
                                   f"{self.row_keys(table, i)}")
        mismatch = (has_values | has_shape) & ((expected != lengths) | (shape < 1).any(axis=1))
        if mismatch.any():
            i = int(np.flatnonzero(mismatch)[0])
            raise self.error("range image shape does not match its values", column=shape_name,
                             expected=f"H*W*C = {int(lengths[i])} values" if has_values[i] else
                             "no shape for a null range image",
                             found=f"shape {shape[i].tolist()} at {self.row_keys(table, i)}")


def _open(root, split, component, segment, storage_options):
    fs, base = _filesystem(root, storage_options)
    return _ComponentFile(fs, base, split, component, segment)


def read_component(root: str, split: str, component: str, segment: str,
                   columns: Sequence[str] | None = None,
                   storage_options: dict | None = None) -> pa.Table:
    """Rows of ``segment`` from ``{root}/{split}/{component}/{segment}.parquet``.

    Args:
        columns: full column names to read (default: every official column); the key columns
            are always included and come first.
    Returns:
        A pyarrow Table with the file's own arrow types (list child names and large variants are
        left as found; the decoders accept them all).
    Raises:
        WaymoFormatError: missing file, truncated/corrupt parquet, missing column, wrong type,
            segment absent, duplicate keys, NaN in a transform, empty range image, or a
            range-image shape that does not match its values length.
    """
    with _open(root, split, component, segment, storage_options) as f:
        return f.read(f.columns(columns))


# --------------------------------------------------------------------------------------------
# Bulk decoders


def _as_array(column) -> pa.Array:
    if isinstance(column, pa.ChunkedArray):
        if column.num_chunks == 1:
            return column.chunk(0)
        return column.combine_chunks() if column.num_chunks else pa.array([], column.type)
    return column


def _valid_mask(column) -> np.ndarray:
    """bool [N], True where the row is not null."""
    arr = _as_array(column)
    if arr.null_count == 0:
        return np.ones(len(arr), dtype=bool)
    return pc.is_valid(arr).to_numpy(zero_copy_only=False)


def _fixed_numpy(column, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(float64 [N, size] with NaN for nulls, bool [N] row valid) of a fixed_size_list column."""
    arr = _as_array(column)
    n = len(arr)
    if n == 0:
        return np.zeros((0, size)), np.zeros(0, dtype=bool)
    child = arr.values.slice(arr.offset * size, n * size)
    flat = child.to_numpy(zero_copy_only=False).astype(np.float64, copy=False).reshape(n, size)
    valid = _valid_mask(arr)
    if not valid.all():
        flat = flat.copy()
        flat[~valid] = np.nan
    return flat, valid


def _scalar_numpy(column, dtype, fill) -> np.ndarray:
    arr = _as_array(column)
    if arr.null_count:
        arr = pc.fill_null(arr, fill)
    return arr.to_numpy(zero_copy_only=False).astype(dtype, copy=False)


def _list_parts(column) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(offsets int64 [N + 1], flat values, valid bool [N]) of a list / large_list column."""
    arr = _as_array(column)
    offsets = arr.offsets.to_numpy().astype(np.int64, copy=False)
    values = arr.values.to_numpy(zero_copy_only=False)
    return offsets, values, _valid_mask(arr)


def transforms_from_column(column) -> np.ndarray:
    """float64 [N, 4, 4] from a ``fixed_size_list<double>[16]`` column (row-major); NaN for nulls."""
    flat, _ = _fixed_numpy(column, 16)
    return matrix_from_flat(flat)


def range_images_from_columns(values, shape) -> list[np.ndarray | None]:
    """Per row, a read-only view float/int [H, W, C] of a range image, or None for a null row.

    Args:
        values: ``list<float>`` (or int32) column, row-major ``[H, W, C]`` (channel innermost).
        shape: ``fixed_size_list<int32>[3]`` column.
    The views share the column's memory (no copy, no per-pixel loop). Shapes are trusted: check
    them first (:func:`read_component` does).
    """
    offsets, flat, valid = _list_parts(values)
    dims, has_shape = _fixed_numpy(shape, 3)
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


def lidar_points(range_image: np.ndarray, vehicle_from_lidar: np.ndarray,
                 inclinations: np.ndarray, pixel_pose: np.ndarray | None = None,
                 world_from_vehicle: np.ndarray | None = None):
    """Valid returns of one range image as vehicle-frame points.

    Args:
        range_image: float [H, W, C] (channels range, intensity, elongation, no-label-zone);
            a pixel is a return where range > 0 and finite (NaN / inf ranges are no return).
        vehicle_from_lidar: float64 [4, 4], ``lidar_calibration.extrinsic``.
        inclinations: float64 [H], radians, row 0 = highest beam (:func:`lidar.beam_inclinations`).
        pixel_pose: optional float [H, W, 6] (``lidar_pose``: roll, pitch, yaw, x, y, z =
            world_from_vehicle at each pixel's capture time); needs ``world_from_vehicle``.
        world_from_vehicle: float64 [4, 4], the frame's vehicle pose.
    Returns:
        ``(points_vehicle float64 [M, 3], row int32 [M], col int32 [M], intensity float32 [M])``
        in row-major pixel order; with ``pixel_pose`` the points are in the frame's vehicle frame
        (motion during the sweep removed).
    """
    h, w, _ = range_image.shape
    azimuths = beam.beam_azimuths(w, vehicle_from_lidar)
    directions = beam.sensor_directions(np.asarray(inclinations, np.float64), azimuths)
    rotated = directions @ np.asarray(vehicle_from_lidar, np.float64)[:3, :3].T
    return _points_from_directions(range_image, rotated, vehicle_from_lidar[:3, 3], pixel_pose,
                                   world_from_vehicle)


def _points_from_directions(range_image, directions_vehicle, origin_vehicle, pixel_pose=None,
                            world_from_vehicle=None):
    rng = range_image[..., 0]
    with np.errstate(invalid="ignore"):
        rows, cols = np.nonzero(np.isfinite(rng) & (rng > 0))
    r = rng[rows, cols].astype(np.float64)
    points = r[:, None] * directions_vehicle[rows, cols] + np.asarray(origin_vehicle, np.float64)
    if range_image.shape[-1] > 1:
        intensity = range_image[rows, cols, 1].astype(np.float32)
    else:
        intensity = np.full(rows.shape, np.nan, np.float32)
    if pixel_pose is not None:
        points = _apply_pixel_pose(points, pixel_pose[rows, cols], world_from_vehicle)
    return points, rows.astype(np.int32), cols.astype(np.int32), intensity


def _apply_pixel_pose(points_vehicle_at_pixel: np.ndarray, pose: np.ndarray,
                      world_from_vehicle: np.ndarray) -> np.ndarray:
    """inv(world_from_vehicle) @ pixel_pose @ p for points [M, 3] and poses [M, 6]."""
    pose = np.asarray(pose, np.float64)
    rotation = rotation_from_rpy(pose[:, 0], pose[:, 1], pose[:, 2])
    world = np.einsum("mij,mj->mi", rotation, points_vehicle_at_pixel) + pose[:, 3:6]
    return transform_points(invert_rigid(world_from_vehicle), world)


def camera_projection_at(projection: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """int16 [M, 6] ``lidar_camera_projection`` [cam1, x1, y1, cam2, x2, y2] at given pixels.

    ``projection`` is the decoded [H, W, 6] range image (integers stored as float); camera 0 means
    no projection. Coordinates follow Waymo: pixel 0 starts at the left/top image edge.
    """
    return np.rint(projection[rows, cols, :6]).astype(np.int16)


# --------------------------------------------------------------------------------------------
# Scene assembly


def _frame_index(timestamps: np.ndarray, ts_rows: np.ndarray, f: _ComponentFile) -> np.ndarray:
    """int32 [R] frame index of each row's timestamp; error for timestamps that are no frame."""
    ts_rows = np.asarray(ts_rows, np.int64)
    if ts_rows.size == 0:
        return np.zeros(0, np.int32)
    idx = np.minimum(np.searchsorted(timestamps, ts_rows), max(len(timestamps) - 1, 0))
    bad = (timestamps[idx] != ts_rows) if len(timestamps) else np.ones(ts_rows.shape, bool)
    if np.any(bad):
        value = int(ts_rows[np.flatnonzero(bad)[0]])
        raise f.error("frame timestamp not present in vehicle_pose", column=KEY_TIMESTAMP,
                      expected="a key.frame_timestamp_micros of vehicle_pose", found=value)
    return idx.astype(np.int32)


@dataclass
class _LidarCalibration:
    vehicle_from_lidar: np.ndarray
    incl_values: np.ndarray | None
    incl_min: float | None
    incl_max: float | None

    def inclinations(self, height: int, f: _ComponentFile, laser: int) -> np.ndarray:
        try:
            return beam.beam_inclinations(height, self.incl_values, self.incl_min, self.incl_max)
        except ValueError as exc:
            raise f.error(f"laser {LaserName(laser).name}: {exc}",
                          column="[LiDARCalibrationComponent].beam_inclination",
                          expected=f"{height} values or min/max", found=None) from None


def _read_lidar_calibration(f: _ComponentFile) -> dict[int, _LidarCalibration]:
    c = f.comp
    table = f.read(f.columns(None))
    names = _scalar_numpy(table["key.laser_name"], np.int64, 0)
    extrinsic = transforms_from_column(table[c.col("extrinsic.transform")])
    incl_min = _scalar_numpy(table[c.col("beam_inclination.min")], np.float64, np.nan)
    incl_max = _scalar_numpy(table[c.col("beam_inclination.max")], np.float64, np.nan)
    offsets, flat, valid = _list_parts(table[c.col("beam_inclination.values")])
    out = {}
    for i, laser in enumerate(names):
        if np.isnan(extrinsic[i]).any():
            raise f.error("null extrinsic", column=c.col("extrinsic.transform"),
                          expected="a transform", found=f"null for laser {int(laser)}")
        values = flat[offsets[i]: offsets[i + 1]].astype(np.float64) if valid[i] else None
        out[int(laser)] = _LidarCalibration(
            extrinsic[i], values, None if np.isnan(incl_min[i]) else float(incl_min[i]),
            None if np.isnan(incl_max[i]) else float(incl_max[i]))
    return out


def _read_camera_calibration(f: _ComponentFile, cameras: Iterable[int]) -> dict[int, CameraModel]:
    c = f.comp
    table = f.read(f.columns(None))
    names = _scalar_numpy(table["key.camera_name"], np.int64, 0).tolist()
    extrinsic = transforms_from_column(table[c.col("extrinsic.transform")])
    out = {}
    for cam in cameras:
        if cam not in names:
            raise f.error("requested camera has no calibration", column="key.camera_name",
                          expected=int(cam), found=sorted(names))
        i = names.index(cam)
        kw = {}
        for p in ("f_u", "f_v", "c_u", "c_v", "k1", "k2", "p1", "p2", "k3"):
            v = table[c.col(f"intrinsic.{p}")][i].as_py()
            if v is None or not np.isfinite(v) or (p in ("f_u", "f_v") and not v > 0):
                raise f.error("missing or invalid intrinsic", column=c.col(f"intrinsic.{p}"),
                              expected="a finite number (f_u, f_v > 0)", found=f"{v} for camera {cam}")
            kw[p] = float(v)
        for p in ("width", "height"):
            v = table[c.col(p)][i].as_py()
            if v is None or v <= 0:
                raise f.error("missing or invalid image size", column=c.col(p),
                              expected="a positive integer", found=f"{v} for camera {cam}")
            kw[p] = int(v)
        if np.isnan(extrinsic[i]).any():
            raise f.error("null extrinsic", column=c.col("extrinsic.transform"),
                          expected="a transform", found=f"null for camera {cam}")
        direction = table[c.col("rolling_shutter_direction")][i].as_py()
        out[cam] = CameraModel(**kw, vehicle_from_camera=extrinsic[i],
                               rolling_shutter_direction=int(direction or 0))
    return out


def _read_cameras(f: _ComponentFile, models: dict[int, CameraModel], timestamps: np.ndarray,
                  with_images: bool) -> dict[int, CameraFrames]:
    c = f.comp
    value_cols = [c.col(p) for p in (
        "pose.transform", "velocity.linear_velocity.x", "velocity.linear_velocity.y",
        "velocity.linear_velocity.z", "velocity.angular_velocity.x", "velocity.angular_velocity.y",
        "velocity.angular_velocity.z", "pose_timestamp", "rolling_shutter_params.shutter",
        "rolling_shutter_params.camera_trigger_time",
        "rolling_shutter_params.camera_readout_done_time")]
    if with_images:
        value_cols.append(c.col("image"))
    table = f.read(f.columns(value_cols))
    cam_col = _scalar_numpy(table["key.camera_name"], np.int64, 0)
    n_frames = len(timestamps)
    out = {}
    for cam, model in models.items():
        sub = table.filter(pa.array(cam_col == cam))
        t = _frame_index(timestamps, _scalar_numpy(sub[KEY_TIMESTAMP], np.int64, 0), f)

        def scatter(values, width=None):
            shape = (n_frames,) if width is None else (n_frames,) + width
            arr = np.full(shape, np.nan)
            arr[t] = values
            return arr

        pose = scatter(transforms_from_column(sub[c.col("pose.transform")]), (4, 4))
        vel = np.stack([_scalar_numpy(sub[name], np.float64, np.nan) for name in value_cols[1:7]],
                       axis=-1)
        jpeg: list = [None] * n_frames
        if with_images:
            images = sub[c.col("image")].to_pylist()
            for ti, data in zip(t.tolist(), images):
                jpeg[ti] = data
        out[cam] = CameraFrames(
            model=model, jpeg=jpeg, world_from_vehicle=pose, pose_timestamp=scatter(
                _scalar_numpy(sub[value_cols[7]], np.float64, np.nan)),
            velocity=scatter(vel, (6,)),
            shutter=scatter(_scalar_numpy(sub[value_cols[8]], np.float64, np.nan)),
            trigger_time=scatter(_scalar_numpy(sub[value_cols[9]], np.float64, np.nan)),
            readout_done_time=scatter(_scalar_numpy(sub[value_cols[10]], np.float64, np.nan)))
    return out


def _read_boxes(f: _ComponentFile, timestamps: np.ndarray) -> Boxes:
    c = f.comp
    names = {p: c.col(p) for p in (
        "box.center.x", "box.center.y", "box.center.z", "box.size.x", "box.size.y", "box.size.z",
        "box.heading", "type", "num_lidar_points_in_box", "speed.x", "speed.y", "speed.z")}
    table = f.read(f.columns(list(names.values())))
    num = lambda p: _scalar_numpy(table[names[p]], np.float64, np.nan)  # noqa: E731
    center = np.stack([num("box.center.x"), num("box.center.y"), num("box.center.z")], -1)
    size = np.stack([num("box.size.x"), num("box.size.y"), num("box.size.z")], -1)
    heading = num("box.heading")
    for col, arr in ((names["box.center.x"], center), (names["box.size.x"], size),
                     (names["box.heading"], heading)):
        bad = ~np.isfinite(arr.reshape(len(arr), -1)).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise f.error("null, NaN or infinite box geometry", column=col, expected="finite numbers",
                          found=f"{arr[i].tolist()} at {f.row_keys(table, i)}")
    negative = (size < 0).any(axis=1)
    if negative.any():
        i = int(np.flatnonzero(negative)[0])
        raise f.error("negative box size", column=names["box.size.x"],
                      expected="sizes x, y, z >= 0 (metres)",
                      found=f"{size[i].tolist()} at {f.row_keys(table, i)}")
    object_id = np.array(table["key.laser_object_id"].to_pylist(), dtype=object)
    # object ids become part of clip file names: refuse any that cannot, before a path is built
    for value in dict.fromkeys(object_id.tolist()):
        try:
            check_name("object_id", value)
        except InvalidNameError as exc:
            i = int(np.flatnonzero(object_id == value)[0]) if value is not None else \
                int(np.flatnonzero(np.equal(object_id, None))[0])
            raise f.error("object id cannot be part of a file name", column="key.laser_object_id",
                          expected=str(exc).split(": use ", 1)[-1],
                          found=f"{value!r} at {f.row_keys(table, i)}") from None
    frame = _frame_index(timestamps, _scalar_numpy(table[KEY_TIMESTAMP], np.int64, 0), f)
    order = np.lexsort((object_id.astype(str), frame)) if len(frame) else np.zeros(0, np.int64)
    boxes = Boxes(
        object_id=object_id, frame=frame, center=center, size=size, heading=heading,
        type=_scalar_numpy(table[names["type"]], np.int8, 0),
        speed=np.stack([num("speed.x"), num("speed.y"), num("speed.z")], -1),
        num_lidar_points_in_box=_scalar_numpy(table[names["num_lidar_points_in_box"]], np.int64, -1))
    return boxes.select(order)


def _empty_boxes() -> Boxes:
    return Boxes(object_id=np.zeros(0, object), frame=np.zeros(0, np.int32), center=np.zeros((0, 3)),
                 size=np.zeros((0, 3)), heading=np.zeros(0), type=np.zeros(0, np.int8),
                 speed=np.zeros((0, 3)), num_lidar_points_in_box=np.zeros(0, np.int64))


def _point_key(frame, laser, return_index) -> np.ndarray:
    """Sort key of a return: frame-major, then laser, then return (1 or 2)."""
    return (np.asarray(frame, np.int64) * 16 + np.asarray(laser, np.int64) * 2
            + np.asarray(return_index, np.int64) - 1)


def _read_lidar(f: _ComponentFile, calibrations: dict[int, _LidarCalibration], lasers: set[int],
                returns: Sequence[int], timestamps: np.ndarray, cal_file: _ComponentFile):
    """Phase 1: stream range images, keep valid returns (vehicle frame of the pixel's pose).

    Returns ``(returns, nonfinite)``: the :class:`LidarReturns` and the number of NaN / inf
    ranges of the lasers and returns read (dropped: such a pixel is no return).
    """
    c = f.comp
    cols = []
    for r in returns:
        cols += [c.col(f"range_image_return{r}.values"), c.col(f"range_image_return{r}.shape")]
    cols = f.columns(cols)
    f.read_keys()
    geometry_cache: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}
    chunks = []
    nonfinite = 0
    for table in f.iter_batches(cols, LIDAR_BATCH_ROWS):
        laser_col = _scalar_numpy(table["key.laser_name"], np.int64, 0)
        frame_col = _frame_index(timestamps, _scalar_numpy(table[KEY_TIMESTAMP], np.int64, 0), f)
        for r in returns:
            images = range_images_from_columns(table[c.col(f"range_image_return{r}.values")],
                                               table[c.col(f"range_image_return{r}.shape")])
            for i, image in enumerate(images):
                laser = int(laser_col[i])
                if image is None or laser not in lasers:
                    continue
                if laser not in calibrations:
                    raise cal_file.error("laser has range images but no calibration",
                                         column="key.laser_name", expected=sorted(calibrations),
                                         found=laser)
                h, w, _ = image.shape
                key = (laser, h, w)
                if key not in geometry_cache:
                    cal = calibrations[laser]
                    incl = cal.inclinations(h, cal_file, laser)
                    dirs = beam.sensor_directions(incl, beam.beam_azimuths(w, cal.vehicle_from_lidar))
                    geometry_cache[key] = (dirs @ cal.vehicle_from_lidar[:3, :3].T,
                                           cal.vehicle_from_lidar[:3, 3].copy())
                dirs, origin = geometry_cache[key]
                nonfinite += int(np.count_nonzero(~np.isfinite(image[..., 0])))
                pts, rows, cols_, inten = _points_from_directions(image, dirs, origin)
                n = len(rows)
                chunks.append((pts, rows, cols_, inten, np.full(n, frame_col[i], np.int32),
                               np.full(n, laser, np.int8), np.full(n, r, np.int8)))
    if not chunks:
        return _empty_returns(len(timestamps)), nonfinite
    pts, rows, cols_, inten, frame, laser, ret = (np.concatenate(x) for x in zip(*chunks))
    del chunks
    order = np.argsort(_point_key(frame, laser, ret), kind="stable")
    frame = frame[order]
    offsets = np.searchsorted(frame, np.arange(len(timestamps) + 1)).astype(np.int64)
    return LidarReturns(points_vehicle=pts[order], frame=frame, laser=laser[order],
                        return_index=ret[order], row=rows[order], col=cols_[order],
                        intensity=inten[order], frame_offsets=offsets), nonfinite


def _empty_returns(n_frames: int) -> LidarReturns:
    return LidarReturns(points_vehicle=np.zeros((0, 3)), frame=np.zeros(0, np.int32),
                        laser=np.zeros(0, np.int8), return_index=np.zeros(0, np.int8),
                        row=np.zeros(0, np.int32), col=np.zeros(0, np.int32),
                        intensity=np.zeros(0, np.float32),
                        frame_offsets=np.zeros(n_frames + 1, np.int64))


def _apply_lidar_pose(f: _ComponentFile, returns: LidarReturns, timestamps: np.ndarray,
                      world_from_vehicle: np.ndarray, returns_read: Sequence[int]) -> np.ndarray:
    """Phase 2: move TOP returns into their frame's vehicle frame with the per-pixel pose.

    Returns float32 [M] capture-time samples (s, :func:`drivetrack.waymo.capture_time.pixel_time_offsets`
    of each TOP return's pixel pose; NaN for other lasers and where the ego stands still).
    """
    c = f.comp
    ego_velocity = capture_time.ego_velocity_world(world_from_vehicle, timestamps)
    time_samples = np.full(len(returns), np.nan, np.float32)
    values, shape = c.col("range_image_return1.values"), c.col("range_image_return1.shape")
    cols = f.columns([values, shape])
    keys = f.read_keys()
    key_all = _point_key(returns.frame, returns.laser, returns.return_index)
    top_frames = np.unique(returns.frame[returns.laser == LaserName.TOP])
    have = _frame_index(timestamps, _scalar_numpy(
        keys[KEY_TIMESTAMP].filter(pc.equal(keys["key.laser_name"], int(LaserName.TOP))),
        np.int64, 0), f)
    missing = np.setdiff1d(top_frames, have)
    if missing.size:
        raise f.error("no per-pixel pose for a TOP range image", column=values,
                      expected="a lidar_pose row for every TOP lidar row",
                      found=f"none at key.frame_timestamp_micros={int(timestamps[missing[0]])}")
    for table in f.iter_batches(cols, LIDAR_BATCH_ROWS):
        laser_col = _scalar_numpy(table["key.laser_name"], np.int64, 0)
        frame_col = _frame_index(timestamps, _scalar_numpy(table[KEY_TIMESTAMP], np.int64, 0), f)
        poses = range_images_from_columns(table[values], table[shape])
        for i, pose in enumerate(poses):
            if laser_col[i] != LaserName.TOP:
                continue  # only TOP range images carry a pose (dataset.proto, RangeImage)
            t = int(frame_col[i])
            for r in returns_read:
                k = _point_key(t, int(LaserName.TOP), r)
                block = slice(int(np.searchsorted(key_all, k, "left")),
                              int(np.searchsorted(key_all, k, "right")))
                if block.stop == block.start:
                    continue
                if pose is None:
                    raise f.error("null per-pixel pose for a TOP range image", column=values,
                                  expected="[H, W, 6] values", found=f"null at {f.row_keys(table, i)}")
                rows, cols_ = returns.row[block], returns.col[block]
                if pose.shape[2] != 6 or rows.max() >= pose.shape[0] or cols_.max() >= pose.shape[1]:
                    raise f.error("per-pixel pose does not match the range image", column=shape,
                                  expected="[H, W, 6] like the TOP range image",
                                  found=f"{list(pose.shape)} at {f.row_keys(table, i)}")
                pixel_pose = pose[rows, cols_]
                bad = ~np.isfinite(pixel_pose).all(axis=1)
                if bad.any():
                    j = int(np.flatnonzero(bad)[0])
                    raise f.error("NaN or infinite per-pixel pose at a lidar return", column=values,
                                  expected="finite roll, pitch, yaw, x, y, z at every pixel with a "
                                           "return",
                                  found=f"{pixel_pose[j].tolist()} at pixel (row {int(rows[j])}, "
                                        f"col {int(cols_[j])}) of {f.row_keys(table, i)}")
                returns.points_vehicle[block] = _apply_pixel_pose(
                    returns.points_vehicle[block], pixel_pose, world_from_vehicle[t])
                time_samples[block] = capture_time.pixel_time_offsets(
                    pixel_pose[:, 3:6], world_from_vehicle[t, :3, 3], ego_velocity[t])
    return time_samples


def _read_camera_projection(f: _ComponentFile, returns: LidarReturns, timestamps: np.ndarray,
                            returns_read: Sequence[int]) -> np.ndarray:
    c = f.comp
    cols = []
    for r in returns_read:
        cols += [c.col(f"range_image_return{r}.values"), c.col(f"range_image_return{r}.shape")]
    cols = f.columns(cols)
    f.read_keys()
    out = np.full((len(returns), 6), -1, np.int16)
    key_all = _point_key(returns.frame, returns.laser, returns.return_index)
    for table in f.iter_batches(cols, LIDAR_BATCH_ROWS):
        laser_col = _scalar_numpy(table["key.laser_name"], np.int64, 0)
        frame_col = _frame_index(timestamps, _scalar_numpy(table[KEY_TIMESTAMP], np.int64, 0), f)
        for r in returns_read:
            images = range_images_from_columns(table[c.col(f"range_image_return{r}.values")],
                                               table[c.col(f"range_image_return{r}.shape")])
            for i, proj in enumerate(images):
                if proj is None:
                    continue
                k = _point_key(int(frame_col[i]), int(laser_col[i]), r)
                lo, hi = np.searchsorted(key_all, k, "left"), np.searchsorted(key_all, k, "right")
                if hi == lo:
                    continue
                rows, cols_ = returns.row[lo:hi], returns.col[lo:hi]
                if proj.shape[2] != 6 or rows.max() >= proj.shape[0] or cols_.max() >= proj.shape[1]:
                    raise f.error("camera projection does not match the range image",
                                  column=c.col(f"range_image_return{r}.shape"),
                                  expected="[H, W, 6] like the lidar range image",
                                  found=f"{list(proj.shape)} at {f.row_keys(table, i)}")
                out[lo:hi] = camera_projection_at(proj, rows, cols_)
    return out


def load_scene(root: str, split: str, segment: str, cameras: Sequence[int] = (1, 2, 3),
               lasers: Sequence[int] | None = None, returns: Sequence[int] = (1, 2),
               with_images: bool = True, storage_options: dict | None = None,
               with_camera_projection: bool = False) -> Scene:
    """Load one segment into a :class:`Scene`, joining components on their key columns.

    Args:
        cameras: ``CameraName`` values to load (each needs a calibration).
        lasers: ``LaserName`` values; None = every laser with a calibration.
        returns: which range-image returns (1, 2) to turn into points.
        with_images: keep the JPEG bytes (decoded lazily by ``CameraFrames.image``).
        with_camera_projection: also fill ``LidarReturns.camera_projection`` from
            ``lidar_camera_projection``.
    ``LidarReturns.capture_offset_s`` is filled from the TOP per-pixel poses
    (:mod:`drivetrack.waymo.capture_time`: one ``a + b * col`` model per segment, 0 for other lasers).
    Frames are ``vehicle_pose``'s timestamps in increasing order; rows of other components whose
    timestamp is not among them raise :class:`WaymoFormatError`.

    Bad numbers: NaN/inf in a transform, a transform that is not rigid, inf in a number column,
    non-finite or non-positive focal lengths, non-finite or negative box geometry and NaN/inf
    per-pixel poses at a return raise :class:`WaymoFormatError`; NaN/inf ranges are no return
    (dropped) and counted in ``Scene.source_stats["lidar_nonfinite_ranges"]``. Split, segment
    and object ids that cannot be part of a file name raise before any path is built.
    """
    _check_names(split, segment)
    fs, base = _filesystem(root, storage_options)
    returns = tuple(sorted(set(int(r) for r in returns)))
    if not set(returns) <= {1, 2}:
        raise ValueError(f"returns must be 1 and/or 2, got {returns}")
    needed = ["vehicle_pose", "lidar_box"]
    if cameras:
        needed += ["camera_calibration", "camera_image"]
    if lasers is None or len(lasers):
        needed += ["lidar_calibration", "lidar"]
    present = [name for name in needed
               if fs.exists(f"{base}/{split}/{name}/{segment}.parquet")]
    files: dict[str, _ComponentFile] = {}
    source_stats = {"lidar_nonfinite_ranges": 0}

    def open_component(name: str) -> _ComponentFile:
        try:
            files[name] = _ComponentFile(fs, base, split, name, segment)
        except WaymoFormatError as exc:
            if exc.problem == "missing component file" and present:
                raise WaymoFormatError(
                    f"segment present in components {present} but absent from component {name!r}",
                    url=exc.url, segment=segment, component=name, column=exc.column,
                    expected="a parquet file", found="no such file") from None
            raise
        return files[name]

    try:
        vp = open_component("vehicle_pose")
        table = vp.read(vp.columns(None))
        timestamps = _scalar_numpy(table[KEY_TIMESTAMP], np.int64, 0)
        order = np.argsort(timestamps, kind="stable")
        timestamps = timestamps[order]
        pose_col = vp.comp.col("world_from_vehicle.transform")
        world_from_vehicle = transforms_from_column(table[pose_col])[order]
        bad = np.isnan(world_from_vehicle).any(axis=(1, 2))
        if bad.any():
            raise vp.error("null vehicle pose", column=pose_col, expected="a transform",
                           found=f"null at {KEY_TIMESTAMP}={int(timestamps[np.flatnonzero(bad)[0]])}")

        camera_frames: dict[int, CameraFrames] = {}
        if cameras:
            models = _read_camera_calibration(open_component("camera_calibration"),
                                              [int(c) for c in cameras])
            camera_frames = _read_cameras(open_component("camera_image"), models, timestamps,
                                          with_images)

        lidar_returns = _empty_returns(len(timestamps))
        if lasers is None or len(lasers):
            cal_file = open_component("lidar_calibration")
            calibrations = _read_lidar_calibration(cal_file)
            wanted = set(calibrations) if lasers is None else {int(x) for x in lasers}
            missing = wanted - set(calibrations)
            if missing:
                raise cal_file.error("requested laser has no calibration", column="key.laser_name",
                                     expected=sorted(missing), found=sorted(calibrations))
            lidar_returns, source_stats["lidar_nonfinite_ranges"] = _read_lidar(
                open_component("lidar"), calibrations, wanted, returns, timestamps, cal_file)
            timing = capture_time.SweepTiming()
            if np.any(lidar_returns.laser == LaserName.TOP):
                samples = _apply_lidar_pose(open_component("lidar_pose"), lidar_returns,
                                            timestamps, world_from_vehicle, returns)
                timing = capture_time.fit_sweep_timing(lidar_returns.col, samples)
            lidar_returns.capture_offset_s = capture_time.capture_offsets(lidar_returns.laser,
                                                                   lidar_returns.col, timing)
            if with_camera_projection:
                lidar_returns.camera_projection = _read_camera_projection(
                    open_component("lidar_camera_projection"), lidar_returns, timestamps, returns)

        boxes = _read_boxes(open_component("lidar_box"), timestamps)
        return Scene(segment=segment, split=split, timestamps_micros=timestamps,
                     world_from_vehicle=world_from_vehicle, cameras=camera_frames,
                     lidar=lidar_returns, boxes=boxes,
                     source_files={name: f.url for name, f in files.items()},
                     source_stats=source_stats)
    finally:
        for f in files.values():
            f.close()


# --------------------------------------------------------------------------------------------
# Summary (drivetrack info)


def segment_summary(root: str, split: str, segment: str,
                    storage_options: dict | None = None) -> dict:
    """Counts of one segment without decoding images or computing points.

    Returns a JSON-ready dict: ``segment``, ``split``, ``num_frames``, ``start_micros``,
    ``end_micros``, ``duration_s``, ``cameras`` (name -> width, height, images),
    ``lasers`` (name -> range-image shape, frames, valid returns per return, NaN/inf ranges
    per return: ``nonfinite_return1/2``, dropped by :func:`load_scene`), ``objects``
    (type name -> distinct objects, boxes), ``files`` (component -> URL).
    """
    from drivetrack.waymo.schema import BoxType, CameraName

    _check_names(split, segment)
    fs, base = _filesystem(root, storage_options)
    out: dict = {"segment": segment, "split": split, "files": {}}

    def opened(name):
        f = _ComponentFile(fs, base, split, name, segment)
        out["files"][name] = f.url
        return f

    with opened("vehicle_pose") as f:
        ts = np.sort(_scalar_numpy(f.read_keys()[KEY_TIMESTAMP], np.int64, 0))
    out.update(num_frames=int(ts.size), start_micros=int(ts[0]), end_micros=int(ts[-1]),
               duration_s=float(ts[-1] - ts[0]) / 1e6)
    cams: dict = {}
    if fs.exists(f"{base}/{split}/camera_calibration/{segment}.parquet"):
        with opened("camera_calibration") as f:
            c = f.comp
            t = f.read(f.columns([c.col("width"), c.col("height")]))
            for name, w, h in zip(t["key.camera_name"].to_pylist(), t[c.col("width")].to_pylist(),
                                  t[c.col("height")].to_pylist()):
                cams[_enum_name(CameraName, name)] = {"width": w, "height": h, "images": 0}
    if fs.exists(f"{base}/{split}/camera_image/{segment}.parquet"):
        with opened("camera_image") as f:
            names = _scalar_numpy(f.read_keys()["key.camera_name"], np.int64, 0)
            for name, n in zip(*np.unique(names, return_counts=True)):
                cams.setdefault(_enum_name(CameraName, name), {"width": None, "height": None,
                                                               "images": 0})["images"] = int(n)
    out["cameras"] = dict(sorted(cams.items()))
    lasers: dict = {}
    if fs.exists(f"{base}/{split}/lidar/{segment}.parquet"):
        with opened("lidar") as f:
            c = f.comp
            cols = f.columns(None)
            f.read_keys()
            for table in f.iter_batches(cols, LIDAR_BATCH_ROWS):
                laser_col = _scalar_numpy(table["key.laser_name"], np.int64, 0)
                for r in (1, 2):
                    images = range_images_from_columns(table[c.col(f"range_image_return{r}.values")],
                                                       table[c.col(f"range_image_return{r}.shape")])
                    for laser, image in zip(laser_col.tolist(), images):
                        entry = lasers.setdefault(_enum_name(LaserName, laser), {
                            "shape": None, "frames": 0, "valid_return1": 0, "valid_return2": 0,
                            "nonfinite_return1": 0, "nonfinite_return2": 0})
                        if r == 1:
                            entry["frames"] += 1
                        if image is not None:
                            entry["shape"] = list(image.shape)
                            finite = np.isfinite(image[..., 0])
                            with np.errstate(invalid="ignore"):
                                entry[f"valid_return{r}"] += int(np.count_nonzero(finite & (image[..., 0] > 0)))
                            entry[f"nonfinite_return{r}"] += int(finite.size - np.count_nonzero(finite))
    out["lasers"] = dict(sorted(lasers.items()))
    objects: dict = {}
    if fs.exists(f"{base}/{split}/lidar_box/{segment}.parquet"):
        with opened("lidar_box") as f:
            t = f.read(f.columns([f.comp.col("type")]))
            types = _scalar_numpy(t[f.comp.col("type")], np.int64, 0)
            ids = np.array(t["key.laser_object_id"].to_pylist(), dtype=object)
            for ty in np.unique(types):
                sel = types == ty
                objects[_enum_name(BoxType, ty)] = {"objects": len(set(ids[sel].tolist())),
                                                   "boxes": int(sel.sum())}
    out["objects"] = objects
    return out


def _enum_name(enum_cls, value) -> str:
    try:
        return enum_cls(int(value)).name
    except ValueError:
        return str(int(value))
