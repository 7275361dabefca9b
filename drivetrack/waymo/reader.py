"""Load one Waymo Open Dataset v2 segment (perception, parquet) into a Scene, without TensorFlow.

The package reads in layers, one module per job:

- :mod:`drivetrack.waymo.components` opens one component file through fsspec and reads only the
  requested columns (plus the key columns), validated against the official types, filtered to the
  segment, duplicate keys refused; :mod:`drivetrack.waymo.checks` checks the numbers (NaN in
  transforms, rigid transforms, range-image shapes). Every problem raises
  :class:`WaymoFormatError` naming the file URL, segment, component, column, expected and found.
- :mod:`drivetrack.waymo.columns` decodes arrow columns into numpy in bulk;
  :mod:`drivetrack.waymo.lidar` turns range images into points (beam geometry, per-pixel poses).
- This module, :func:`load_scene`, joins the components on their key columns (never on row order)
  into a :class:`drivetrack.scene.Scene`. :mod:`drivetrack.waymo.summary` counts a segment.

Column names come from :mod:`drivetrack.waymo.schema` only.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from drivetrack.camera.model import CameraModel
from drivetrack.geometry import invert_rigid
from drivetrack.names import InvalidNameError, check_name
from drivetrack.scene import Boxes, CameraFrames, LidarReturns, Scene
from drivetrack.waymo import lidar as beam
from drivetrack.waymo import capture_time
from drivetrack.waymo.columns import (list_parts, range_images_from_columns, scalar_numpy,
                                      transforms_from_column)
# list_segments, read_component and WaymoFormatError are the documented entry points of
# drivetrack.waymo.reader (docs/waymo-v2.md): re-exported from their home, waymo/components.py.
from drivetrack.waymo.components import (LIDAR_BATCH_ROWS, ComponentFile, WaymoFormatError,  # noqa: F401
                                         check_names, filesystem, list_segments, read_component)
from drivetrack.waymo.kernel import posed_returns, returns_from_range_image
from drivetrack.waymo.schema import (KEY_CAMERA, KEY_LASER, KEY_LASER_OBJECT, KEY_TIMESTAMP, CameraName, LaserName,
                                     merge_rows)

__all__ = ["WaymoFormatError", "list_segments", "read_component", "load_scene"]

def _frame_index(timestamps: np.ndarray, ts_rows: np.ndarray, f: ComponentFile) -> np.ndarray:
    """int32 [R] frame index of each row's timestamp (joined to ``vehicle_pose`` on
    :data:`KEY_TIMESTAMP`); error for timestamps that are no frame."""
    frame, found = merge_rows({KEY_TIMESTAMP: timestamps}, {KEY_TIMESTAMP: ts_rows})
    if not found.all():
        value = int(np.asarray(ts_rows, np.int64)[np.flatnonzero(~found)[0]])
        raise f.error("frame timestamp not present in vehicle_pose", column=KEY_TIMESTAMP,
                      expected=f"a {KEY_TIMESTAMP} of vehicle_pose", found=value)
    return frame.astype(np.int32)


@dataclass
class _LidarCalibration:
    vehicle_from_lidar: np.ndarray
    incl_values: np.ndarray | None
    incl_min: float | None
    incl_max: float | None

    def inclinations(self, height: int, f: ComponentFile, laser: int) -> np.ndarray:
        try:
            return beam.beam_inclinations(height, self.incl_values, self.incl_min, self.incl_max)
        except ValueError as exc:
            raise f.error(f"laser {LaserName(laser).name}: {exc}",
                          column="[LiDARCalibrationComponent].beam_inclination",
                          expected=f"{height} values or min/max", found=None) from None


def _read_lidar_calibration(f: ComponentFile) -> dict[int, _LidarCalibration]:
    c = f.comp
    table = f.read(f.columns(None))
    names = scalar_numpy(table[KEY_LASER], np.int64, 0)
    extrinsic = transforms_from_column(table[c.col("extrinsic.transform")])
    incl_min = scalar_numpy(table[c.col("beam_inclination.min")], np.float64, np.nan)
    incl_max = scalar_numpy(table[c.col("beam_inclination.max")], np.float64, np.nan)
    offsets, flat, valid = list_parts(table[c.col("beam_inclination.values")])
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


def _read_camera_calibration(f: ComponentFile, cameras: Iterable[int]) -> dict[int, CameraModel]:
    c = f.comp
    table = f.read(f.columns(None))
    names = scalar_numpy(table[KEY_CAMERA], np.int64, 0)
    extrinsic = transforms_from_column(table[c.col("extrinsic.transform")])
    cameras = list(cameras)
    rows, found = merge_rows({KEY_CAMERA: names}, {KEY_CAMERA: cameras})
    out = {}
    for cam, i, ok in zip(cameras, rows.tolist(), found.tolist()):
        if not ok:
            raise f.error("requested camera has no calibration", column=KEY_CAMERA,
                          expected=int(cam), found=sorted(names.tolist()))
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


def _read_cameras(f: ComponentFile, models: dict[int, CameraModel], timestamps: np.ndarray,
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
    cam_col = scalar_numpy(table[KEY_CAMERA], np.int64, 0)
    n_frames = len(timestamps)
    out = {}
    for cam, model in models.items():
        sub = table.filter(pa.array(cam_col == cam))
        t = _frame_index(timestamps, scalar_numpy(sub[KEY_TIMESTAMP], np.int64, 0), f)

        def scatter(values, width=None):
            shape = (n_frames,) if width is None else (n_frames,) + width
            arr = np.full(shape, np.nan)
            arr[t] = values
            return arr

        pose = scatter(transforms_from_column(sub[c.col("pose.transform")]), (4, 4))
        vel = np.stack([scalar_numpy(sub[name], np.float64, np.nan) for name in value_cols[1:7]],
                       axis=-1)
        jpeg: list = [None] * n_frames
        if with_images:
            images = sub[c.col("image")].to_pylist()
            for ti, data in zip(t.tolist(), images):
                jpeg[ti] = data
        out[cam] = CameraFrames(
            model=model, jpeg=jpeg, world_from_vehicle=pose, pose_timestamp=scatter(
                scalar_numpy(sub[value_cols[7]], np.float64, np.nan)),
            velocity=scatter(vel, (6,)),
            shutter=scatter(scalar_numpy(sub[value_cols[8]], np.float64, np.nan)),
            trigger_time=scatter(scalar_numpy(sub[value_cols[9]], np.float64, np.nan)),
            readout_done_time=scatter(scalar_numpy(sub[value_cols[10]], np.float64, np.nan)))
    return out


def _read_boxes(f: ComponentFile, timestamps: np.ndarray) -> Boxes:
    c = f.comp
    names = {p: c.col(p) for p in (
        "box.center.x", "box.center.y", "box.center.z", "box.size.x", "box.size.y", "box.size.z",
        "box.heading", "type", "num_lidar_points_in_box", "speed.x", "speed.y", "speed.z")}
    table = f.read(f.columns(list(names.values())))
    num = lambda p: scalar_numpy(table[names[p]], np.float64, np.nan)  # noqa: E731
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
    object_id = np.array(table[KEY_LASER_OBJECT].to_pylist(), dtype=object)
    # object ids become part of clip file names: refuse any that cannot, before a path is built
    for value in dict.fromkeys(object_id.tolist()):
        try:
            check_name("object_id", value)
        except InvalidNameError as exc:
            i = int(np.flatnonzero(object_id == value)[0]) if value is not None else \
                int(np.flatnonzero(np.equal(object_id, None))[0])
            raise f.error("object id cannot be part of a file name", column=KEY_LASER_OBJECT,
                          expected=str(exc).split(": use ", 1)[-1],
                          found=f"{value!r} at {f.row_keys(table, i)}") from None
    frame = _frame_index(timestamps, scalar_numpy(table[KEY_TIMESTAMP], np.int64, 0), f)
    order = np.lexsort((object_id.astype(str), frame)) if len(frame) else np.zeros(0, np.int64)
    boxes = Boxes(
        object_id=object_id, frame=frame, center=center, size=size, heading=heading,
        type=scalar_numpy(table[names["type"]], np.int8, 0),
        speed=np.stack([num("speed.x"), num("speed.y"), num("speed.z")], -1),
        num_lidar_points_in_box=scalar_numpy(table[names["num_lidar_points_in_box"]], np.int64, -1))
    return boxes.select(order)


def _read_synced_boxes(f: ComponentFile, timestamps: np.ndarray, boxes: Boxes) -> dict:
    """Attach ``lidar_camera_synced_box`` to ``boxes`` (``Boxes.synced_shift`` / ``synced_camera``,
    joined on frame timestamp and object id); returns counts for ``Scene.source_stats``.

    Non-finite synced geometry and camera names that are no ``CameraName`` raise; synced rows
    without a ``lidar_box`` row of the same key are not used (counted: ``synced_boxes_unmatched``).
    """
    c = f.comp
    names = {p: c.col(p) for p in ("camera_synced_box.center.x", "camera_synced_box.center.y",
                                   "camera_synced_box.center.z", "most_visible_camera_name")}
    table = f.read(f.columns(list(names.values())))
    center = np.stack([scalar_numpy(table[names[f"camera_synced_box.center.{a}"]], np.float64, np.nan)
                       for a in "xyz"], -1)
    bad = ~np.isfinite(center).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise f.error("null, NaN or infinite synced box centre", column=names["camera_synced_box.center.x"],
                      expected="finite numbers", found=f"{center[i].tolist()} at {f.row_keys(table, i)}")
    camera = scalar_numpy(table[names["most_visible_camera_name"]], np.int64, 0)
    unknown = ~np.isin(camera, [int(v) for v in CameraName])
    if unknown.any():
        i = int(np.flatnonzero(unknown)[0])
        raise f.error("unknown camera name", column=names["most_visible_camera_name"],
                      expected=f"one of {[int(v) for v in CameraName]} (CameraName)",
                      found=f"{int(camera[i])} at {f.row_keys(table, i)}")
    frame = _frame_index(timestamps, scalar_numpy(table[KEY_TIMESTAMP], np.int64, 0), f)
    ids = np.array(table[KEY_LASER_OBJECT].to_pylist(), dtype=object).astype(str)
    codes = np.unique(np.concatenate([boxes.object_id.astype(str), ids]), return_inverse=True)[1]
    row, found = merge_rows({KEY_TIMESTAMP: boxes.frame, KEY_LASER_OBJECT: codes[:len(boxes)]},
                            {KEY_TIMESTAMP: frame, KEY_LASER_OBJECT: codes[len(boxes):]})
    boxes.synced_shift = np.full((len(boxes), 3), np.nan)
    boxes.synced_camera = np.zeros(len(boxes), np.int8)
    boxes.synced_shift[row[found]] = center[found] - boxes.center[row[found]]
    boxes.synced_camera[row[found]] = camera[found]
    return {"synced_boxes": int(found.sum()), "synced_boxes_unmatched": int((~found).sum())}


def _range_images(f: ComponentFile, timestamps: np.ndarray, returns: Sequence[int]
                  ) -> Iterator[tuple[pa.Table, int, int, int, int, np.ndarray | None]]:
    """Stream the range images of ``returns`` (1, 2) of a range-image component (``lidar``,
    ``lidar_camera_projection``) in batches of :data:`LIDAR_BATCH_ROWS` rows.

    Yields ``(table, i, frame, laser, return, image)`` per row ``i`` of each batch ``table`` and
    return: the row's frame (joined to ``vehicle_pose`` on its timestamp), its laser name and the
    read-only [H, W, C] image view, None for a null image.
    """
    c = f.comp
    cols = []
    for r in returns:
        cols += [c.col(f"range_image_return{r}.values"), c.col(f"range_image_return{r}.shape")]
    cols = f.columns(cols)
    f.read_keys()
    for table in f.iter_batches(cols, LIDAR_BATCH_ROWS):
        laser_col = scalar_numpy(table[KEY_LASER], np.int64, 0)
        frame_col = _frame_index(timestamps, scalar_numpy(table[KEY_TIMESTAMP], np.int64, 0), f)
        for r in returns:
            images = range_images_from_columns(table[c.col(f"range_image_return{r}.values")],
                                               table[c.col(f"range_image_return{r}.shape")])
            for i, image in enumerate(images):
                yield table, i, int(frame_col[i]), int(laser_col[i]), r, image


def _image_blocks(returns: LidarReturns) -> dict[tuple[int, int, int], slice]:
    """``(frame, laser, return) -> slice`` of that range image's returns in ``returns`` (ordered
    by (frame, laser, return) as :func:`_read_lidar` orders them; each image's returns are one run)."""
    n = len(returns.frame)
    if n == 0:
        return {}
    image = ((returns.frame.astype(np.int64) << 8) | (returns.laser.astype(np.int64) << 4)
             | returns.return_index.astype(np.int64))
    starts = np.concatenate([[0], np.flatnonzero(image[1:] != image[:-1]) + 1])
    stops = np.append(starts[1:], n)
    return {(int(returns.frame[a]), int(returns.laser[a]), int(returns.return_index[a])): slice(int(a), int(b))
            for a, b in zip(starts, stops)}


def _read_lidar(f: ComponentFile, calibrations: dict[int, _LidarCalibration], lasers: set[int],
                returns: Sequence[int], timestamps: np.ndarray, cal_file: ComponentFile,
                world_from_vehicle: np.ndarray, open_poses: Callable[[], ComponentFile]):
    """Stream range images, keep valid returns in the vehicle frame of their frame.

    TOP returns are moved with their pixel's pose (``lidar_pose``, opened with ``open_poses`` at
    the first TOP image with returns and decoded on a helper thread, :class:`_TopPoses`) as each
    image is read, so that applying the poses overlaps decoding the range images.

    Returns ``(returns, nonfinite, samples)``: the :class:`LidarReturns`, the number of NaN / inf
    ranges of the lasers and returns read (dropped: such a pixel is no return) and float32 [M]
    capture-time samples (s, :func:`drivetrack.waymo.capture_time.pixel_time_offsets` of each TOP
    return's pixel pose; NaN for other lasers and where the ego stands still), None without TOP
    returns.
    """
    geometry_cache: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}
    chunks = []
    nonfinite = 0
    poses: _TopPoses | None = None
    try:
        for table, i, frame, laser, r, image in _range_images(f, timestamps, returns):
            if poses is not None:
                poses.batch(table)
            if image is None or laser not in lasers:
                continue
            if laser not in calibrations:
                raise cal_file.error("laser has range images but no calibration",
                                     column=KEY_LASER, expected=sorted(calibrations),
                                     found=laser)
            h, w, _ = image.shape
            _check_keyable(f, table, i, laser, h, w, f.comp.col(f"range_image_return{r}.shape"))
            key = (laser, h, w)
            if key not in geometry_cache:
                cal = calibrations[laser]
                incl = cal.inclinations(h, cal_file, laser)
                dirs = beam.sensor_directions(incl, beam.beam_azimuths(w, cal.vehicle_from_lidar))
                geometry_cache[key] = (dirs @ cal.vehicle_from_lidar[:3, :3].T,
                                       cal.vehicle_from_lidar[:3, 3].copy())
            dirs, origin = geometry_cache[key]
            pts, rows, cols_, inten, bad_ranges = returns_from_range_image(image, dirs, origin)
            nonfinite += bad_ranges
            samples = None
            if laser == LaserName.TOP and rows.size:
                if poses is None:
                    poses = _TopPoses(open_poses(), timestamps, world_from_vehicle)
                    poses.batch(table)
                pts, samples = poses.apply(frame, pts, rows, cols_)
            chunks.append(((frame, laser, r), pts, rows, cols_, inten, samples))
    finally:
        if poses is not None:
            poses.close()
    if not chunks:
        return _empty_returns(len(timestamps)), nonfinite, None
    # Each image's returns are in row-major pixel order already, so ordering the images by
    # (frame, laser, return) orders every return by its key (images are unique: keys checked).
    chunks.sort(key=lambda chunk: chunk[0])
    images = [chunk[0] for chunk in chunks]
    sizes = [len(chunk[2]) for chunk in chunks]
    frame, laser, ret = (np.repeat(np.array([image[k] for image in images], dtype), sizes)
                         for k, dtype in enumerate((np.int32, np.int8, np.int8)))
    pts, rows, cols_, inten = (np.concatenate([chunk[k] for chunk in chunks]) for k in range(1, 5))
    samples = None
    if poses is not None:
        samples = np.concatenate([np.full(n, np.nan, np.float32) if chunk[5] is None else chunk[5]
                                  for chunk, n in zip(chunks, sizes)])
    del chunks
    offsets = np.searchsorted(frame, np.arange(len(timestamps) + 1)).astype(np.int64)
    return LidarReturns(points_vehicle=pts, frame=frame, laser=laser, return_index=ret, row=rows,
                        col=cols_, intensity=inten, frame_offsets=offsets), nonfinite, samples


class _TopPoses:
    """The TOP per-pixel poses of a ``lidar_pose`` file, decoded on a helper thread.

    The constructor checks the columns and keys in the caller's thread; the helper then decodes
    the file batch by batch (joined on each row's timestamp, never on row order) while the caller
    reads range images. :meth:`apply` waits for one frame's pose image, checks it where returns
    use it and moves the returns; a frame's pose image is dropped after the lidar batch that used
    it (:meth:`batch`). Errors of the helper are raised in the caller.
    """

    def __init__(self, f: ComponentFile, timestamps: np.ndarray, world_from_vehicle: np.ndarray):
        self.f, self.timestamps, self.world_from_vehicle = f, timestamps, world_from_vehicle
        self.ego_velocity = capture_time.ego_velocity_world(world_from_vehicle, timestamps)
        c = f.comp
        self.values, self.shape = c.col("range_image_return1.values"), c.col("range_image_return1.shape")
        self.cols = f.columns([self.values, self.shape])
        keys = f.read_keys()
        self.have = set(_frame_index(timestamps, scalar_numpy(
            keys[KEY_TIMESTAMP].filter(pc.equal(keys[KEY_LASER], int(LaserName.TOP))),
            np.int64, 0), f).tolist())
        self.images: dict[int, tuple[np.ndarray | None, pa.Table, int]] = {}
        self.used: set[int] = set()
        self.table = None
        self.done, self.error, self.stop = False, None, False
        self.cond = threading.Condition()
        self.thread = threading.Thread(target=self._decode, name=f"read-{c.name}", daemon=True)
        self.thread.start()

    def _decode(self) -> None:
        try:
            for table in self.f.iter_batches(self.cols, LIDAR_BATCH_ROWS):
                laser_col = scalar_numpy(table[KEY_LASER], np.int64, 0)
                frame_col = _frame_index(self.timestamps, scalar_numpy(table[KEY_TIMESTAMP], np.int64, 0), self.f)
                poses = range_images_from_columns(table[self.values], table[self.shape])
                with self.cond:
                    if self.stop:
                        return
                    for i, pose in enumerate(poses):
                        if laser_col[i] == LaserName.TOP:   # only TOP range images carry a pose
                            self.images[int(frame_col[i])] = (pose, table, i)
                    self.cond.notify_all()
        except BaseException as exc:      # raised in the caller's thread by apply()
            with self.cond:
                self.error = exc
        finally:
            with self.cond:
                self.done = True
                self.cond.notify_all()

    def batch(self, table: pa.Table) -> None:
        """The caller moved on to lidar batch ``table``: drop the pose images the previous one used."""
        if table is not self.table:
            self.table = table
            with self.cond:
                for t in self.used:
                    self.images.pop(t, None)
            self.used = set()

    def _pose(self, t: int):
        f = self.f
        if t not in self.have:
            raise f.error("no per-pixel pose for a TOP range image", column=self.values,
                          expected="a lidar_pose row for every TOP lidar row",
                          found=f"none at {KEY_TIMESTAMP}={int(self.timestamps[t])}")
        with self.cond:
            while t not in self.images and not self.done:
                self.cond.wait()
            if t in self.images:
                return self.images[t]
            error = self.error
        if error is not None:
            raise error
        raise f.error("no per-pixel pose for a TOP range image", column=self.values,
                      expected="a lidar_pose row for every TOP lidar row",
                      found=f"none at {KEY_TIMESTAMP}={int(self.timestamps[t])}")

    def apply(self, t: int, points: np.ndarray, rows: np.ndarray, cols_: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
        """(float64 [N, 3] returns ``points`` of frame ``t``'s TOP image at pixels (``rows``,
        ``cols_``) moved with their pixel's pose into the frame's vehicle frame, float32 [N]
        capture-time samples)."""
        f = self.f
        pose, table, i = self._pose(t)
        self.used.add(t)
        if pose is None:
            raise f.error("null per-pixel pose for a TOP range image", column=self.values,
                          expected="[H, W, 6] values", found=f"null at {f.row_keys(table, i)}")
        if pose.shape[2] != 6 or rows.max() >= pose.shape[0] or cols_.max() >= pose.shape[1]:
            raise f.error("per-pixel pose does not match the range image", column=self.shape,
                          expected="[H, W, 6] like the TOP range image",
                          found=f"{list(pose.shape)} at {f.row_keys(table, i)}")
        # one pass: the pose at each return checked finite, the return moved, its time sample
        # (reference: lidar.apply_pixel_pose and capture_time.pixel_time_offsets)
        moved, samples, j = posed_returns(points, rows, cols_, pose, invert_rigid(self.world_from_vehicle[t]),
                                          self.world_from_vehicle[t, :3, 3], self.ego_velocity[t],
                                          capture_time.MIN_EGO_SPEED_MPS, capture_time.MAX_ABS_OFFSET_S)
        if j >= 0:
            raise f.error("NaN or infinite per-pixel pose at a lidar return", column=self.values,
                          expected="finite roll, pitch, yaw, x, y, z at every pixel with a return",
                          found=f"{pose[rows[j], cols_[j]].tolist()} at pixel (row {int(rows[j])}, "
                                f"col {int(cols_[j])}) of {f.row_keys(table, i)}")
        return moved, samples

    def close(self) -> None:
        """Stop the helper after its current batch and wait for it."""
        with self.cond:
            self.stop = True
        self.thread.join()


def _check_keyable(f: ComponentFile, table: pa.Table, i: int, laser: int, height: int, width: int,
                   shape_column: str) -> None:
    """Refuse a laser name or range-image size that :func:`lidar.return_keys` cannot pack."""
    limits = dict(beam.RETURN_KEY_BITS)
    if not 0 <= laser < 1 << limits["laser"]:
        raise f.error("laser name outside the LiDAR return key", column=KEY_LASER,
                      expected=f"0 <= laser < {1 << limits['laser']}",
                      found=f"{laser} at {f.row_keys(table, i)}")
    if height > 1 << limits["row"] or width > 1 << limits["col"]:
        raise f.error("range image larger than the LiDAR return key allows", column=shape_column,
                      expected=f"H <= {1 << limits['row']}, W <= {1 << limits['col']}",
                      found=f"[{height}, {width}] at {f.row_keys(table, i)}")


def _empty_returns(n_frames: int) -> LidarReturns:
    return LidarReturns(points_vehicle=np.zeros((0, 3)), frame=np.zeros(0, np.int32),
                        laser=np.zeros(0, np.int8), return_index=np.zeros(0, np.int8),
                        row=np.zeros(0, np.int32), col=np.zeros(0, np.int32),
                        intensity=np.zeros(0, np.float32),
                        frame_offsets=np.zeros(n_frames + 1, np.int64))


def _read_camera_projection(f: ComponentFile, returns: LidarReturns, timestamps: np.ndarray,
                            returns_read: Sequence[int]) -> np.ndarray:
    out = np.full((len(returns), 6), -1, np.int16)
    blocks = _image_blocks(returns)
    lasers_read = set(np.unique(returns.laser).tolist())
    for table, i, frame, laser, r, proj in _range_images(f, timestamps, returns_read):
        if proj is None or laser not in lasers_read:
            continue
        block = blocks.get((frame, laser, r))
        if block is None:
            continue
        rows, cols_ = returns.row[block], returns.col[block]
        if proj.shape[2] != 6 or rows.max() >= proj.shape[0] or cols_.max() >= proj.shape[1]:
            raise f.error("camera projection does not match the range image",
                          column=f.comp.col(f"range_image_return{r}.shape"),
                          expected="[H, W, 6] like the lidar range image",
                          found=f"{list(proj.shape)} at {f.row_keys(table, i)}")
        out[block] = beam.camera_projection_at(proj, rows, cols_)
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
    ``lidar_camera_synced_box``, when the segment has it, fills ``Boxes.synced_shift`` and
    ``synced_camera`` (its boxes are time samples of the trajectory model, issue 16).
    Frames are ``vehicle_pose``'s timestamps in increasing order; rows of other components whose
    timestamp is not among them raise :class:`WaymoFormatError`.

    Bad numbers: NaN/inf in a transform, a transform that is not rigid, inf in a number column,
    non-finite or non-positive focal lengths, non-finite or negative box geometry and NaN/inf
    per-pixel poses at a return raise :class:`WaymoFormatError`; NaN/inf ranges are no return
    (dropped) and counted in ``Scene.source_stats["lidar_nonfinite_ranges"]``. Split, segment
    and object ids that cannot be part of a file name raise before any path is built.
    """
    check_names(split, segment)
    fs, base = filesystem(root, storage_options)
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
    files: dict[str, ComponentFile] = {}
    source_stats = {"lidar_nonfinite_ranges": 0}

    def open_component(name: str) -> ComponentFile:
        try:
            files[name] = ComponentFile(fs, base, split, name, segment)
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
        timestamps = scalar_numpy(table[KEY_TIMESTAMP], np.int64, 0)
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
        lidar_origins: dict[int, np.ndarray] = {}
        if lasers is None or len(lasers):
            cal_file = open_component("lidar_calibration")
            calibrations = _read_lidar_calibration(cal_file)
            wanted = set(calibrations) if lasers is None else {int(x) for x in lasers}
            lidar_origins = {laser: cal.vehicle_from_lidar[:3, 3].copy() for laser, cal in calibrations.items()}
            missing = wanted - set(calibrations)
            if missing:
                raise cal_file.error("requested laser has no calibration", column=KEY_LASER,
                                     expected=sorted(missing), found=sorted(calibrations))
            lidar_returns, source_stats["lidar_nonfinite_ranges"], samples = _read_lidar(
                open_component("lidar"), calibrations, wanted, returns, timestamps, cal_file,
                world_from_vehicle, lambda: open_component("lidar_pose"))
            timing = capture_time.SweepTiming()
            if samples is not None:
                timing = capture_time.fit_sweep_timing(lidar_returns.col, samples)
            lidar_returns.capture_offset_s = capture_time.capture_offsets(lidar_returns.laser,
                                                                   lidar_returns.col, timing)
            if with_camera_projection:
                lidar_returns.camera_projection = _read_camera_projection(
                    open_component("lidar_camera_projection"), lidar_returns, timestamps, returns)

        boxes = _read_boxes(open_component("lidar_box"), timestamps)
        if fs.exists(f"{base}/{split}/lidar_camera_synced_box/{segment}.parquet"):
            source_stats.update(_read_synced_boxes(open_component("lidar_camera_synced_box"), timestamps, boxes))
        return Scene(segment=segment, split=split, timestamps_micros=timestamps,
                     world_from_vehicle=world_from_vehicle, cameras=camera_frames,
                     lidar=lidar_returns, boxes=boxes,
                     source_files={name: f.url for name, f in files.items()},
                     source_stats=source_stats, lidar_origins=lidar_origins)
    finally:
        for f in files.values():
            f.close()
