"""Counts of one Waymo v2 segment without decoding images or computing points
(``drivetrack info``)."""
from __future__ import annotations

import numpy as np

from drivetrack.waymo.columns import range_images_from_columns, scalar_numpy
from drivetrack.waymo.components import (LIDAR_BATCH_ROWS, ComponentFile, check_names,
                                         filesystem)
from drivetrack.waymo.schema import (KEY_CAMERA, KEY_LASER, KEY_LASER_OBJECT, KEY_TIMESTAMP, BoxType,
                                     CameraName, LaserName)

__all__ = ["segment_summary"]

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
    check_names(split, segment)
    fs, base = filesystem(root, storage_options)
    out: dict = {"segment": segment, "split": split, "files": {}}

    def opened(name):
        f = ComponentFile(fs, base, split, name, segment)
        out["files"][name] = f.url
        return f

    with opened("vehicle_pose") as f:
        ts = np.sort(scalar_numpy(f.read_keys()[KEY_TIMESTAMP], np.int64, 0))
    out.update(num_frames=int(ts.size), start_micros=int(ts[0]), end_micros=int(ts[-1]),
               duration_s=float(ts[-1] - ts[0]) / 1e6)
    cams: dict = {}
    if fs.exists(f"{base}/{split}/camera_calibration/{segment}.parquet"):
        with opened("camera_calibration") as f:
            c = f.comp
            t = f.read(f.columns([c.col("width"), c.col("height")]))
            for name, w, h in zip(t[KEY_CAMERA].to_pylist(), t[c.col("width")].to_pylist(),
                                  t[c.col("height")].to_pylist()):
                cams[_enum_name(CameraName, name)] = {"width": w, "height": h, "images": 0}
    if fs.exists(f"{base}/{split}/camera_image/{segment}.parquet"):
        with opened("camera_image") as f:
            names = scalar_numpy(f.read_keys()[KEY_CAMERA], np.int64, 0)
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
                laser_col = scalar_numpy(table[KEY_LASER], np.int64, 0)
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
            types = scalar_numpy(t[f.comp.col("type")], np.int64, 0)
            ids = np.array(t[KEY_LASER_OBJECT].to_pylist(), dtype=object)
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
