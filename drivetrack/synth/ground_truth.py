"""Exact ground truth written beside each synthetic segment, and its loader.

Layout (``OUT/{split}/drivetrack_ground_truth/{segment}/``), every file an ``.npz`` (zip of
``.npy``; written with fixed zip timestamps so identical inputs give identical bytes):

``objects.npz``
    ``object_id`` str [K] (= ``key.laser_object_id``), ``type`` int8 [K] (``BoxType``),
    ``size`` float64 [K, 3] m (length, width, height), ``world_from_box`` float64 [K, T, 4, 4],
    ``velocity_world`` float64 [K, T, 3] m/s, ``labelled`` bool [K, T] (a ``lidar_box`` row
    exists), ``timestamps_micros`` int64 [T], ``world_from_vehicle`` float64 [T, 4, 4],
    ``camera_names`` int8 [C] (``CameraName`` order of the camera axis below).
``lidar_hits.npz`` (N = returns that hit an object, all lasers, both returns)
    ``frame`` int32 [N], ``laser`` int8 [N], ``return_index`` int8 [N] (1 or 2), ``row``,
    ``col`` int32 [N] (range-image pixel), ``object_index`` int32 [N] (into ``objects``),
    ``capture_time`` float64 [N] s since frame 0, ``point_vehicle`` float64 [N, 3] m (vehicle
    frame of the return's frame, what a perfect reader decodes), ``point_box`` float64 [N, 3] m
    (the body-frame point, box frame of its object), ``pixels`` float32 [N, C, T, 2] (x, y)
    pixels of that body point carried by the exact object pose to frame tau and projected by
    camera c (NaN where behind the camera or outside trusted distortion), ``visible`` bool
    [N, C, T] (in front, trusted, inside the image, and the first surface along the camera ray is
    that point within ``VISIBILITY_TOLERANCE_M``). With rolling-shutter cameras
    (``SynthConfig.rolling_shutter``) pixels and visibility are at the point's own capture time
    in image tau (solved with the camera's readout law, see ``drivetrack.synth.generate``); so
    are they with cameras triggered by the sweep (at the camera's pose time).
Extended truth (only when ``SynthConfig.extended_truth``: the hard world, ``camera_trigger`` or
``label_time`` "sweep"; the default output keeps its bytes)
    ``objects.npz`` adds ``role`` str [K] (what the object is there for, e.g. ``pole``,
    ``close_pass``), ``label_time_offset_s`` float64 [K, T] (when the written ``lidar_box``
    holds, minus the frame time), ``camera_time_offset_s`` float64 [C] (pose time minus frame
    time), ``world_from_camera_vehicle`` float64 [C, T, 4, 4] (the ego pose at each image's pose
    time = ``camera_image.pose``); ``lidar_hits.npz`` adds ``facing`` bool [N, C, T]: the
    point's face normal points towards the camera centre at the point's capture time (False: a
    back face, hidden by its own box), computed where the pixel is inside the image, False
    elsewhere.
``depth_{CAMERA}.npz``
    ``depth`` float32 [T, H, W]: exact z-depth (camera-frame x, metres) of the first surface
    through each pixel centre; 0 = sky (rolling shutter: at that pixel's capture time).
"""
from __future__ import annotations

import io
from dataclasses import dataclass, field

import numpy as np

from drivetrack.waymo.schema import CameraName

__all__ = ["GroundTruth", "load_ground_truth", "ground_truth_url", "write_npz",
           "VISIBILITY_TOLERANCE_M"]

#: a tracked point is visible when the first camera-ray hit lies within this distance of it.
VISIBILITY_TOLERANCE_M = 1e-4
GT_DIR = "drivetrack_ground_truth"


def ground_truth_url(root: str, split: str, segment: str) -> str:
    """``{root}/{split}/drivetrack_ground_truth/{segment}``."""
    return f"{str(root).rstrip('/')}/{split}/{GT_DIR}/{segment}"


def write_npz(url: str, arrays: dict[str, np.ndarray], compresslevel: int = 1) -> int:
    """Write a deterministic compressed ``.npz`` (:func:`drivetrack.storage.write_npz`);
    returns the number of bytes written."""
    import fsspec

    from drivetrack.storage import write_npz as _write

    _write(url, arrays, compresslevel)
    fs, path = fsspec.core.url_to_fs(url)
    return int(fs.size(path))


def _read_npz(url: str) -> dict[str, np.ndarray]:
    import fsspec

    try:
        with fsspec.open(url, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        raise FileNotFoundError(f"ground truth file {url} does not exist") from None
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


@dataclass
class GroundTruth:
    """Exact truth of one synthetic segment (see the module docstring for every array).

    ``objects`` and ``hits`` hold the arrays of ``objects.npz`` and ``lidar_hits.npz``;
    dense depth is read on demand with :meth:`depth` (a full-size segment holds ~1 GB of it).
    """
    url: str
    segment: str
    objects: dict[str, np.ndarray]
    hits: dict[str, np.ndarray]
    _depth_cache: dict = field(default_factory=dict, repr=False)

    @property
    def camera_names(self) -> list[int]:
        return [int(c) for c in self.objects["camera_names"]]

    def camera_axis(self, camera: int | str) -> int:
        """Index of ``camera`` (name or ``CameraName`` value) on the C axis of ``hits``."""
        value = int(CameraName[camera]) if isinstance(camera, str) else int(camera)
        if value not in self.camera_names:
            raise KeyError(f"segment {self.segment}: camera {camera!r} not in ground truth "
                           f"(has {[CameraName(c).name for c in self.camera_names]})")
        return self.camera_names.index(value)

    def depth(self, camera: int | str) -> np.ndarray:
        """float32 [T, H, W] exact z-depth of ``camera`` in metres (0 = sky)."""
        name = CameraName(self.camera_names[self.camera_axis(camera)]).name
        if name not in self._depth_cache:
            self._depth_cache[name] = _read_npz(f"{self.url}/depth_{name}.npz")["depth"]
        return self._depth_cache[name]


def load_ground_truth(root: str, split: str, segment: str) -> GroundTruth:
    """Load the ground truth written by ``drivetrack synth`` for one segment."""
    url = ground_truth_url(root, split, segment)
    return GroundTruth(url=url, segment=segment, objects=_read_npz(f"{url}/objects.npz"),
                       hits=_read_npz(f"{url}/lidar_hits.npz"))
