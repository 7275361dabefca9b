"""The in-memory scene: one segment's frames, poses, calibrations, LiDAR returns and boxes.

This is the contract between ingestion (``drivetrack.waymo``, which builds a :class:`Scene` from
parquet) and every later stage (depth, tracks, evaluation), which never touch column names.
Everything is columnar numpy so that a segment is loaded once and shared read-only by all the
object jobs of that segment.

Frame index ``t`` (0..T-1) orders frames by ``timestamps_micros``. Units: metres, radians,
seconds, pixels as in :mod:`drivetrack.geometry`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from drivetrack.camera.model import CameraModel
from drivetrack.geometry import box_from_center_heading

__all__ = ["LidarReturns", "Boxes", "CameraFrames", "Scene"]


@dataclass
class LidarReturns:
    """Every valid LiDAR return of a segment, all lasers and returns, concatenated over frames.

    Attributes (M = number of returns):
        points_vehicle: float64 [M, 3], metres, in the vehicle frame *of the return's frame*
            (for TOP, already corrected with the per-pixel pose for motion during the sweep).
        frame: int32 [M], frame index t.
        laser: int8 [M], ``LaserName`` value.
        return_index: int8 [M], 1 or 2.
        row, col: int32 [M], pixel of the return in its range image.
        intensity: float32 [M].
        frame_offsets: int64 [T + 1]; returns of frame t are ``[frame_offsets[t], frame_offsets[t+1])``
            (rows are sorted by frame).
        camera_projection: optional int16 [M, 6], ``lidar_camera_projection`` at the return's
            pixel: [cam1, x1, y1, cam2, x2, y2] (camera 0 = none, -1 = no projection row);
            None unless requested from the reader.
        capture_offset_s: optional float32 [M], seconds: when the return was captured, relative
            to the time of its frame's vehicle pose (the boxes' reference); estimated by the
            reader from the TOP per-pixel poses (``drivetrack.waymo.capture_time``), 0 for lasers without
            one; None when unknown (then no compensation of object motion during the sweep).
    """
    points_vehicle: np.ndarray
    frame: np.ndarray
    laser: np.ndarray
    return_index: np.ndarray
    row: np.ndarray
    col: np.ndarray
    intensity: np.ndarray
    frame_offsets: np.ndarray
    camera_projection: np.ndarray | None = None
    capture_offset_s: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.points_vehicle.shape[0])

    def of_frame(self, t: int) -> slice:
        """The slice of rows belonging to frame ``t``."""
        return slice(int(self.frame_offsets[t]), int(self.frame_offsets[t + 1]))


@dataclass
class Boxes:
    """3D box labels (``lidar_box``), one row per (object, frame); K rows.

    Attributes:
        object_id: object [K] of str, ``key.laser_object_id``.
        frame: int32 [K], frame index t.
        center: float64 [K, 3], metres, vehicle frame of frame t.
        size: float64 [K, 3], metres (length along heading, width, height).
        heading: float64 [K], radians, yaw about +z in the vehicle frame.
        type: int8 [K], ``BoxType`` value.
        speed: float64 [K, 3], m/s, box velocity (NaN where the source has none).
        num_lidar_points_in_box: int64 [K] (-1 where unknown).
        pitch, roll: optional float64 [K], radians, the box's tilt in the vehicle frame (rotation
            ``Rz(heading) Ry(pitch) Rx(roll)``, see ``geometry.box_from_center_heading``). None
            (the reader's labels, which are yaw-only): 0. Set by pose refinement
            (``drivetrack.refine``); every stage that carries points with a box uses
            :meth:`vehicle_from_box`, so they take effect wherever present.
        synced_shift: optional float64 [K, 3], metres, vehicle frame of frame t:
            ``lidar_camera_synced_box``'s centre minus the label's centre (NaN where the source has
            no synced box; None: no ``lidar_camera_synced_box`` read). Waymo defines it as
            ``speed x (t_capture - t_frame)``, t_capture when ``synced_camera`` captured the box
            centre (``drivetrack.tracks.trajectory.synced_samples``). Kept relative to the label,
            so a refined box carries it unchanged.
        synced_camera: optional int8 [K], ``most_visible_camera_name`` (0 where none).
    """
    object_id: np.ndarray
    frame: np.ndarray
    center: np.ndarray
    size: np.ndarray
    heading: np.ndarray
    type: np.ndarray
    speed: np.ndarray
    num_lidar_points_in_box: np.ndarray
    pitch: np.ndarray | None = None
    roll: np.ndarray | None = None
    synced_shift: np.ndarray | None = None
    synced_camera: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.frame.shape[0])

    def select(self, mask: np.ndarray) -> "Boxes":
        """Rows where ``mask`` (bool [K] or int index) holds."""
        return Boxes(**{k: (None if v is None else v[mask]) for k, v in self.__dict__.items()})

    def tilt(self, rows=slice(None)) -> tuple[np.ndarray | None, np.ndarray | None]:
        """``(pitch, roll)`` of rows ``rows`` (float64 [R] each, radians), or (None, None) for
        yaw-only boxes (then every transform is exactly the label's)."""
        if self.pitch is None and self.roll is None:
            return None, None
        heading = self.heading[rows]
        return (np.zeros_like(heading) if self.pitch is None else self.pitch[rows],
                np.zeros_like(heading) if self.roll is None else self.roll[rows])

    def vehicle_from_box(self, rows=slice(None)) -> np.ndarray:
        """float64 [R, 4, 4] pose of rows ``rows`` (index, mask or slice) in the vehicle frame of
        each row's frame: ``box_from_center_heading(center, heading, pitch, roll)``."""
        return box_from_center_heading(self.center[rows], self.heading[rows], *self.tilt(rows))

    def object_ids(self) -> list[str]:
        """Distinct object ids, sorted."""
        return sorted(set(self.object_id.tolist()))


@dataclass
class CameraFrames:
    """One camera's images and per-frame metadata over a segment.

    Attributes:
        model: calibration.
        jpeg: list [T] of bytes (``camera_image.image``), decoded on demand; None where missing.
        world_from_vehicle: float64 [T, 4, 4], ``camera_image.pose`` (vehicle pose at the image's
            ``pose_timestamp``), NaN where missing.
        pose_timestamp: float64 [T], seconds.
        velocity: float64 [T, 6], (vx, vy, vz) m/s of the vehicle in the world frame and
            (wx, wy, wz) rad/s its angular velocity in the vehicle frame (the official camera
            model, ``camera_model.cc``, rotates w by the pose into the world frame).
        shutter, trigger_time, readout_done_time: float64 [T], rolling-shutter parameters
            (seconds; ``shutter`` is the exposure duration).
    """
    model: CameraModel
    jpeg: list
    world_from_vehicle: np.ndarray
    pose_timestamp: np.ndarray
    velocity: np.ndarray
    shutter: np.ndarray
    trigger_time: np.ndarray
    readout_done_time: np.ndarray

    def image(self, t: int) -> np.ndarray:
        """uint8 [H, W, 3] RGB image of frame ``t``."""
        import cv2

        data = self.jpeg[t]
        if data is None:
            raise ValueError(f"camera {self.model!r} has no image at frame {t}")
        bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"frame {t}: the camera image is not a decodable JPEG")
        return bgr[..., ::-1].copy()


@dataclass
class Scene:
    """One segment, ready for annotation.

    Attributes:
        segment: ``key.segment_context_name``.
        split: ``training`` / ``validation`` / ``testing``.
        timestamps_micros: int64 [T], frame timestamps, strictly increasing.
        world_from_vehicle: float64 [T, 4, 4], ``vehicle_pose`` of each frame.
        cameras: camera name (``CameraName`` value) -> :class:`CameraFrames`.
        lidar: every valid return, see :class:`LidarReturns`.
        boxes: ``lidar_box`` labels, see :class:`Boxes`.
        source_files: component -> URL of the parquet file it came from (for provenance).
        box_refinement: object id -> flat summary of the pose refinement applied to its boxes
            (``drivetrack.refine.RefinedPoses.summary()``); empty when the labels are used as read.
        box_labels: the labelled boxes as read, when ``boxes`` holds refined poses; None when
            ``boxes`` are the labels themselves.
        source_stats: counts of what the reader dropped from the source as data, e.g.
            ``lidar_nonfinite_ranges`` (NaN / inf range values, no return).
        lidar_origins: ``LaserName`` value -> float64 [3], metres, the lidar's position in the
            vehicle frame (``lidar_calibration.extrinsic``); empty when no lidar was read.
    """
    segment: str
    split: str
    timestamps_micros: np.ndarray
    world_from_vehicle: np.ndarray
    cameras: dict[int, CameraFrames]
    lidar: LidarReturns
    boxes: Boxes
    source_files: dict[str, str] = field(default_factory=dict)
    box_refinement: dict[str, dict] = field(default_factory=dict)
    box_labels: Boxes | None = None
    source_stats: dict[str, int] = field(default_factory=dict)
    lidar_origins: dict[int, np.ndarray] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.timestamps_micros.shape[0])
