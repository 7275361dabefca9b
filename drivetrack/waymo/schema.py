"""The Waymo Open Dataset v2 perception schema, as code.

One :class:`Component` per parquet component directory (``{root}/{split}/{component}/``), with the
exact column names and arrow types of the official release
(``waymo-research/waymo-open-dataset``, ``src/waymo_open_dataset/v2/perception``). Every column is
nullable. Key columns are named ``key.<field>``; value columns ``[<ComponentClass>].<dotted.path>``.
This module is the only place in the project that spells column names: everything else asks for
them through :data:`COMPONENTS`, the ``Component`` helpers or the ``KEY_*`` constants, and joins
components on their key columns through :func:`merge_rows` (the SDK's ``v2.merge`` on shared
key columns, for numpy key arrays).

List columns compare equal whatever their child field is called (``item`` or ``element``): the
official writer and other producers differ, so nothing here depends on it.
"""
from __future__ import annotations

import enum
import re
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np
import pyarrow as pa

__all__ = [
    "CameraName", "LaserName", "BoxType", "Column", "Component", "COMPONENTS", "KEY_SEGMENT",
    "KEY_TIMESTAMP", "KEY_CAMERA", "KEY_LASER", "KEY_LASER_OBJECT", "KEY_CAMERA_OBJECT",
    "arrow_type_from_text", "types_compatible", "component", "merge_rows",
]

KEY_SEGMENT = "key.segment_context_name"
KEY_TIMESTAMP = "key.frame_timestamp_micros"
KEY_CAMERA = "key.camera_name"
KEY_LASER = "key.laser_name"
KEY_LASER_OBJECT = "key.laser_object_id"
KEY_CAMERA_OBJECT = "key.camera_object_id"


class CameraName(enum.IntEnum):
    """``key.camera_name`` values (``dataset.proto`` CameraName.Name)."""
    UNKNOWN = 0
    FRONT = 1
    FRONT_LEFT = 2
    FRONT_RIGHT = 3
    SIDE_LEFT = 4
    SIDE_RIGHT = 5


class LaserName(enum.IntEnum):
    """``key.laser_name`` values (``dataset.proto`` LaserName.Name)."""
    UNKNOWN = 0
    TOP = 1
    FRONT = 2
    SIDE_LEFT = 3
    SIDE_RIGHT = 4
    REAR = 5


class BoxType(enum.IntEnum):
    """``[LiDARBoxComponent].type`` values (``label.proto`` Label.Type)."""
    UNKNOWN = 0
    VEHICLE = 1
    PEDESTRIAN = 2
    SIGN = 3
    CYCLIST = 4


_SCALARS = {
    "string": pa.string(), "binary": pa.binary(), "bool": pa.bool_(), "int8": pa.int8(),
    "int32": pa.int32(), "int64": pa.int64(), "float": pa.float32(), "double": pa.float64(),
}


def arrow_type_from_text(text: str) -> pa.DataType:
    """Parse a type as printed in the schema table, e.g. ``fixed_size_list<item: double>[16]``."""
    text = text.strip()
    if text in _SCALARS:
        return _SCALARS[text]
    m = re.fullmatch(r"fixed_size_list<\w+: (\w+)>\[(\d+)\]", text)
    if m:
        return pa.list_(_SCALARS[m.group(1)], int(m.group(2)))
    m = re.fullmatch(r"list<\w+: (\w+)>", text)
    if m:
        return pa.list_(_SCALARS[m.group(1)])
    raise ValueError(f"unknown arrow type text {text!r}")


def types_compatible(expected: pa.DataType, found: pa.DataType) -> bool:
    """True when ``found`` is the official type ``expected``, ignoring list child names.

    ``large_list``/``large_string``/``large_binary`` variants are accepted as well: some writers
    (pandas, polars) produce them and they decode to the same values.
    """
    if pa.types.is_fixed_size_list(expected):
        return (pa.types.is_fixed_size_list(found) and found.list_size == expected.list_size
                and types_compatible(expected.value_type, found.value_type))
    if pa.types.is_list(expected):
        return ((pa.types.is_list(found) or pa.types.is_large_list(found))
                and types_compatible(expected.value_type, found.value_type))
    if pa.types.is_string(expected):
        return pa.types.is_string(found) or pa.types.is_large_string(found)
    if pa.types.is_binary(expected):
        return pa.types.is_binary(found) or pa.types.is_large_binary(found)
    return expected.equals(found)


@dataclass(frozen=True)
class Column:
    """One parquet column: its exact name and official arrow type."""
    name: str
    type: pa.DataType

    @property
    def is_key(self) -> bool:
        return self.name.startswith("key.")


@dataclass(frozen=True)
class Component:
    """One v2 component: directory name, class name and its columns in official order."""
    name: str
    class_name: str
    columns: tuple[Column, ...] = field(repr=False)

    @property
    def keys(self) -> tuple[str, ...]:
        """Key column names, the join keys shared with other components."""
        return tuple(c.name for c in self.columns if c.is_key)

    def col(self, path: str) -> str:
        """Full column name of value field ``path``, e.g. ``col("extrinsic.transform")``.

        Raises KeyError naming the component when the field does not exist.
        """
        name = f"[{self.class_name}].{path}"
        if name not in self.by_name:
            raise KeyError(f"component {self.name!r} has no column {name!r}")
        return name

    @property
    def by_name(self) -> dict[str, Column]:
        return {c.name: c for c in self.columns}

    def arrow_schema(self) -> pa.Schema:
        """The official arrow schema (list child fields named ``item``)."""
        return pa.schema([pa.field(c.name, c.type, nullable=True) for c in self.columns])


def _component(name: str, class_name: str, rows: list[tuple[str, str]]) -> Component:
    return Component(name, class_name, tuple(Column(n, arrow_type_from_text(t)) for n, t in rows))


COMPONENTS: dict[str, Component] = {}

COMPONENTS["camera_image"] = _component("camera_image", "CameraImageComponent", [
    ("key.segment_context_name", "string"),
    ("key.frame_timestamp_micros", "int64"),
    ("key.camera_name", "int8"),
    ("[CameraImageComponent].image", "binary"),
    ("[CameraImageComponent].pose.transform", "fixed_size_list<item: double>[16]"),
    ("[CameraImageComponent].velocity.linear_velocity.x", "float"),
    ("[CameraImageComponent].velocity.linear_velocity.y", "float"),
    ("[CameraImageComponent].velocity.linear_velocity.z", "float"),
    ("[CameraImageComponent].velocity.angular_velocity.x", "double"),
    ("[CameraImageComponent].velocity.angular_velocity.y", "double"),
    ("[CameraImageComponent].velocity.angular_velocity.z", "double"),
    ("[CameraImageComponent].pose_timestamp", "double"),
    ("[CameraImageComponent].rolling_shutter_params.shutter", "double"),
    ("[CameraImageComponent].rolling_shutter_params.camera_trigger_time", "double"),
    ("[CameraImageComponent].rolling_shutter_params.camera_readout_done_time", "double"),
])
COMPONENTS["camera_calibration"] = _component("camera_calibration", "CameraCalibrationComponent", [
    ("key.segment_context_name", "string"),
    ("key.camera_name", "int8"),
    ("[CameraCalibrationComponent].intrinsic.f_u", "double"),
    ("[CameraCalibrationComponent].intrinsic.f_v", "double"),
    ("[CameraCalibrationComponent].intrinsic.c_u", "double"),
    ("[CameraCalibrationComponent].intrinsic.c_v", "double"),
    ("[CameraCalibrationComponent].intrinsic.k1", "double"),
    ("[CameraCalibrationComponent].intrinsic.k2", "double"),
    ("[CameraCalibrationComponent].intrinsic.p1", "double"),
    ("[CameraCalibrationComponent].intrinsic.p2", "double"),
    ("[CameraCalibrationComponent].intrinsic.k3", "double"),
    ("[CameraCalibrationComponent].extrinsic.transform", "fixed_size_list<item: double>[16]"),
    ("[CameraCalibrationComponent].width", "int32"),
    ("[CameraCalibrationComponent].height", "int32"),
    ("[CameraCalibrationComponent].rolling_shutter_direction", "int8"),
])
COMPONENTS["lidar"] = _component("lidar", "LiDARComponent", [
    ("key.segment_context_name", "string"),
    ("key.frame_timestamp_micros", "int64"),
    ("key.laser_name", "int8"),
    ("[LiDARComponent].range_image_return1.values", "list<item: float>"),
    ("[LiDARComponent].range_image_return1.shape", "fixed_size_list<item: int32>[3]"),
    ("[LiDARComponent].range_image_return2.values", "list<item: float>"),
    ("[LiDARComponent].range_image_return2.shape", "fixed_size_list<item: int32>[3]"),
])
COMPONENTS["lidar_calibration"] = _component("lidar_calibration", "LiDARCalibrationComponent", [
    ("key.segment_context_name", "string"),
    ("key.laser_name", "int8"),
    ("[LiDARCalibrationComponent].extrinsic.transform", "fixed_size_list<item: double>[16]"),
    ("[LiDARCalibrationComponent].beam_inclination.min", "double"),
    ("[LiDARCalibrationComponent].beam_inclination.max", "double"),
    ("[LiDARCalibrationComponent].beam_inclination.values", "list<item: double>"),
])
COMPONENTS["lidar_pose"] = _component("lidar_pose", "LiDARPoseComponent", [
    ("key.segment_context_name", "string"),
    ("key.frame_timestamp_micros", "int64"),
    ("key.laser_name", "int8"),
    ("[LiDARPoseComponent].range_image_return1.values", "list<item: float>"),
    ("[LiDARPoseComponent].range_image_return1.shape", "fixed_size_list<item: int32>[3]"),
])
COMPONENTS["lidar_box"] = _component("lidar_box", "LiDARBoxComponent", [
    ("key.segment_context_name", "string"),
    ("key.frame_timestamp_micros", "int64"),
    ("key.laser_object_id", "string"),
    ("[LiDARBoxComponent].box.center.x", "double"),
    ("[LiDARBoxComponent].box.center.y", "double"),
    ("[LiDARBoxComponent].box.center.z", "double"),
    ("[LiDARBoxComponent].box.size.x", "double"),
    ("[LiDARBoxComponent].box.size.y", "double"),
    ("[LiDARBoxComponent].box.size.z", "double"),
    ("[LiDARBoxComponent].box.heading", "double"),
    ("[LiDARBoxComponent].type", "int8"),
    ("[LiDARBoxComponent].num_lidar_points_in_box", "int64"),
    ("[LiDARBoxComponent].num_top_lidar_points_in_box", "int64"),
    ("[LiDARBoxComponent].speed.x", "double"),
    ("[LiDARBoxComponent].speed.y", "double"),
    ("[LiDARBoxComponent].speed.z", "double"),
    ("[LiDARBoxComponent].acceleration.x", "double"),
    ("[LiDARBoxComponent].acceleration.y", "double"),
    ("[LiDARBoxComponent].acceleration.z", "double"),
    ("[LiDARBoxComponent].difficulty_level.detection", "int8"),
    ("[LiDARBoxComponent].difficulty_level.tracking", "int8"),
])
COMPONENTS["camera_box"] = _component("camera_box", "CameraBoxComponent", [
    ("key.segment_context_name", "string"),
    ("key.frame_timestamp_micros", "int64"),
    ("key.camera_name", "int8"),
    ("key.camera_object_id", "string"),
    ("[CameraBoxComponent].box.center.x", "double"),
    ("[CameraBoxComponent].box.center.y", "double"),
    ("[CameraBoxComponent].box.size.x", "double"),
    ("[CameraBoxComponent].box.size.y", "double"),
    ("[CameraBoxComponent].type", "int8"),
    ("[CameraBoxComponent].difficulty_level.detection", "int8"),
    ("[CameraBoxComponent].difficulty_level.tracking", "int8"),
])
COMPONENTS["vehicle_pose"] = _component("vehicle_pose", "VehiclePoseComponent", [
    ("key.segment_context_name", "string"),
    ("key.frame_timestamp_micros", "int64"),
    ("[VehiclePoseComponent].world_from_vehicle.transform", "fixed_size_list<item: double>[16]"),
])
COMPONENTS["camera_to_lidar_box_association"] = _component("camera_to_lidar_box_association", "CameraToLiDARBoxAssociationComponent", [
    ("key.segment_context_name", "string"),
    ("key.frame_timestamp_micros", "int64"),
    ("key.camera_name", "int8"),
    ("key.camera_object_id", "string"),
    ("key.laser_object_id", "string"),
])
COMPONENTS["lidar_camera_projection"] = _component("lidar_camera_projection", "LiDARCameraProjectionComponent", [
    ("key.segment_context_name", "string"),
    ("key.frame_timestamp_micros", "int64"),
    ("key.laser_name", "int8"),
    ("[LiDARCameraProjectionComponent].range_image_return1.values", "list<item: float>"),
    ("[LiDARCameraProjectionComponent].range_image_return1.shape", "fixed_size_list<item: int32>[3]"),
    ("[LiDARCameraProjectionComponent].range_image_return2.values", "list<item: float>"),
    ("[LiDARCameraProjectionComponent].range_image_return2.shape", "fixed_size_list<item: int32>[3]"),
])
COMPONENTS["projected_lidar_box"] = _component("projected_lidar_box", "ProjectedLiDARBoxComponent", [
    ("key.segment_context_name", "string"),
    ("key.frame_timestamp_micros", "int64"),
    ("key.camera_name", "int8"),
    ("key.laser_object_id", "string"),
    ("[ProjectedLiDARBoxComponent].box.center.x", "double"),
    ("[ProjectedLiDARBoxComponent].box.center.y", "double"),
    ("[ProjectedLiDARBoxComponent].box.size.x", "double"),
    ("[ProjectedLiDARBoxComponent].box.size.y", "double"),
    ("[ProjectedLiDARBoxComponent].type", "int8"),
])
COMPONENTS["lidar_camera_synced_box"] = _component("lidar_camera_synced_box", "LiDARCameraSyncedBoxComponent", [
    ("key.segment_context_name", "string"),
    ("key.frame_timestamp_micros", "int64"),
    ("key.laser_object_id", "string"),
    ("[LiDARCameraSyncedBoxComponent].most_visible_camera_name", "int8"),
    ("[LiDARCameraSyncedBoxComponent].camera_synced_box.center.x", "double"),
    ("[LiDARCameraSyncedBoxComponent].camera_synced_box.center.y", "double"),
    ("[LiDARCameraSyncedBoxComponent].camera_synced_box.center.z", "double"),
    ("[LiDARCameraSyncedBoxComponent].camera_synced_box.size.x", "double"),
    ("[LiDARCameraSyncedBoxComponent].camera_synced_box.size.y", "double"),
    ("[LiDARCameraSyncedBoxComponent].camera_synced_box.size.z", "double"),
    ("[LiDARCameraSyncedBoxComponent].camera_synced_box.heading", "double"),
])
COMPONENTS["stats"] = _component("stats", "StatsComponent", [
    ("key.segment_context_name", "string"),
    ("key.frame_timestamp_micros", "int64"),
    ("[StatsComponent].time_of_day", "string"),
    ("[StatsComponent].location", "string"),
    ("[StatsComponent].weather", "string"),
    ("[StatsComponent].lidar_object_counts.types", "list<item: int8>"),
    ("[StatsComponent].lidar_object_counts.counts", "list<item: int32>"),
    ("[StatsComponent].camera_object_counts.types", "list<item: int8>"),
    ("[StatsComponent].camera_object_counts.counts", "list<item: int32>"),
])
COMPONENTS["lidar_segmentation"] = _component("lidar_segmentation", "LiDARSegmentationLabelComponent", [
    ("key.segment_context_name", "string"),
    ("key.frame_timestamp_micros", "int64"),
    ("key.laser_name", "int8"),
    ("[LiDARSegmentationLabelComponent].range_image_return1.values", "list<item: int32>"),
    ("[LiDARSegmentationLabelComponent].range_image_return1.shape", "fixed_size_list<item: int32>[3]"),
    ("[LiDARSegmentationLabelComponent].range_image_return2.values", "list<item: int32>"),
    ("[LiDARSegmentationLabelComponent].range_image_return2.shape", "fixed_size_list<item: int32>[3]"),
])
COMPONENTS["camera_segmentation"] = _component("camera_segmentation", "CameraSegmentationLabelComponent", [
    ("key.segment_context_name", "string"),
    ("key.frame_timestamp_micros", "int64"),
    ("key.camera_name", "int8"),
    ("[CameraSegmentationLabelComponent].panoptic_label_divisor", "int32"),
    ("[CameraSegmentationLabelComponent].panoptic_label", "binary"),
    ("[CameraSegmentationLabelComponent].instance_id_to_global_id_mapping.local_instance_ids", "list<item: int32>"),
    ("[CameraSegmentationLabelComponent].instance_id_to_global_id_mapping.global_instance_ids", "list<item: int32>"),
    ("[CameraSegmentationLabelComponent].instance_id_to_global_id_mapping.is_tracked", "list<item: bool>"),
    ("[CameraSegmentationLabelComponent].sequence_id", "string"),
    ("[CameraSegmentationLabelComponent].num_cameras_covered", "binary"),
])


def merge_rows(left: Mapping[str, np.ndarray], right: Mapping[str, np.ndarray]
               ) -> tuple[np.ndarray, np.ndarray]:
    """Join the rows of ``right`` to those of ``left`` on their shared key columns.

    The numpy counterpart of the SDK's ``v2.merge`` (which joins two components on the ``key.``
    columns they share), for the integer keys the reader aligns on (timestamps, camera and laser
    names): never on row order.

    Args:
        left: key column name -> int array [L]; its key tuples must be unique (component files
            are checked for duplicate keys when read), e.g. ``{KEY_TIMESTAMP: timestamps}``.
        right: key column name -> int array [R].
    Returns:
        ``(row int64 [R], found bool [R])``: the row of ``left`` with the same values in every
        shared key column, and whether there is one (``row`` is only meaningful where found).
    Raises:
        ValueError when the two share no key column.
    """
    on = [name for name in left if name in right and name.startswith("key.")]
    if not on:
        raise ValueError(f"no shared key column to join on: left has {sorted(left)}, right has "
                         f"{sorted(right)}")
    left_cols = [np.asarray(left[name], np.int64).reshape(-1) for name in on]
    right_cols = [np.asarray(right[name], np.int64).reshape(-1) for name in on]
    n_left, n_right = left_cols[0].size, right_cols[0].size
    if len(on) == 1:
        left_key, right_key = left_cols[0], right_cols[0]
    else:  # one int64 code per distinct key tuple, shared by both sides
        both = np.stack([np.concatenate([a, b]) for a, b in zip(left_cols, right_cols)], axis=-1)
        _, code = np.unique(both, axis=0, return_inverse=True)
        code = code.reshape(-1)
        left_key, right_key = code[:n_left], code[n_left:]
    if n_left == 0:
        return np.zeros(n_right, np.int64), np.zeros(n_right, bool)
    order = np.argsort(left_key, kind="stable")
    pos = np.minimum(np.searchsorted(left_key[order], right_key), n_left - 1)
    found = left_key[order][pos] == right_key
    return order[pos].astype(np.int64), found


def component(name: str) -> Component:
    """The component called ``name``; KeyError listing the known names otherwise."""
    try:
        return COMPONENTS[name]
    except KeyError:
        raise KeyError(f"unknown Waymo v2 component {name!r}; known: {sorted(COMPONENTS)}") from None
