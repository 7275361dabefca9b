"""The track stage: one (segment, camera, object) clip -> point tracks with occlusion.

Object-frame formulation of the paper's ``X_tau = W_tau^-1 B_tau B_t^-1 W_t X_t``: every LiDAR
return of the clip is moved ONCE into its box's frame (``p_box = box_from_vehicle_t X_t``), then
carried to every target frame tau by one transform per frame (``vehicle_from_box_tau``,
``camera_from_box_tau``, ``world_from_box_tau``), vectorised as [T, n, 3] over a chunk of n points.

When the scene carries per-return capture times (``LidarReturns.capture_offset_s``) and
``TrackConfig.compensate_sweep_motion`` holds, ``p_box`` uses the box moved to each return's
capture time (constant velocity and yaw rate from the clip's boxes, :mod:`drivetrack.tracks.sweep_motion`).

Visibility of a point at tau: in front of the camera with trusted distortion, inside the image,
and not behind the scene surface: with ``D = lookup_max4(depth_tau, pixel)`` (z-depth, metres),
occluded iff ``D > 0 and D < occlusion_ratio * z`` where z is the point's z-depth from the
camera. Unknown depth (0) means no known surface in front, hence visible.

Memory: a job keeps per kept point its box-frame point, speeds, sources and ``visibles`` [N, T]
(1 byte per point and frame), never ``tracks`` or ``points3d`` (20 bytes per point and frame).
Those are recomputed from the job's transforms by its :class:`TrackSource`, a chunk of points or
frames at a time, when a writer streams them into a file (:mod:`drivetrack.tracks.writers`);
``ObjectTracks.tracks`` / ``.points3d`` materialise them whole on first access for in-memory
consumers (evaluation, previews).
"""
from __future__ import annotations

import dataclasses
import importlib
import threading
import warnings
import zlib
from dataclasses import dataclass, field

import numpy as np

from drivetrack.camera.model import CameraModel
from drivetrack.geometry import invert_rigid, rigid_velocity_world
from drivetrack.outputs import RejectionReason
from drivetrack.tracks.context import SegmentContext
from drivetrack.tracks.plan import ObjectJob
from drivetrack.tracks.sweep_motion import box_motion_world, points_box_at_capture
from drivetrack.tracks.trajectory import points_box_at, segment_trajectory
from drivetrack.visibility.facing import other_surface, own_surface
from drivetrack.waymo.schema import BoxType, CameraName

__all__ = ["ObjectTracks", "TrackSource", "ClipPoses", "clip_poses", "run_object_job", "track_speeds", "rolling_shutter_projector",
           "image_time_offsets", "fill_invalid_positions", "points_per_chunk", "frames_per_chunk",
           "occluding_objects"]

#: Point-frames per chunk of the streamed outputs: a chunk's [k, T, 2 + 3] float32 (and the
#: job's scratch) is 5 MiB; the time-major [F, N, 3] float32 + float64 temporaries of the
#: TAPVid-3D writer ~15 MiB (measured in docs/benchmarks.md, "Object-job memory").
CHUNK_POINT_FRAMES = 1 << 18


def points_per_chunk(num_frames: int) -> int:
    """Points per point-major chunk of a clip of ``num_frames`` frames (>= 1)."""
    return max(1, CHUNK_POINT_FRAMES // max(int(num_frames), 1))


def frames_per_chunk(num_points: int) -> int:
    """Frames per time-major chunk of a clip of ``num_points`` tracks (>= 1)."""
    return max(1, CHUNK_POINT_FRAMES // max(int(num_points), 1))


@dataclass
class ObjectTracks:
    """Point tracks of one clip (N tracks, T frames). Pixels (x, y), pixel i covers [i, i+1).

    Attributes:
        split, segment, camera (``CameraName`` value), object_id, object_type (``BoxType`` value).
        frames: int64 [T], the clip's frame indices in the segment.
        timestamps_micros: int64 [T].
        visibles: bool [N, T].
        points_box: float64 [N, 3], metres, each track's point in its box's frame.
        query_frames: int32 [N], clip frame of the LiDAR return that produced the track.
        lidar_sources: int32 [N, 4], (laser_name, return 1|2, range-image row, col).
        track_speed_mps: float64 [N], mean world-frame speed of each track over the clip.
        box_speed_mps: mean over the clip of the annotated box speed magnitude (NaN if none).
        speed_error_mps: float64 [N], |track_speed_mps - box_speed_mps|.
        camera_model: the camera's calibration.
        camera_from_vehicle: float64 [T, 4, 4] (vehicle frame of each frame, camera at the image
            pose); with ``world_from_vehicle`` float64 [T, 4, 4] they give camera extrinsics.
        jpeg: list [T] of the clip's JPEG bytes (references into the scene, not copies).
        source: the :class:`TrackSource` that computes ``tracks`` and ``points3d`` in chunks.
        query_pixels: float32 [N, 2], ``tracks[i, f_i]`` at the TAPVid-3D query frame ``f_i``
            (``query_frames[i]`` when visible there, else the first visible frame).
        num_nonfinite_visible, num_visible_outside_image: visible point-frames whose ``tracks``
            position is not finite / lies outside the image (sanity counts, 0 when correct).
        min_camera_distance_m: closest camera-to-box-centre distance over the clip.
        projection: ``rolling_shutter`` or ``global_shutter``.
        num_candidates: returns inside the box over the clip (before the visibility filter).
        num_dropped_invisible, num_dropped_speed: candidates dropped by each filter.
        rejection: None, or a :class:`drivetrack.outputs.RejectionReason` when no track survived.
        time_model, label_time: ``TrackConfig.time_model`` and the label-time convention the
            clip's poses used (``frame`` / ``sweep``; ``auto`` resolved per segment).
        time_residual_m: mean distance (metres) outside the box of the clip's candidate returns,
            each with the box at its capture time (0 when every return lies inside).
        num_unreliable_normals: candidates whose surface normal is too poorly supported for the
            back-face test and not on a single face of their label box
            (``TrackConfig.box_face_normals_m``; :mod:`drivetrack.visibility.facing`; the depth
            test decides for them); 0 when ``TrackConfig.back_face_max_deg`` is None.
        num_ambiguous_occlusion: (track, frame) pairs of the kept tracks, inside the image, whose
            occlusion decision was close to flipping: ``|occlusion_margin| < 1`` (below).
        occlusion_margin: float16 [N, T] or None (only with ``TrackConfig.occlusion_margins``):
            how far each decision was from flipping, signed (>= 0 on the visible side), in units
            of the ambiguity thresholds: the smallest of the depth-map test's margin ``(D - r z) /
            ambiguity_m`` (D the max-of-4 map depth, r ``occlusion_ratio``; +inf where D is
            unknown), the z-buffer's ``(farthest occluder depth over the footprint - (z - tol)) /
            ambiguity_m`` (+inf where no occluder covers the footprint) and the back-face test's
            ``(back_face_max_deg - angle) / ambiguity_deg`` (+inf for an unreliable normal); the
            tests a config switches off are left out. NaN where the point is outside the image.

    Computed on first access (then kept): ``tracks`` float32 [N, T, 2], pixels, finite
    everywhere for a track with one valid projection; meaningful where visible. Where the point is
    behind the camera or its distortion is untrusted, the position of the nearest frame with a
    valid projection is held (:func:`fill_invalid_positions`). ``points3d`` float32 [N, T, 3],
    metres, vehicle frame of each frame tau. Writers stream them instead
    (:meth:`TrackSource.point_chunks`, :meth:`TrackSource.frame_chunks`).
    """
    split: str
    segment: str
    camera: int
    object_id: str
    object_type: int
    frames: np.ndarray
    timestamps_micros: np.ndarray
    visibles: np.ndarray
    points_box: np.ndarray
    query_frames: np.ndarray
    lidar_sources: np.ndarray
    track_speed_mps: np.ndarray
    box_speed_mps: float
    speed_error_mps: np.ndarray
    camera_model: CameraModel
    camera_from_vehicle: np.ndarray
    world_from_vehicle: np.ndarray
    jpeg: list = field(repr=False)
    source: TrackSource = field(repr=False)
    query_pixels: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32), repr=False)
    num_nonfinite_visible: int = 0
    num_visible_outside_image: int = 0
    min_camera_distance_m: float = float("nan")
    projection: str = "global_shutter"
    num_candidates: int = 0
    num_dropped_invisible: int = 0
    num_dropped_speed: int = 0
    rejection: str | None = None
    time_model: str = "velocity"
    label_time: str = "frame"
    time_residual_m: float = float("nan")
    num_unreliable_normals: int = 0
    num_ambiguous_occlusion: int = 0
    occlusion_margin: np.ndarray | None = field(default=None, repr=False)
    _materialised: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def camera_name(self) -> str:
        return CameraName(self.camera).name

    @property
    def object_type_name(self) -> str:
        return BoxType(self.object_type).name

    @property
    def num_tracks(self) -> int:
        return int(self.visibles.shape[0])

    @property
    def num_frames(self) -> int:
        return int(self.frames.shape[0])

    @property
    def tracks(self) -> np.ndarray:
        """float32 [N, T, 2] (see the class docstring); computed whole on first access."""
        return self._materialise("tracks")

    @property
    def points3d(self) -> np.ndarray:
        """float32 [N, T, 3] (see the class docstring); computed whole on first access."""
        return self._materialise("points3d")

    def _materialise(self, name: str) -> np.ndarray:
        if name not in self._materialised:
            which = 0 if name == "tracks" else 1
            out = np.empty((self.num_tracks, self.num_frames, 2 if which == 0 else 3), dtype=np.float32)
            row = 0
            for chunk in self.source.point_chunks(what=(name,)):
                out[row:row + chunk[which].shape[0]] = chunk[which]
                row += chunk[which].shape[0]
            if row != out.shape[0]:
                raise RuntimeError(f"segment {self.segment!r} camera {self.camera_name} object {self.object_id!r}: "
                                   f"the track source gave {row} of {out.shape[0]} tracks")
            self._materialised[name] = out
        return self._materialised[name]


class _NumpyProjection:
    """The numpy reference projection of box-frame points (global or rolling shutter).

    ``project(chunk)`` -> ``(points_camera float64 [T, n, 3], pixels float64 [T, n, 2], valid
    bool [T, n])`` for box-frame points float64 [n, 3], exactly as the job computes them.
    """

    def __init__(self, model, rolling, projector, frames_meta, frames, camera_from_box, shift_camera,
                 world_from_box, shift_world, velocity_world, yaw_rate_world=None):
        self.model, self.rolling, self.projector, self.frames_meta = model, rolling, projector, frames_meta
        self.frames, self.camera_from_box, self.shift_camera = frames, camera_from_box, shift_camera
        self.world_from_box, self.shift_world, self.velocity_world = world_from_box, shift_world, velocity_world
        self.yaw_rate_world = yaw_rate_world

    def project(self, chunk: np.ndarray, at_capture: bool = False, towards: bool = False):
        """``at_capture``: under rolling shutter the camera-frame points (their depth) are taken at
        each point's capture time in its row (the z-buffer compares depths there), else at the
        image pose like the global path; the pixels are the same either way. ``towards`` (with
        ``at_capture``) adds a fourth result, float64 [T, n, 3]: the direction (not unit) from each
        point to the camera centre in the object's box frame at the point's capture time (the
        back-face test's; at the image pose where the point has none)."""
        points_camera = _carry(self.camera_from_box, chunk) + self.shift_camera[:, None]   # [T, n, 3]
        # from the point to the camera at the image pose, in the box frame: R^T (-p_camera)
        to_camera = -np.einsum("tji,tnj->tni", self.camera_from_box[:, :3, :3], points_camera) if towards else None
        if not self.rolling:
            pixels, valid = self.model.pixels_from_camera(points_camera)
        else:
            pixels = np.empty(points_camera.shape[:2] + (2,), dtype=np.float64)
            valid = np.zeros(points_camera.shape[:2], dtype=bool)
            if at_capture:
                from drivetrack.camera.rolling_shutter import project_world, shutter_state

                captured = np.full(points_camera.shape, np.nan)
            for tau, t in enumerate(self.frames.tolist()):
                world = _carry(self.world_from_box[tau:tau + 1], chunk)[0] + self.shift_world[tau]
                yaw_rate = 0.0 if self.yaw_rate_world is None else float(self.yaw_rate_world[tau])
                velocity = rigid_velocity_world(world, self.world_from_box[tau, :3, 3], self.velocity_world[tau],
                                                yaw_rate)
                if at_capture:
                    found = project_world(self.frames_meta, t, world, velocity)
                    pixels[tau], valid[tau], captured[tau] = found.pixels, found.valid, found.points_camera
                    if towards:
                        to_camera[tau] = _towards_camera_box(shutter_state(self.frames_meta, t), found, world, velocity,
                                                             self.world_from_box[tau], yaw_rate, to_camera[tau])
                else:
                    px, ok, _ = self.projector(self.frames_meta, t, world, velocity)
                    pixels[tau], valid[tau] = px, ok
            valid &= points_camera[..., 0] > 0
            if at_capture:
                points_camera = np.where(valid[..., None], captured, points_camera)
        if towards:
            return points_camera, pixels, valid, to_camera
        return points_camera, pixels, valid


def _towards_camera_box(state, found, world: np.ndarray, velocity: np.ndarray, world_from_box: np.ndarray,
                        yaw_rate: float, fallback: np.ndarray) -> np.ndarray:
    """float64 [n, 3]: from each point (``world`` float [n, 3] at the image pose, moving with
    ``velocity`` float [n, 3] m/s) to the camera centre at its capture time (``found``, a
    :class:`drivetrack.camera.rolling_shutter.Projection`; ``state`` the image's shutter state),
    in the box frame of the object then (``world_from_box`` float [4, 4] at the image pose,
    turning at ``yaw_rate`` rad/s about the world z): ``R0^T Rz(-w dt) (c(dt) - p - v dt)``;
    ``fallback`` float [n, 3] where the point has no capture time (not seen)."""
    if not state.rolling:
        return fallback
    dt = found.capture_time - state.pose_timestamp
    seen = np.isfinite(dt)
    dt = np.where(seen, dt, 0.0)
    d = state.pose_at(dt)[1] - world - dt[:, None] * velocity                        # world frame [n, 3]
    cos, sin = np.cos(-yaw_rate * dt), np.sin(-yaw_rate * dt)
    turned = np.column_stack([cos * d[:, 0] - sin * d[:, 1], sin * d[:, 0] + cos * d[:, 1], d[:, 2]])
    return np.where(seen[:, None], np.einsum("ji,nj->ni", world_from_box[:3, :3], turned), fallback)


class TrackSource:
    """Recomputes a clip's ``tracks`` and ``points3d`` from its transforms, a chunk at a time.

    Kernel path (global shutter, numba): :func:`drivetrack.tracks.kernel.fill_positions` over
    chunks of the kept points, :func:`~drivetrack.tracks.kernel.fill_points3d_frames` over chunks
    of frames. Numpy path (the reference; rolling shutter): the job's own computation over its
    candidate chunks (``chunk_points``), keeping the kept points of each. Either gives exactly
    (bit for bit) what the job would have materialised. Holds no depth map and no image.
    """

    def __init__(self, points_box: np.ndarray, camera_from_box: np.ndarray, shift_camera: np.ndarray,
                 vehicle_from_box: np.ndarray, camera: np.ndarray | None,
                 numpy_path: tuple | None = None):
        """``points_box`` float64 [N, 3] kept points; transforms [T, 4, 4]; ``camera`` the kernel's
        camera parameters (None for the numpy path); ``numpy_path`` = (projection, candidate
        box points float64 [n, 3], kept mask bool [n], chunk_points) for the numpy path."""
        self.points_box = np.ascontiguousarray(points_box, dtype=np.float64)
        self.camera_from_box = np.ascontiguousarray(camera_from_box, dtype=np.float64)
        self.shift_camera = np.ascontiguousarray(shift_camera, dtype=np.float64)
        self.vehicle_from_box = np.ascontiguousarray(vehicle_from_box, dtype=np.float64)
        self.camera = camera
        self.numpy_path = numpy_path

    @property
    def num_points(self) -> int:
        return int(self.points_box.shape[0])

    @property
    def num_frames(self) -> int:
        return int(self.vehicle_from_box.shape[0])

    def _numpy_chunks(self):
        """(candidate chunk float64 [n, 3], indices of its kept points) of the numpy path."""
        _, candidates, keep, step = self.numpy_path
        for start in range(0, candidates.shape[0], step):
            idx = np.flatnonzero(keep[start:start + step])
            if idx.size:
                yield candidates[start:start + step], idx

    def point_chunks(self, points: int | None = None, what: tuple[str, ...] = ("tracks", "points3d")):
        """Yield ``(tracks float32 [k, T, 2], points3d float32 [k, T, 3])`` of consecutive tracks.

        ``points`` tracks per chunk (default :func:`points_per_chunk`); the numpy path yields
        the kept points of each of its candidate chunks instead. An output not named in ``what``
        is not computed (None in its place).
        """
        t_count = self.num_frames
        with_tracks, with_points3d = "tracks" in what, "points3d" in what
        if self.numpy_path is not None:
            projection = self.numpy_path[0]
            for chunk, idx in self._numpy_chunks():
                tracks = points3d = None
                if with_tracks:
                    _, pixels, _ = projection.project(chunk)
                    tracks = fill_invalid_positions(np.swapaxes(pixels[:, idx], 0, 1).astype(np.float32))
                if with_points3d:
                    points3d = np.swapaxes(_carry(self.vehicle_from_box, chunk[idx]), 0, 1).astype(np.float32)
                yield tracks, points3d
            return
        from drivetrack.tracks import kernel

        step = points or points_per_chunk(t_count)
        for start in range(0, self.num_points, step):
            part = self.points_box[start:start + step]
            k = part.shape[0]
            tracks = np.empty((k if with_tracks else 0, t_count, 2), dtype=np.float32)
            points3d = np.empty((k if with_points3d else 0, t_count, 3), dtype=np.float32)
            kernel.fill_positions(part, self.camera_from_box, self.shift_camera, self.vehicle_from_box,
                                  self.camera, tracks, points3d, with_tracks, with_points3d)
            yield (tracks if with_tracks else None), (points3d if with_points3d else None)

    def frame_chunks(self, frames: int | None = None):
        """Yield time-major ``points3d`` float32 [F, N, 3] of consecutive frames (vehicle frame
        of each frame); ``frames`` per chunk (default :func:`frames_per_chunk`)."""
        step = frames or frames_per_chunk(self.num_points)
        n = self.num_points
        for start in range(0, self.num_frames, step):
            transforms = self.vehicle_from_box[start:start + step]
            out = np.empty((transforms.shape[0], n, 3), dtype=np.float32)
            if self.numpy_path is not None:
                row = 0
                for chunk, idx in self._numpy_chunks():
                    out[:, row:row + idx.size] = _carry(transforms, chunk[idx]).astype(np.float32)
                    row += idx.size
            else:
                from drivetrack.tracks import kernel

                kernel.fill_points3d_frames(self.points_box, transforms, out)
            yield out


def rolling_shutter_projector():
    """``drivetrack.camera.rolling_shutter.pixels_from_world`` if that module exists, else None."""
    try:
        module = importlib.import_module("drivetrack.camera.rolling_shutter")
    except ModuleNotFoundError as error:
        if error.name != "drivetrack.camera.rolling_shutter":
            raise
        return None
    return getattr(module, "pixels_from_world")


def track_speeds(points_world: np.ndarray, timestamps_micros: np.ndarray) -> np.ndarray:
    """float64 [N]: path length / duration of tracks float [T, N, 3] (metres) over the clip.

    NaN for a single-frame clip.
    """
    points_world = np.asarray(points_world, dtype=np.float64)
    seconds = (timestamps_micros[-1] - timestamps_micros[0]) * 1e-6
    if points_world.shape[0] < 2 or seconds <= 0:
        return np.full(points_world.shape[1], np.nan)
    steps = np.linalg.norm(np.diff(points_world, axis=0), axis=-1)
    return steps.sum(axis=0) / seconds


def _box_velocity_world(world_from_box: np.ndarray, timestamps_micros: np.ndarray) -> np.ndarray:
    """float64 [T, 3] box-centre velocity in the world frame (finite differences), m/s."""
    centres = world_from_box[:, :3, 3]
    if centres.shape[0] < 2:
        return np.zeros_like(centres)
    return np.gradient(centres, timestamps_micros * 1e-6, axis=0)


def _carry(dst_from_box: np.ndarray, points_box: np.ndarray) -> np.ndarray:
    """float64 [T, n, 3]: box-frame points float64 [n, 3] through transforms [T, 4, 4] (BLAS matmul)."""
    return np.matmul(points_box[None], np.swapaxes(dst_from_box[:, :3, :3], 1, 2)) + dst_from_box[:, None, :3, 3]


def image_time_offsets(scene, camera: int, frames: np.ndarray) -> np.ndarray:
    """float64 [T]: image pose time minus frame time (s) of ``frames``; 0 where unknown.

    Raises ValueError when an offset exceeds 1 s (the image does not belong to the frame).
    """
    pose_time = np.asarray(scene.cameras[camera].pose_timestamp, dtype=np.float64)[frames]
    offsets = pose_time - scene.timestamps_micros[frames] * 1e-6
    offsets = np.where(np.isfinite(offsets), offsets, 0.0)
    bad = np.flatnonzero(np.abs(offsets) > 1.0)
    if bad.size:
        raise ValueError(f"segment {scene.segment!r} camera {CameraName(camera).name}: image pose_timestamp "
                         f"differs from the frame timestamp by {offsets[bad[0]]:.3f} s at frame "
                         f"{int(frames[bad[0]])}")
    return offsets


def fill_invalid_positions(tracks: np.ndarray) -> np.ndarray:
    """float32 [N, T, 2] with every non-finite position replaced by the nearest finite one in time.

    A point behind the camera or outside the trusted distortion has no meaningful projection.
    The field's loaders cannot take NaN there (alltracker drops any track with a NaN frame, and a
    loss masked by multiplying with ``visibles`` turns NaN), so those frames hold the position of
    the nearest frame (ties: the earlier) where the projection is valid; ``visibles`` stays False
    for them. Tracks with no finite frame are left as they are (they are never visible).
    """
    finite = np.isfinite(tracks).all(axis=-1)                                   # [N, T]
    if finite.all() or tracks.shape[1] == 0:
        return tracks
    t_count = tracks.shape[1]
    frames = np.arange(t_count)
    before = np.maximum.accumulate(np.where(finite, frames, -1), axis=1)       # last finite <= t
    after = np.minimum.accumulate(np.where(finite, frames, t_count)[:, ::-1], axis=1)[:, ::-1]
    use_after = (before < 0) | ((after < t_count) & (after - frames < frames - before))
    source = np.where(use_after, after, before)
    source = np.where((source < 0) | (source >= t_count), frames, source)      # no finite frame at all
    return np.take_along_axis(tracks, source[..., None], axis=1)


def _any_rolling_frame(frames_meta, frames: np.ndarray) -> bool:
    """True when some clip frame has usable rolling-shutter data (``shutter_state(...).rolling``).

    The decision is ``drivetrack.camera.rolling_shutter.shutter_state``'s own (direction 0 or 5,
    readout <= 0 or a missing value mean global shutter), asked frame by frame; it also raises
    the same errors the projector would (a frame without a pose).
    """
    from drivetrack.camera.rolling_shutter import shutter_state

    return any(shutter_state(frames_meta, t).rolling for t in frames.tolist())


_KERNEL_WARNED = False


def _use_kernel(config) -> bool:
    """Whether the global-shutter path runs the numba kernel (``config.kernel == "numba"``).

    Falls back to the numpy path, warning once per process, when numba cannot be imported.
    """
    global _KERNEL_WARNED
    if config.kernel != "numba":
        return False
    from drivetrack.tracks.kernel import NUMBA_AVAILABLE

    if not NUMBA_AVAILABLE and not _KERNEL_WARNED:
        warnings.warn("TrackConfig.kernel='numba' but numba cannot be imported; the track stage uses "
                      "its numpy path (same results, slower)", RuntimeWarning, stacklevel=3)
        _KERNEL_WARNED = True
    return NUMBA_AVAILABLE


@dataclass
class ClipPoses:
    """Where an object is in each clip frame's image, at that image's capture time (T frames).

    Attributes:
        vehicle_from_box: float64 [T, 4, 4], the object at the frame time, in the vehicle frame of
            the frame (the labelled box under ``time_model="velocity"``).
        world_from_box: float64 [T, 4, 4], the object at the image's pose time.
        camera_from_box: float64 [T, 4, 4], camera (at the image pose) from that box; with
            ``shift_camera`` float64 [T, 3] (metres, added in the camera frame; 0 under the
            trajectory) it maps box-frame points to the camera frame for a global shutter.
        shift_world: float64 [T, 3], the same shift in the world frame.
        velocity_world: float64 [T, 3], m/s, box-centre velocity at the image's pose time.
        yaw_rate_world: float64 [T], rad/s, about the world z (0 under ``time_model="velocity"``).
        trajectory: the segment's :class:`drivetrack.tracks.trajectory.BoxTrajectory` (None under
            ``time_model="velocity"``); ``decision`` its label-time decision (dict, or None).
    A rolling-shutter projection moves a point ``p`` linearly from its pose-time position with
    ``velocity_world + yaw_rate_world z x (p - centre)``.
    """
    vehicle_from_box: np.ndarray
    world_from_box: np.ndarray
    camera_from_box: np.ndarray
    shift_camera: np.ndarray
    shift_world: np.ndarray
    velocity_world: np.ndarray
    yaw_rate_world: np.ndarray
    trajectory: object = None
    decision: dict | None = None


def clip_poses(plan, camera: int, frames: np.ndarray, rows: np.ndarray) -> ClipPoses:
    """The object's pose in each clip frame's image of ``camera``, at the image's capture time.

    ``frames`` int [T] clip frames, ``rows`` int [T] the object's box rows there. The one place
    that poses objects for projection (tracks, and visibility code that must agree with them).
    ``TrackConfig.time_model`` "trajectory": the segment's trajectory (label time per
    ``TrackConfig.label_time``) at the image pose time; "velocity": the labelled box moved along
    its finite-difference velocity from the frame time to the image pose time.
    """
    scene, config = plan.scene, plan.config
    geometry = plan.cameras[camera]
    frames = np.asarray(frames, np.int64)
    rows = np.asarray(rows, np.int64)
    image_offset_s = image_time_offsets(scene, camera, frames)
    if config.time_model == "trajectory":
        trajectory, decision = segment_trajectory(plan, config.label_time)
        image_time = trajectory.frame_time_s[rows] + image_offset_s
        _, _, _, _, velocity, yaw_rate = trajectory.motion(rows, image_time)
        world_from_box = trajectory.world_from_box(rows, image_time)
        camera_from_box = geometry.camera_from_world[frames] @ world_from_box
        zeros = np.zeros((frames.size, 3))
        vehicle_from_box = invert_rigid(scene.world_from_vehicle[frames]) @ trajectory.world_from_box(
            rows, trajectory.frame_time_s[rows])
        return ClipPoses(vehicle_from_box, world_from_box, camera_from_box, zeros, zeros.copy(), velocity, yaw_rate,
                         trajectory, decision)
    timestamps = scene.timestamps_micros[frames].astype(np.int64)
    vehicle_from_box = scene.boxes.vehicle_from_box(rows)
    world_from_box = scene.world_from_vehicle[frames] @ vehicle_from_box
    camera_from_box = geometry.camera_from_vehicle[frames] @ vehicle_from_box
    velocity_world = _box_velocity_world(world_from_box, timestamps)
    # Boxes and LiDAR are at the frame timestamp, the image at its pose timestamp: move the
    # object along its velocity by the difference (camera frame shift per clip frame).
    shift_world = image_offset_s[:, None] * velocity_world                                  # [T,3]
    shift_camera = np.einsum("tij,tj->ti", geometry.camera_from_world[frames, :3, :3], shift_world)
    return ClipPoses(vehicle_from_box, world_from_box, camera_from_box, shift_camera, shift_world, velocity_world,
                     np.zeros(frames.size))


def _points_box(plan, frames: np.ndarray, rows: np.ndarray, poses: ClipPoses, lidar_rows: np.ndarray,
                source_clip: np.ndarray) -> np.ndarray:
    """float64 [n, 3]: an object's returns ``lidar_rows`` (from clip frame ``source_clip``) in its box frame.

    ``frames``, ``rows`` int [T] the clip frames and the object's box rows there; ``poses`` its
    :func:`clip_poses`. Under the trajectory the box is taken at each return's capture time;
    under ``velocity`` the box moves during the sweep when ``compensate_sweep_motion``. In chunks
    of ``TrackConfig.chunk_points`` returns: the per-return poses ([k, 4, 4] and the trajectory's
    terms) stay a chunk's (each return's point is its own, so the result is the same).
    """
    out = np.empty((lidar_rows.size, 3), dtype=np.float64)
    step = int(plan.config.chunk_points)
    for start in range(0, lidar_rows.size, step):
        out[start:start + step] = _points_box_chunk(plan, frames, rows, poses, lidar_rows[start:start + step],
                                                    source_clip[start:start + step])
    return out


def _points_box_chunk(plan, frames: np.ndarray, rows: np.ndarray, poses: ClipPoses, lidar_rows: np.ndarray,
                      source_clip: np.ndarray) -> np.ndarray:
    """:func:`_points_box` of one chunk of returns."""
    scene, config = plan.scene, plan.config
    boxes, lidar = scene.boxes, scene.lidar
    vehicle_from_box = poses.vehicle_from_box
    box_from_vehicle = invert_rigid(vehicle_from_box)
    if poses.trajectory is not None:
        # ... with the object at each return's capture time, on its trajectory
        offsets_s = (lidar.capture_offset_s[lidar_rows].astype(np.float64)
                     if config.compensate_sweep_motion and lidar.capture_offset_s is not None else 0.0)
        world_from_vehicle = scene.world_from_vehicle[frames][source_clip]                   # [n,4,4]
        points_world = (np.einsum("nij,nj->ni", world_from_vehicle[:, :3, :3], lidar.points_vehicle[lidar_rows])
                        + world_from_vehicle[:, :3, 3])
        return points_box_at(poses.trajectory, rows[source_clip],
                             poses.trajectory.frame_time_s[rows][source_clip] + offsets_s, points_world)
    if config.compensate_sweep_motion and lidar.capture_offset_s is not None:
        # ... with the box at each return's capture time (object motion during the sweep).
        timestamps = scene.timestamps_micros[frames].astype(np.int64)
        world_from_box = scene.world_from_vehicle[frames] @ vehicle_from_box
        yaw_rate = box_motion_world(world_from_box, timestamps * 1e-6)[1]
        velocity_vehicle = np.einsum("tji,tj->ti", scene.world_from_vehicle[frames, :3, :3], poses.velocity_world)
        return points_box_at_capture(lidar.points_vehicle[lidar_rows], lidar.capture_offset_s[lidar_rows],
                                     boxes.center[rows][source_clip], boxes.heading[rows][source_clip],
                                     velocity_vehicle[source_clip], yaw_rate[source_clip],
                                     *(None if a is None else a[source_clip] for a in boxes.tilt(rows)))
    return np.einsum("nij,nj->ni", box_from_vehicle[source_clip, :3, :3], lidar.points_vehicle[lidar_rows]) \
        + box_from_vehicle[source_clip, :3, 3]


#: Angle (radians) added to the sum of two objects' angular radii before an object is skipped as an
#: occluder of another (:func:`_occluders`): label boxes are at the frame time, images a few tens
#: of milliseconds away, and a box centre moves a degree or two in that time beside the ego.
_OCCLUDER_ANGLE_MARGIN_RAD = np.radians(5.0)


def _surfel_cube_m(config) -> float:
    """Side (metres) of the cubes object surfaces are thinned to, one return each, and whose means
    the back-face normals are fitted on: ``TrackConfig.surfel_cube_m`` (2.5 cm; until 2026-12-02
    half the splat footprint ``surfel_radius_m``, then 5 cm; measured on the small hard world, a
    cube of a whole footprint dropped OA). The footprint is 2 cm now and the closing of
    ``occluder_fill_px`` spans the gaps between splats; finer cubes would change the normals'
    neighbourhoods (back faces called visible on the exact medium world 39 -> 83 with 1 cm cubes)."""
    return float(config.surfel_cube_m)


def depth_lookup_grow_px(plan) -> int:
    """The depth map look-up's growth in pixels for every clip of the segment (``lookup_max4``'s
    ``grow_px``): ``TrackConfig.depth_lookup_px`` under ``occlusion: surface`` where the labels
    jitter by ``depth_lookup_min_jitter_m`` or more (:func:`drivetrack.tracks.plan.label_jitter_m`
    of the boxes the tracks use, measured once per segment), else 0 (the max-of-4)."""
    config = plan.config
    if config.occlusion != "surface" or config.depth_lookup_px == 0:
        return 0
    if config.depth_lookup_min_jitter_m is None:
        return int(config.depth_lookup_px)
    return int(config.depth_lookup_px) if segment_label_jitter_m(plan) >= float(config.depth_lookup_min_jitter_m) else 0


def segment_label_jitter_m(plan) -> float:
    """:func:`drivetrack.tracks.plan.label_jitter_m` of the plan's scene, measured once per segment."""
    jitter = plan.occluder_cache.get("label_jitter_m")
    if jitter is None:
        from drivetrack.tracks.plan import label_jitter_m

        jitter = plan.occluder_cache.setdefault("label_jitter_m", label_jitter_m(plan.scene))
    return jitter


def _object_rows(boxes, object_id: str) -> np.ndarray:
    """int64 [R]: the box rows of ``object_id``, in frame order."""
    rows = np.flatnonzero(boxes.object_id == object_id)
    return rows[np.argsort(boxes.frame[rows], kind="stable")]


def _segment_points(plan, object_id: str, poses, with_rows: bool = False):
    """float64 [m, 3]: all of ``object_id``'s returns over the segment in its box frame (on the
    trajectory of ``poses``): those inside its boxes grown by ``segment_margin_m``
    (:func:`_segment_selection`), or with None the tracked points' selection. ``with_rows``:
    ``(points, lidar_rows int [m], source int [m])``, each return's lidar row and its place in the
    object's box rows (:func:`_object_rows`)."""
    boxes = plan.scene.boxes
    all_rows = _object_rows(boxes, object_id)
    if plan.config.segment_margin_m is None:
        lidar_rows, source = plan.box_points(all_rows)
    else:
        from drivetrack.tracks.plan import box_members

        lidar_rows, source = box_members(*_segment_selection(plan), all_rows)
    points = _points_box(plan, boxes.frame[all_rows].astype(np.int64), all_rows, poses, lidar_rows, source)
    return (points, lidar_rows, source) if with_rows else points


def _segment_selection(plan) -> tuple[np.ndarray, np.ndarray]:
    """``(offsets, index)`` (:func:`drivetrack.tracks.plan.select_object_points`) of every box row
    of the objects whose returns the track stage reads (``returns_type_values``), grown by
    ``segment_margin_m`` (:func:`_cached_selection`)."""
    config, boxes = plan.config, plan.scene.boxes
    return _cached_selection(plan, "#segment", float(config.segment_margin_m),
                             lambda: np.flatnonzero(np.isin(boxes.type, config.returns_type_values)))


def _cached_selection(plan, key: str, margin_m: float, rows_of) -> tuple[np.ndarray, np.ndarray]:
    """``(offsets, index)`` (:func:`drivetrack.tracks.plan.select_object_points`) of the box rows
    ``rows_of()`` (int [R]) grown by ``margin_m``: one pass over the segment's returns for all of
    them (a pass per object scans each frame's returns once per object), made when the first
    object needs it and cached in ``plan.occluder_cache[key]``."""
    from dataclasses import replace

    from drivetrack.tracks.plan import select_object_points

    cache = plan.occluder_cache
    grown = cache.get(key)
    if grown is None:
        # the other objects' jobs wait for it rather than make it again (the lock leaves the
        # cache once it is made: a plan sent to another process carries no lock)
        with cache.setdefault(f"{key}-lock", threading.Lock()):
            grown = cache.get(key)
            if grown is None:
                grown = select_object_points(plan.scene, replace(plan.config, box_margin_m=margin_m), rows_of())
                cache[key] = grown
        cache.pop(f"{key}-lock", None)
    return grown


def _segment_clouds(plan, object_id: str, poses) -> tuple[np.ndarray, ...]:
    """``(surface, normals_cloud, lidar_rows, source)``: the returns of :func:`segment_surface`
    as they were measured (before any snap) and :func:`segment_normals_cloud`, both from one pass
    over the object's returns, and the surface returns' lidar rows and places in the object's box
    rows (:func:`_segment_points`), cached in ``plan.occluder_cache``."""
    from drivetrack.visibility.zbuffer import surfel_first_and_means

    clouds = plan.occluder_cache.get(object_id)
    if clouds is None:
        points_box, lidar_rows, source = _segment_points(plan, object_id, poses, with_rows=True)
        cube_m = _surfel_cube_m(plan.config)
        first, means = surfel_first_and_means(points_box, cube_m)
        clouds = (points_box[first], means, lidar_rows[first], source[first])
        plan.occluder_cache[object_id] = clouds
    return clouds


def segment_surface(plan, object_id: str, poses) -> np.ndarray:
    """float64 [m, 3]: all of ``object_id``'s returns over the segment in its box frame, thinned
    to one per cube of ``surfel_cube_m`` (the first, a return itself: the z-buffer's
    surface, its hull and roof fill; the part of its box it fills, :func:`segment_solid_bounds`);
    computed once per object and segment
    (``plan.occluder_cache``). ``poses``: any :func:`clip_poses` of the object on the segment's
    trajectory (the returns' box-frame positions do not depend on the camera or the clip).

    Where the returns carry range noise (the object's normals were refitted for it,
    ``CloudNormals.noise_cube_m``) and ``TrackConfig.surface_snap_segment``, each of these returns
    moves along its own lidar ray onto the object's surface, as the tracked points do
    (:func:`_snapped_surface`): over a segment the ego sees an object from many directions, and a
    return's range noise along one sweep's ray lies across the view of another image, so the
    measured cloud is a shell centimetres thicker than the object all round, and every outline
    drawn from it (another object's splats, the part of its box it fills) grew by as much
    (docs/visibility.md, "Occluder surfaces under range noise"). Exact ranges: the returns as
    measured, bit for bit."""
    return _segment_snapped(plan, object_id, poses)[0]


def segment_returns_by_frame(plan, object_id: str, poses) -> tuple[np.ndarray, np.ndarray]:
    """``(points_box float64 [m, 3], frame int64 [m])``: every one of ``object_id``'s returns over
    the segment in its box frame (not thinned, not snapped; :func:`_segment_points`) and the frame
    each was measured in, once per object and segment (``plan.occluder_cache``): the surface an
    object of ``TrackConfig.occluder_recent_types`` hides others with, an image's near frames'
    returns at a time (:func:`_occluders`)."""
    key = f"{object_id}#by-frame"
    if key not in plan.occluder_cache:
        points_box, _, source = _segment_points(plan, object_id, poses, with_rows=True)
        frame = plan.scene.boxes.frame[_object_rows(plan.scene.boxes, object_id)][source].astype(np.int64)
        plan.occluder_cache[key] = (np.ascontiguousarray(points_box, dtype=np.float64), frame)
    return plan.occluder_cache[key]


def _hides_with_recent(plan, object_id: str, box_type: int, poses) -> bool:
    """Whether ``object_id``, of ``box_type`` and posed by ``poses`` (its :func:`clip_poses` in the
    clip's images), hides with its recent returns rather than its segment's surface: it is of
    ``TrackConfig.occluder_recent_types``, within ``occluder_recent_max_m`` of the camera by the
    median over the images, and its segment's returns are noisy (its back-face normals were
    fitted on coarser cubes for it, ``CloudNormals.noise_cube_m``, the test the segment snap
    takes): returns that agree over the segment draw it as it is, from every frame."""
    config = plan.config
    if poses.trajectory is None or box_type not in config.occluder_recent_type_values:
        return False
    if config.occluder_recent_max_m is not None:
        distance = np.linalg.norm(poses.camera_from_box[:, :3, 3] + poses.shift_camera, axis=1)
        if np.median(distance) > float(config.occluder_recent_max_m):
            return False
    return getattr(segment_cloud_normals(plan, object_id, poses), "noise_cube_m", None) is not None


def segment_solid_bounds(plan, object_id: str, poses) -> np.ndarray:
    """float64 [2, 3]: the low and high corners (box frame, metres) of :func:`segment_surface`'s
    returns the part of the object's box its returns fill is taken from
    (:func:`drivetrack.visibility.solid_extents` reads no more of them). Where the surface was
    snapped, each face is at the outermost return the snap *moved* when that lies within
    ``surface_snap_max_m`` of the outermost of all: a return it could not move (no surface round
    it, its ray grazing) keeps its noise, and the extremes are such returns (on a 30 cm pole 3-6
    cm beyond it); farther in, the snap did not reach that face, which keeps the outermost return.
    Elsewhere the outermost returns, as measured."""
    surface, moved = _segment_snapped(plan, object_id, poses)
    if not surface.shape[0]:
        return np.zeros((0, 3))
    lo, hi = surface.min(axis=0), surface.max(axis=0)
    if moved is not None and moved.any():
        reach = float(plan.config.surface_snap_max_m)
        moved_lo, moved_hi = surface[moved].min(axis=0), surface[moved].max(axis=0)
        lo = np.where(moved_lo - lo <= reach, moved_lo, lo)
        hi = np.where(hi - moved_hi <= reach, moved_hi, hi)
    return np.stack([lo, hi])


def _segment_snapped(plan, object_id: str, poses) -> tuple[np.ndarray, np.ndarray | None]:
    """``(surface, moved bool [m] or None)``: :func:`segment_surface` and which of its returns
    the snap moved (None: not snapped), cached per object and segment."""
    raw = _segment_clouds(plan, object_id, poses)[0]
    config = plan.config
    if not config.surface_snap_segment or config.surface_snap_max_m is None or poses.trajectory is None:
        return raw, None
    key = f"{object_id}#surface"
    if key not in plan.occluder_cache:
        plan.occluder_cache[key] = _snapped_surface(plan, object_id, poses)
    return plan.occluder_cache[key]


#: :func:`_snapped_surface`: the frames either side of a return's whose returns make the surface
#: it is moved onto (the tracked points take :data:`drivetrack.visibility.facing.SNAP_WINDOW_FRAMES`)
SEGMENT_SNAP_WINDOW_FRAMES = 2


def _lidar_rays_box(scene, lidar_rows: np.ndarray, box_from_vehicle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(sensor_box, rays_box)`` float64 [n, 3]: the lidar that measured each return ``lidar_rows``
    (int [n]) and the ray from it to the return (any length), in the box frame given per return by
    ``box_from_vehicle`` float [n, 4, 4]."""
    from drivetrack.visibility import sensor_positions

    sensor_vehicle = sensor_positions(scene.lidar.laser[lidar_rows], scene.lidar_origins)          # [n, 3]
    rotation = box_from_vehicle[:, :3, :3]
    sensor_box = np.einsum("nij,nj->ni", rotation, sensor_vehicle) + box_from_vehicle[:, :3, 3]
    rays_box = np.einsum("nij,nj->ni", rotation, scene.lidar.points_vehicle[lidar_rows] - sensor_vehicle)
    return sensor_box, rays_box


def _snapped_surface(plan, object_id: str, poses) -> tuple[np.ndarray, np.ndarray | None]:
    """``(surface, moved)``: :func:`segment_surface` with its returns moved along their rays onto
    the object's surface (:func:`drivetrack.visibility.points_on_surface`, with the normals and
    the surface the tracked points take: :func:`segment_cloud_normals`,
    :func:`segment_surface_cloud`) and which of them moved; the returns as measured and None where
    the normals saw no range noise (or there are none) or nothing moved."""
    from drivetrack.visibility import points_on_surface, surfel_normals

    raw, _, lidar_rows, source = _segment_clouds(plan, object_id, poses)
    fitted = segment_cloud_normals(plan, object_id, poses)
    if fitted is None or getattr(fitted, "noise_cube_m", None) is None or not raw.shape[0]:
        return raw, None
    scene, config = plan.scene, plan.config
    boxes = scene.boxes
    all_rows = _object_rows(boxes, object_id)
    frames = boxes.frame[all_rows].astype(np.int64)
    trajectory = poses.trajectory
    # each return's sensor and ray in its box frame at its frame time (directions: the box's
    # motion between frame and capture time turns them by a fraction of a degree)
    box_from_vehicle = (invert_rigid(trajectory.world_from_box(all_rows, trajectory.frame_time_s[all_rows]))
                        @ scene.world_from_vehicle[frames])[source]                             # [m, 4, 4]
    sensor_box, rays_box = _lidar_rays_box(scene, lidar_rows, box_from_vehicle)
    surfels = surfel_normals(raw, sensor_box, fitted=fitted, transfer=config.normal_transfer)
    moved, was_moved = points_on_surface(raw, frames[source], rays_box, surfels.normal,
                                         lambda: segment_surface_cloud(plan, object_id, poses), surfels.reliable,
                                         float(config.surface_snap_max_m), window=SEGMENT_SNAP_WINDOW_FRAMES)
    return moved, (was_moved if was_moved.any() else None)


def segment_roof_fill(plan, object_id: str, poses) -> np.ndarray:
    """float64 [h, 3]: the unsampled part of ``object_id``'s roof over the segment (box frame;
    :func:`drivetrack.visibility.zbuffer.roof_fill` of :func:`segment_surface`, on a grid of 1.5
    ``surfel_radius_m``: each fill point's footprint, ``surfel_radius_m`` either side, overlaps
    its neighbours'), computed once per object and segment (``plan.occluder_cache``)."""
    from drivetrack.visibility.zbuffer import roof_fill

    key = f"{object_id}#roof"
    if key not in plan.occluder_cache:
        plan.occluder_cache[key] = roof_fill(segment_surface(plan, object_id, poses),
                                             1.5 * float(plan.config.surfel_radius_m),
                                             spanned=_segment_spanned(plan, object_id, poses))
    return plan.occluder_cache[key]


def _segment_spanned(plan, object_id: str, poses):
    """:func:`drivetrack.visibility.zbuffer.returns_hull` of :func:`segment_surface`: the convex
    hull both the roof fill and the occluder hull start from, once per object and segment
    (``plan.occluder_cache``)."""
    from drivetrack.visibility.zbuffer import returns_hull

    key = f"{object_id}#spanned"
    if key not in plan.occluder_cache:
        plan.occluder_cache[key] = returns_hull(segment_surface(plan, object_id, poses))
    return plan.occluder_cache[key]


def segment_normals_cloud(plan, object_id: str, poses) -> np.ndarray:
    """float64 [m, 3]: the same returns as :func:`segment_surface`, each cube's *mean* instead
    of its first return (:func:`drivetrack.visibility.zbuffer.surfel_means`): the neighbourhoods
    of the back-face normals. A return's range carries centimetres of noise; the mean of the
    returns of a 2.5 cm cube carries less, and the cubes keep a sharp edge sharp."""
    return _segment_clouds(plan, object_id, poses)[1]


def segment_cloud_normals(plan, object_id: str, poses):
    """The :func:`drivetrack.visibility.cloud_normals` of :func:`segment_normals_cloud` (None when
    it has fewer points than ``normal_neighbours``), or of coarser cubes' means where the returns
    carry range noise (``normal_noise_cubes``; :func:`drivetrack.visibility.facing.noise_aware_normals`),
    computed once per object and segment (``plan.occluder_cache``): every camera's clip of the
    object takes its points' normals from them."""
    from drivetrack.visibility.facing import noise_aware_normals

    key = f"{object_id}#normals"
    if key not in plan.occluder_cache:
        config = plan.config
        plan.occluder_cache[key] = noise_aware_normals(
            segment_normals_cloud(plan, object_id, poses), _surfel_cube_m(config), config.normal_neighbours,
            config.normal_neighbourhood, config.normal_noise_cubes,
            returns_of=lambda: _segment_points(plan, object_id, poses), precise_m=config.normal_precise_m)
    return plan.occluder_cache[key]


def _pocket_points(plan, object_id: str, poses, p_box: np.ndarray, size: np.ndarray) -> np.ndarray:
    """bool [n]: the points ``p_box`` float [n, 3] (box frame) of ``object_id`` that lie in a pocket
    of its convex hull (:func:`drivetrack.visibility.zbuffer.pocket_points`; ``size`` float [3],
    its label box's). On the trajectory with the segment's normals the pockets are found once per
    object among the cubes the normals are fitted on (:func:`segment_cloud_normals`: those of
    :func:`segment_normals_cloud`, coarser under range noise; ``plan.occluder_cache``) and each
    point takes its nearest cube's; otherwise among the points themselves, against the hull of
    their own thinned cloud."""
    from drivetrack.visibility.zbuffer import pocket_points, surfel_subsample

    if poses.trajectory is not None and plan.config.normals_from == "segment":
        fitted = segment_cloud_normals(plan, object_id, poses)
        if fitted is None:
            return np.zeros(p_box.shape[0], dtype=bool)
        key = f"{object_id}#pockets"
        if key not in plan.occluder_cache:
            rows = _object_rows(plan.scene.boxes, object_id)
            half = 0.5 * np.median(plan.scene.boxes.size[rows], axis=0)
            plan.occluder_cache[key] = pocket_points(fitted.cloud, half, fitted.cloud)
        flags = plan.occluder_cache[key]
        if not flags.any():                       # a convex object (any box-shaped one): nothing to look up
            return np.zeros(p_box.shape[0], dtype=bool)
        return flags[fitted.nearest(p_box)]
    cloud = p_box[surfel_subsample(p_box, _surfel_cube_m(plan.config))]
    return pocket_points(p_box, 0.5 * np.asarray(size, np.float64), cloud)


def _grown_selection(plan) -> tuple[np.ndarray, np.ndarray]:
    """``(offsets, index)`` (:func:`drivetrack.tracks.plan.select_object_points`) of every box row
    of the plan's tracked objects, grown by ``surface_snap_margin_m`` (:func:`_cached_selection`)."""
    boxes = plan.scene.boxes
    tracked = sorted({job.object_id for job in plan.jobs})
    return _cached_selection(plan, "#grown", plan.config.surface_snap_margin_m,
                             lambda: np.flatnonzero(np.isin(boxes.object_id.astype(str), tracked)))


def segment_surface_cloud(plan, object_id: str, poses):
    """The :func:`drivetrack.visibility.surface_cloud` of all of ``object_id``'s returns over the
    segment inside its boxes grown by ``surface_snap_margin_m`` (both sides of a noisy surface;
    :func:`_grown_selection`), cached per object and segment (``plan.occluder_cache``); None
    without returns or normals."""
    from drivetrack.tracks.plan import box_members
    from drivetrack.visibility import surface_cloud

    key = f"{object_id}#snap"
    if key not in plan.occluder_cache:
        fitted = segment_cloud_normals(plan, object_id, poses)
        surface = None
        if fitted is not None:
            boxes = plan.scene.boxes
            all_rows = _object_rows(boxes, object_id)
            offsets, index = _grown_selection(plan)
            lidar_rows, source = box_members(offsets, index, all_rows)
            points_box = _points_box(plan, boxes.frame[all_rows].astype(np.int64), all_rows, poses, lidar_rows, source)
            surface = surface_cloud(points_box, boxes.frame[all_rows][source], fitted)
        plan.occluder_cache[key] = surface
    return plan.occluder_cache[key]


def segment_surface_radius(plan, object_id: str, poses) -> np.ndarray:
    """float64 [m]: the splat radius (metres) of each point of :func:`segment_surface`: from the
    local spacing, ``surfel_spacing_scale`` x the distance to the 4th nearest neighbour, within
    [``surfel_radius_m``, ``surfel_max_radius_m``]; cached with the surface."""
    from scipy.spatial import cKDTree

    key = f"{object_id}#radius"
    radius = plan.occluder_cache.get(key)
    if radius is None:
        config = plan.config
        points_box = segment_surface(plan, object_id, poses)
        k = 5                                                   # the point itself and 4 neighbours
        if points_box.shape[0] >= k:
            dist, _ = cKDTree(points_box).query(points_box, k=k)
            spacing = dist[:, -1]
        else:
            spacing = np.full(points_box.shape[0], np.inf)
        radius = np.clip(config.surfel_spacing_scale * spacing, config.surfel_radius_m, config.surfel_max_radius_m)
        plan.occluder_cache[key] = radius
    return radius


def _can_occlude(boxes, camera_from_vehicle: np.ndarray, rows: np.ndarray, at: np.ndarray,
                 target_camera: np.ndarray, target_radius_m: np.ndarray) -> np.ndarray:
    """bool [r]: which box rows ``rows`` (int [r]) may hide part of a target object in their
    frame's image: not when the row's bounding sphere lies entirely farther from the camera than
    the target's far side, nor when it is seen at an angle from the target's that their angular
    radii (plus :data:`_OCCLUDER_ANGLE_MARGIN_RAD`) cannot bridge.

    ``camera_from_vehicle`` float64 [F, 4, 4] per segment frame; ``at`` int [r], each row's index
    into the target's ``target_camera`` float64 [T, 3] (its centre, camera frame, metres) and
    ``target_radius_m`` float64 [T].
    """
    frame = boxes.frame[rows]
    # distance from the camera centre to each candidate box's centre, minus its half diagonal
    centre_camera = (np.einsum("nij,nj->ni", camera_from_vehicle[frame, :3, :3], boxes.center[rows])
                     + camera_from_vehicle[frame, :3, 3])
    radius = 0.5 * np.linalg.norm(boxes.size[rows], axis=-1)
    distance = np.linalg.norm(centre_camera, axis=-1)
    target_distance = np.linalg.norm(target_camera, axis=-1)[at]
    near = distance - radius < target_distance + target_radius_m[at]
    # ... and whose angular disc can overlap the target's in the image
    cosine = np.einsum("ni,ni->n", centre_camera, target_camera[at]) / np.maximum(distance * target_distance, 1e-9)
    apart = np.arccos(np.clip(cosine, -1.0, 1.0))
    reach = (np.arcsin(np.clip(radius / np.maximum(distance, 1e-9), 0.0, 1.0))
             + np.arcsin(np.clip(target_radius_m[at] / np.maximum(target_distance, 1e-9), 0.0, 1.0)))
    return near & (apart <= reach + _OCCLUDER_ANGLE_MARGIN_RAD)


def occluding_objects(plan) -> set[str]:
    """Object ids of the labelled objects of the annotated or occluding types
    (``TrackConfig.object_types``, ``occluder_types``: only they have returns) that may hide part
    of some job's object in some clip image
    (:func:`_can_occlude`, from the labels at frame time: no returns needed), the jobs' own
    objects excluded unless they occlude another. These are the other objects the
    occlusion z-buffer (:func:`_occluders`) carries; the pose refinement refines them too
    (``drivetrack.annotate.refine_scene``), so that a noisily labelled occluder's surface is as
    sharp as a tracked object's."""
    scene = plan.scene
    boxes = scene.boxes
    found: set[str] = set()
    typed = np.isin(boxes.type, plan.config.returns_type_values)    # only these have returns
    slot = np.full(scene.num_frames, -1, dtype=np.int64)
    for job in plan.jobs:
        frames, rows = job.frames, job.box_rows
        slot[frames] = np.arange(frames.size)
        geometry = plan.cameras[job.camera]
        others = np.flatnonzero((slot[boxes.frame] >= 0) & (boxes.object_id != job.object_id) & typed)
        if others.size:
            target = (np.einsum("tij,tj->ti", geometry.camera_from_vehicle[frames, :3, :3], boxes.center[rows])
                      + geometry.camera_from_vehicle[frames, :3, 3])
            hit = _can_occlude(boxes, geometry.camera_from_vehicle, others, slot[boxes.frame[others]],
                               target, 0.5 * np.linalg.norm(boxes.size[rows], axis=-1))
            found.update(np.unique(boxes.object_id[others[hit]]).astype(str).tolist())
        slot[frames] = -1
    return found


#: Under a rolling shutter an occluder's returns are solved for their capture time only within
#: this fraction of the image's larger side of the tracked object's disc (at the image pose; the
#: readout moves an object beside the ego by tens of pixels relative to another).
_ROLLING_PAD = 0.1


def _near_windows(model: CameraModel, centre_camera: np.ndarray,
                 radius_m: np.ndarray) -> list[tuple[float, float, float, float]]:
    """Per clip frame ``(x_lo, x_hi, y_lo, y_hi)`` pixels: the square round the image disc of the
    sphere of centre ``centre_camera`` float [T, 3] (camera frame, metres) and radius ``radius_m``
    float [T], padded by ``_ROLLING_PAD`` of the image; infinite (everywhere) when the sphere
    reaches the camera or its centre does not project. (One projection for all T frames.)"""
    pad = _ROLLING_PAD * max(model.width, model.height)
    centre_camera = np.asarray(centre_camera, np.float64).reshape(-1, 3)
    radius_m = np.asarray(radius_m, np.float64).reshape(-1)
    centre_px, ok = model.pixels_from_camera(centre_camera)
    out = []
    for s in range(centre_camera.shape[0]):
        distance, radius = float(np.linalg.norm(centre_camera[s])), float(radius_m[s])
        if distance <= 1.5 * radius or not ok[s] or not np.isfinite(centre_px[s]).all():
            out.append((-np.inf, np.inf, -np.inf, np.inf))
            continue
        # the disc's radius in pixels, generously (the distortion is not inverted here)
        half = 2.0 * max(model.f_u, model.f_v) * radius / max(distance - radius, 1e-6) + pad
        x, y = float(centre_px[s, 0]), float(centre_px[s, 1])
        out.append((x - half, x + half, y - half, y + half))
    return out


def _captured_splats(shutter, t: int, poses: ClipPoses, k: int, points_box: np.ndarray, radius_m: np.ndarray,
                     select: np.ndarray):
    """(pixels float64 [s, 2], depth float64 [s], radius float64 [s]) of an occluder's returns
    ``points_box[select]`` (box frame) in image ``t`` of ``shutter`` (the camera's frames), each at
    its capture time in its row: the object moves rigidly from its pose ``k`` of ``poses`` (at the
    image pose time) with its velocity and yaw rate, as :class:`_NumpyProjection` moves the
    tracked points."""
    from drivetrack.camera.rolling_shutter import project_world

    chosen = np.flatnonzero(select)
    world = _carry(poses.world_from_box[k:k + 1], points_box[chosen])[0] + poses.shift_world[k]
    found = project_world(shutter, t, world, rigid_velocity_world(world, poses.world_from_box[k, :3, 3],
                                                             poses.velocity_world[k], poses.yaw_rate_world[k]))
    ok = found.valid & (found.points_camera[:, 0] > 0)
    return found.pixels[ok], found.points_camera[ok, 0], radius_m[chosen[ok]]


_POSE_FIELDS = ("vehicle_from_box", "world_from_box", "camera_from_box", "shift_camera", "shift_world",
                "velocity_world", "yaw_rate_world")


def _occluder_poses(plan, camera: int, object_id: str, frames: np.ndarray, rows: np.ndarray) -> ClipPoses:
    """:func:`clip_poses` of an occluder's box ``rows`` (int [k], at ``frames``) in ``camera``'s
    images. Under the trajectory each row's pose depends on that row and the image alone, so each
    row is posed once per camera (``plan.occluder_cache``; an occluder is posed for every clip of
    the camera it may hide) and later calls take the rows they need from those; under
    ``time_model="velocity"`` the velocities are differences over ``frames``: computed here."""
    if plan.config.time_model != "trajectory":
        return clip_poses(plan, camera, frames, rows)
    key = (f"{object_id}#poses", camera)
    known, poses = plan.occluder_cache.get(key, (np.zeros(0, dtype=np.int64), None))
    missing = np.setdiff1d(rows, known)
    if missing.size:
        new = clip_poses(plan, camera, plan.scene.boxes.frame[missing].astype(np.int64), missing)
        known = np.concatenate([known, missing])
        order = np.argsort(known, kind="stable")
        fields = {name: getattr(new, name) if poses is None
                  else np.concatenate([getattr(poses, name), getattr(new, name)]) for name in _POSE_FIELDS}
        known = known[order]
        poses = ClipPoses(**{name: value[order] for name, value in fields.items()}, trajectory=new.trajectory,
                          decision=new.decision)
        plan.occluder_cache[key] = (known, poses)
    at = np.searchsorted(known, rows)
    return ClipPoses(**{name: getattr(poses, name)[at] for name in _POSE_FIELDS}, trajectory=poses.trajectory,
                     decision=poses.decision)


def _occluders(plan, job, frames: np.ndarray, target_camera: np.ndarray, target_radius_m: np.ndarray,
               shutter=None, use_kernel: bool = False, with_own: bool = False):
    """``(returns, boxes, seen, own)``: per clip frame, (pixels float64 [m, 2], depth float64 [m], footprint
    radius float64 [m], metres, object int32 [m], which object each return is of, numbered from
    0 in the clip) of the other labelled objects' returns, and the boxes of those
    objects as posed for the image: (camera_from_box float64 [k, 4, 4] with each object's shift
    added to the translation, size float64 [k, 3], solid float64 [k, 2, 3], the part of each box
    its returns fill, :func:`drivetrack.visibility.solid_extents`).

    Every object but ``job``'s with a box at some clip frame and returns selected by the plan
    (somewhere in the segment) is carried by its own :func:`clip_poses` (the capture time of
    ``job.camera``'s image). Its surface is its returns in its box frame (:func:`_points_box`):
    under the trajectory all its returns over the segment, computed once per object
    (``plan.occluder_cache``); under ``time_model="velocity"`` those of the clip frames. Both are
    thinned to one return per cube of ``surfel_cube_m``
    (:func:`drivetrack.visibility.zbuffer.surfel_subsample`). An object of
    ``TrackConfig.occluder_recent_types`` near the camera whose returns over the segment are noisy
    (:func:`_hides_with_recent`) is drawn in each image from its returns of the frames within
    ``occluder_recent_frames`` of it instead (:func:`segment_returns_by_frame`, not thinned). With ``roof_fill`` (on the
    trajectory), each other object's surface also holds the part of its roof its returns leave
    unsampled (:func:`segment_roof_fill`; splats only: the boxes' ``solid`` parts stay its
    returns'). The tracked object is the sphere of
    centre ``target_camera`` float64 [T, 3] (camera frame, metres) and radius ``target_radius_m``
    float64 [T] at each clip frame; an object's box row is skipped when its own bounding sphere
    lies entirely farther from the camera than the target's far side, or is seen at an angle from
    the target's that their angular radii (plus :data:`_OCCLUDER_ANGLE_MARGIN_RAD`, for the motion
    between label and image time) cannot bridge: it cannot occlude the target in that image.
    ``shutter``: the camera's frames (``scene.cameras[job.camera]``, without images) when the job
    projects with a rolling shutter: each return is then splatted at its pixel and depth at its
    capture time in its row, as the tracked points are looked up (the boxes stay at the image
    pose); None: the global-shutter image pose. Only returns near the target in the image
    (:func:`_near_windows` at its pose) are kept: the z-buffer test looks no farther than the
    footprints round the tracked points. ``seen``: some return of an object kept above projected
    validly into some clip frame's image, near the target or not. ``use_kernel``: project with the
    numba kernel (:func:`drivetrack.visibility.kernel.project_in_window`; the global shutter
    only), else with numpy. ``own``: with ``with_own``, ``job``'s own object's returns placed
    the same way, per clip frame like ``returns`` (object 0), for its own z-buffer
    (``TrackConfig.self_occlusion``); None without, or when none of them projects validly.
    """
    from drivetrack.visibility import solid_extents
    from drivetrack.visibility.zbuffer import surfel_subsample

    scene = plan.scene
    boxes = scene.boxes
    cube_m = _surfel_cube_m(plan.config)
    geometry = plan.cameras[job.camera]
    model = scene.cameras[job.camera].model
    t_count = frames.size
    slot = np.full(scene.num_frames, -1, dtype=np.int64)
    slot[frames] = np.arange(t_count)
    # objects with selected returns somewhere in the segment occlude at every clip frame they have a box in
    with_points = np.unique(boxes.object_id[plan.box_point_offsets[1:] > plan.box_point_offsets[:-1]])
    in_clip = np.flatnonzero((slot[boxes.frame] >= 0) & (boxes.object_id != job.object_id)
                             & np.isin(boxes.object_id, with_points))
    candidates = in_clip
    per_frame: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in range(t_count)]
    frame_boxes: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in range(t_count)]
    frame_ids: list[list[tuple]] = [[] for _ in range(t_count)]
    if in_clip.size:
        in_clip = in_clip[_can_occlude(boxes, geometry.camera_from_vehicle, in_clip, slot[boxes.frame[in_clip]],
                                       target_camera, target_radius_m)]
    # only returns near the target in the image at its pose matter (and, under a rolling shutter,
    # are solved for their capture time)
    windows = _near_windows(model, target_camera, target_radius_m)
    use_kernel = use_kernel and shutter is None
    if use_kernel:
        from drivetrack.camera.kernel import camera_parameters
        from drivetrack.visibility.kernel import project_in_window

        params = camera_parameters(model)
    seen = own_seen = False
    others = np.unique(boxes.object_id[in_clip]).tolist()
    own_rows = (np.flatnonzero((slot[boxes.frame] >= 0) & (boxes.object_id == job.object_id))
                if with_own else np.zeros(0, np.int64))
    own_frame: list[list[tuple[np.ndarray, ...]]] = [[] for _ in range(t_count)]
    records: list[tuple] = []                      # the kernel path's objects, splatted lazily
    recent_frames = int(plan.config.occluder_recent_frames)
    for label, object_id in enumerate(others + ([job.object_id] if own_rows.size else [])):
        is_own = label == len(others)
        obj_rows = own_rows if is_own else in_clip[boxes.object_id[in_clip] == object_id]
        obj_rows = obj_rows[np.argsort(boxes.frame[obj_rows], kind="stable")]
        obj_frames = boxes.frame[obj_rows].astype(np.int64)
        poses = _occluder_poses(plan, job.camera, object_id, obj_frames, obj_rows)
        measured = None                            # int [m]: each return's frame, for a recent-returns occluder
        if not is_own and _hides_with_recent(plan, object_id, int(boxes.type[obj_rows[0]]), poses):
            # it hides with its returns of the frames near each image (selected per image below)
            points_box, measured = segment_returns_by_frame(plan, object_id, poses)
            radius_m = None
        elif poses.trajectory is not None:
            # On the segment's trajectory an object's returns in its box frame do not depend on the
            # camera or the clip: all its returns over the segment, thinned to the first of each
            # surfel cube, computed once per object and segment.
            points_box = segment_surface(plan, object_id, poses)
            radius_m = (segment_surface_radius(plan, object_id, poses)
                        if plan.config.surfel_radius_from == "spacing" else None)
        else:
            radius_m = None
            # the clip's returns (of the frames it has a box in, before the skips above)
            clip_rows = own_rows if is_own else candidates[boxes.object_id[candidates] == object_id]
            clip_rows = clip_rows[np.argsort(boxes.frame[clip_rows], kind="stable")]
            lidar_rows, source = plan.box_points(clip_rows)
            points_box = _points_box(plan, boxes.frame[clip_rows].astype(np.int64), clip_rows,
                                     clip_poses(plan, job.camera, boxes.frame[clip_rows], clip_rows), lidar_rows, source)
            points_box = points_box[surfel_subsample(points_box, cube_m)]
        if points_box.shape[0] == 0:
            continue
        if radius_m is None:
            radius_m = np.full(points_box.shape[0], float(plan.config.surfel_radius_m))
        if poses.trajectory is not None:
            # the object's surface is the segment's: its extent, once per object (the solid parts
            # depend on the returns only through it)
            key = f"{object_id}#extent"
            if key not in plan.occluder_cache:
                plan.occluder_cache[key] = segment_solid_bounds(plan, object_id, poses)
            solid = solid_extents(plan.occluder_cache[key], boxes.size[obj_rows])
        else:
            solid = solid_extents(points_box, boxes.size[obj_rows])
        if plan.config.roof_fill and not is_own and poses.trajectory is not None:
            # the roof its returns leave unsampled (splats only: the boxes' solid parts stay the returns')
            fill = segment_roof_fill(plan, object_id, poses)
            points_box = np.concatenate([points_box, fill])
            radius_m = np.concatenate([radius_m, np.full(fill.shape[0], float(plan.config.surfel_radius_m))])
            if measured is not None:                # the fill is the segment's: in every image
                measured = np.concatenate([measured, np.full(fill.shape[0], _ANY_FRAME, dtype=np.int64)])
        placed = poses.camera_from_box.copy()
        placed[:, :3, 3] += poses.shift_camera
        if use_kernel:
            # splatted lazily, one image at a time (_LazySplats); here only whether some return
            # projects validly somewhere (the first valid frame settles it)
            points_box = np.ascontiguousarray(points_box, dtype=np.float64)
            record = len(records)
            records.append((points_box, placed, radius_m, 0 if is_own else label, measured))
            if not (own_seen if is_own else seen):
                scratch = (np.empty((points_box.shape[0], 2)), np.empty(points_box.shape[0]),
                           np.empty(points_box.shape[0], dtype=np.int64))
                for k in range(obj_frames.size):
                    if project_in_window(points_box, placed[k], params, np.inf, -np.inf, np.inf, -np.inf,
                                         *scratch)[1] > 0:
                        if is_own:
                            own_seen = True
                        else:
                            seen = True
                        break
        else:
            # per image k the returns it is drawn from: all, or a recent-returns occluder's near
            # frames' (each image's own few: never [t, every return] of a long clip)
            chosen = ([slice(None)] * obj_frames.size if measured is None else
                      [np.flatnonzero(_recent(measured, t, recent_frames)) for t in obj_frames.tolist()])
            if measured is None:
                points_camera = _carry(poses.camera_from_box, points_box) + poses.shift_camera[:, None]   # [t, m, 3]
                pixels, valid = model.pixels_from_camera(points_camera)
                valid &= (points_camera[..., 0] > 0) & np.isfinite(pixels).all(axis=-1)
            else:
                points_camera = [_carry(poses.camera_from_box[k:k + 1], points_box[c])[0] + poses.shift_camera[k]
                                 for k, c in enumerate(chosen)]
                projected = [model.pixels_from_camera(p) for p in points_camera]
                pixels = [p[0] for p in projected]
                valid = [ok & (p[:, 0] > 0) & np.isfinite(px).all(axis=-1)
                         for (px, ok), p in zip(projected, points_camera)]
            any_valid = any(bool(v.any()) for v in valid)
            if is_own:
                own_seen = own_seen or any_valid
            else:
                seen = seen or any_valid
        for k, t in enumerate(obj_frames.tolist()):
            x_lo, x_hi, y_lo, y_hi = windows[slot[t]]
            if use_kernel:
                splats = (record, k, slot[t])             # splatted when the frame is asked for
            else:
                near = (valid[k] & (pixels[k][:, 0] >= x_lo) & (pixels[k][:, 0] <= x_hi) & (pixels[k][:, 1] >= y_lo)
                        & (pixels[k][:, 1] <= y_hi))
                if shutter is None:
                    splats = (pixels[k][near], points_camera[k][near, 0], radius_m[chosen[k]][near])
                else:
                    splats = _captured_splats(shutter, t, poses, k, points_box[chosen[k]], radius_m[chosen[k]], near)
            if not use_kernel:                            # each return's object (the own one's: 0)
                splats += (np.full(splats[1].shape[0], 0 if is_own else label, dtype=np.int32),)
            (own_frame if is_own else per_frame)[slot[t]].append(splats)
            if is_own:
                continue
            frame_boxes[slot[t]].append((placed[k], boxes.size[obj_rows[k]], solid[k]))
            world_from_other = poses.world_from_box[k].copy()
            world_from_other[:3, 3] += poses.shift_world[k]
            frame_ids[slot[t]].append((object_id, world_from_other, poses.velocity_world[k],
                                       float(poses.yaw_rate_world[k])))
    def joined(frames_parts):
        return (_LazySplats(frames_parts, records, params, windows, frames, recent_frames) if use_kernel
                else _joined_splats(frames_parts))

    return (joined(per_frame),
            [(np.stack([b[0] for b in parts]) if parts else np.empty((0, 4, 4)),
              np.stack([b[1] for b in parts]) if parts else np.empty((0, 3)),
              np.stack([b[2] for b in parts]) if parts else np.empty((0, 2, 3))) for parts in frame_boxes],
            seen, joined(own_frame) if own_seen else None, frame_ids)


#: :func:`_occluders`: the "frame" of a recent-returns occluder's roof fill, kept in every image
_ANY_FRAME = np.iinfo(np.int64).min


def _recent(measured: np.ndarray, frame: int, within: int) -> np.ndarray:
    """bool [m]: the returns measured (``measured`` int64 [m], frame indices; :data:`_ANY_FRAME`
    for any) within ``within`` frames of ``frame``."""
    return (np.abs(measured - frame) <= within) | (measured == _ANY_FRAME)


def _joined_splats(frames_parts):
    """Per frame, the (pixels, depth, radius, object) of its parts, each concatenated."""
    return [(np.concatenate([p[0] for p in parts]) if parts else np.empty((0, 2)),
             np.concatenate([p[1] for p in parts]) if parts else np.empty(0),
             np.concatenate([p[2] for p in parts]) if parts else np.empty(0),
             np.concatenate([p[3] for p in parts]) if parts else np.empty(0, dtype=np.int32))
            for parts in frames_parts]


class _LazySplats:
    """:func:`_occluders`' per-frame splats on the kernel path, splatted when a frame is asked
    for (``splats[tau]`` or ``splats[slice]``, a list) and not kept: a clip's images are asked
    for one at a time, so only one image's splats are held (a near car's own returns over 54
    full-size frames held 45 MiB, its occluders' 37 MiB). ``frames_parts`` per frame the
    ``(record, k, slot)`` of each object there, in order; ``records`` per object ``(points_box
    float64 [m, 3], placed float64 [K, 4, 4], radius_m float64 [m], label, measured)``, with
    ``measured`` int64 [m] the frame of each return of an object that hides with its recent
    returns (``TrackConfig.occluder_recent_types``: those within ``recent_frames`` of the
    image's frame ``frames[slot]`` are splatted) or None."""

    def __init__(self, frames_parts, records, params, windows, frames=None, recent_frames=0):
        self.frames_parts, self.records, self.params, self.windows = frames_parts, records, params, windows
        self.frames, self.recent_frames = frames, recent_frames

    def __len__(self) -> int:
        return len(self.frames_parts)

    def __getitem__(self, at):
        if isinstance(at, slice):
            return [self[tau] for tau in range(len(self))[at]]
        return _joined_splats([[self._splat(*part) for part in self.frames_parts[at]]])[0]

    def _splat(self, record: int, k: int, slot: int):
        from drivetrack.visibility.kernel import project_in_window

        points_box, placed, radius_m, label, measured = self.records[record]
        if measured is not None:
            chosen = np.flatnonzero(_recent(measured, int(self.frames[slot]), self.recent_frames))
            points_box, radius_m = np.ascontiguousarray(points_box[chosen]), radius_m[chosen]
        pixels, depth = np.empty((points_box.shape[0], 2)), np.empty(points_box.shape[0])
        index = np.empty(points_box.shape[0], dtype=np.int64)
        kept, _ = project_in_window(points_box, placed[k], self.params, *self.windows[slot], pixels, depth, index)
        return (pixels[:kept].copy(), depth[:kept].copy(), radius_m[index[:kept]],
                np.full(kept, label, dtype=np.int32))


def segment_hull(plan, object_id: str, poses):
    """The :class:`drivetrack.visibility.zbuffer.OccluderHull` of ``object_id``'s segment surface
    (:func:`segment_surface`; its facets trusted against that surface and, with ``roof_fill``, its
    roof fill, :func:`segment_roof_fill`), or None; once per object and segment
    (``plan.occluder_cache``): :func:`drivetrack.visibility.zbuffer.hull_hidden`."""
    from drivetrack.visibility.zbuffer import occluder_hull

    key = f"{object_id}#hull"
    if key not in plan.occluder_cache:
        cloud = segment_surface(plan, object_id, poses)
        surface = np.concatenate([cloud, segment_roof_fill(plan, object_id, poses)]) if plan.config.roof_fill else cloud
        plan.occluder_cache[key] = occluder_hull(cloud, surface, spanned=_segment_spanned(plan, object_id, poses),
                                                 use_kernel=_use_kernel(plan.config))
    return plan.occluder_cache[key]


def run_object_job(ctx: SegmentContext, job: ObjectJob) -> ObjectTracks:
    """Point tracks of one accepted clip (see the module docstring). Pure: writes nothing."""
    from drivetrack.depth import lookup_max4

    plan, config, scene = ctx.plan, ctx.config, ctx.scene
    geometry = plan.cameras[job.camera]
    frames_meta = scene.cameras[job.camera]
    model = frames_meta.model
    boxes, lidar = scene.boxes, scene.lidar
    frames, rows = job.frames, job.box_rows
    t_count = frames.size
    timestamps = scene.timestamps_micros[frames].astype(np.int64)

    poses = clip_poses(plan, job.camera, frames, rows)
    # the object at each frame time (points3d, speeds): refined boxes may carry pitch and roll
    # (drivetrack.refine); the trajectory levels yaw-only labels' ego tilt
    vehicle_from_box = poses.vehicle_from_box                                                # [T,4,4]
    world_from_box = scene.world_from_vehicle[frames] @ vehicle_from_box
    camera_from_box, shift_camera = poses.camera_from_box, poses.shift_camera

    lidar_rows, source_clip = plan.box_points(rows)
    n_candidates = lidar_rows.size
    if config.max_tracks_per_object is not None and n_candidates > config.max_tracks_per_object:
        # Same subset for every camera of the object; independent of job order.
        rng = np.random.default_rng([config.seed, zlib.crc32(f"{scene.segment}/{job.object_id}".encode())])
        keep = np.sort(rng.choice(n_candidates, size=config.max_tracks_per_object, replace=False))
        lidar_rows, source_clip = lidar_rows[keep], source_clip[keep]
    n = lidar_rows.size
    box_from_vehicle = invert_rigid(vehicle_from_box)
    p_box = _points_box(plan, frames, rows, poses, lidar_rows, source_clip)

    # Back faces (drivetrack.visibility.facing): normals from the object's own returns, turned
    # towards the ego that saw them; None when the test is off (the paper's depth test alone).
    by_surface = config.occlusion == "surface"
    surfels = centres_box = None
    if by_surface and config.back_face_max_deg is not None:
        from drivetrack.visibility import (SurfelNormals, camera_centres_box, points_on_surface, surfel_normals,
                                           with_box_face_normals)

        sensor_box, rays_box = _lidar_rays_box(scene, lidar_rows, box_from_vehicle[source_clip])
        # neighbourhoods among all the object's returns over the segment (on the trajectory): denser
        # than the clip's, so far objects' normals are fixed more often (the clip's otherwise)
        if poses.trajectory is not None and config.normals_from == "segment":
            fitted = segment_cloud_normals(plan, job.object_id, poses)
            surfels = (surfel_normals(p_box, sensor_box, fitted=fitted, transfer=config.normal_transfer)
                       if fitted is not None    # too few: none
                       else SurfelNormals(np.zeros((n, 3)), np.zeros(n, dtype=bool)))
            # range noise: each return moved along its ray onto its sweep's surface (exact ranges stay)
            if fitted is not None and config.surface_snap_max_m is not None:
                p_box, _ = points_on_surface(p_box, boxes.frame[rows][source_clip], rays_box, surfels.normal,
                                             lambda: segment_surface_cloud(plan, job.object_id, poses),
                                             surfels.reliable, float(config.surface_snap_max_m), keys=lidar_rows)
        else:
            surfels = surfel_normals(p_box, sensor_box, neighbours=config.normal_neighbours,
                                     neighbourhood=config.normal_neighbourhood, precise_m=config.normal_precise_m)
        if config.box_face_normals_m is not None:
            # too thinly sampled for a plane, but on one face of the label box: that face's normal
            # (a roof or a side seen at a grazing angle by the lidar; docs/visibility.md)
            surfels = with_box_face_normals(surfels, p_box, np.median(boxes.size[rows], axis=0),
                                            float(config.box_face_normals_m))
        centres_box = camera_centres_box(camera_from_box, shift_camera)
        del sensor_box, rays_box
    # The object's own box for the depth-map test (drivetrack.visibility.own_surface): with the
    # back-face test on, a depth-map surface inside it hides nothing at a point whose normal is
    # reliable (``own_points``); where it is not, the back-face test cannot decide, and the surface
    # is the object's own smear only where the ray from it to the point runs outside the box
    # itself (no gap limit: measured, docs/visibility.md "Unreliable normals"). Its camera centres are the
    # global-shutter image pose's; on the rolling-shutter path the surface point is placed with
    # them too (off by (1 - depth ratio) x the camera's motion relative to the object between the
    # image pose and the row's time: centimetres, inside the margin). Only within
    # ``own_surface_max_gap_m`` in front of the point: farther, a part of the object itself (a
    # cabin in front of a bonnet) hides it, if the surface lies inside the box itself and not in
    # its margin (where no part of it is: a roof seen at a grazing angle). The box itself is the part
    # its returns fill (drivetrack.visibility.solid_extents: a label is drawn wider than its
    # object). [0, 13]: off.
    own_box, own_points = np.zeros((0, 13)), np.zeros(n, dtype=bool)
    if surfels is not None and config.own_surface_margin_m is not None:
        from drivetrack.visibility import own_box_parameters, solid_extents

        own_cloud = segment_solid_bounds(plan, job.object_id, poses) if poses.trajectory is not None else p_box
        own_box = own_box_parameters(centres_box, boxes.size[rows], float(config.own_surface_margin_m),
                                     config.own_surface_max_gap_m, solid_extents(own_cloud, boxes.size[rows]))
        own_points = np.ascontiguousarray(surfels.reliable, dtype=bool)

    def back_faces(start: int, stop: int) -> np.ndarray | None:
        """bool [T, k] back-face test of candidates ``start:stop`` (the numpy path's):
        :func:`drivetrack.visibility.facing_mask`, held for them (from ``held_from``)."""
        if front_facing is None:
            return None
        return front_facing[:, start - held_from:stop - held_from]

    def project_global(chunk: np.ndarray, tau: int | None = None):
        """(points_camera [T, k, 3], pixels [T, k, 2], valid [T, k]) of box-frame points ``chunk``
        [k, 3] at the image pose (global shutter), in front of the camera; with ``tau`` at clip
        frame ``tau`` alone (T = 1)."""
        at = slice(None) if tau is None else slice(tau, tau + 1)
        points_camera = _carry(camera_from_box[at], chunk) + shift_camera[at, None]
        pixels, valid = model.pixels_from_camera(points_camera)
        return points_camera, pixels, valid & (points_camera[..., 0] > 0)

    use_kernel = _use_kernel(config)

    def project_frame(chunk: np.ndarray, tau: int):
        """:func:`project_global` of ``chunk`` at clip frame ``tau`` by the numba kernel
        (:func:`drivetrack.visibility.kernel.project_points`): points_camera [1, k, 1] (the z-depth
        alone), pixels [1, k, 2], valid [1, k]."""
        from drivetrack.camera.kernel import camera_parameters
        from drivetrack.visibility.kernel import project_points

        placed = camera_from_box[tau].copy()
        placed[:3, 3] += shift_camera[tau]
        pixels = np.empty((1, chunk.shape[0], 2))
        depth = np.empty((1, chunk.shape[0], 1))
        valid = np.empty((1, chunk.shape[0]), dtype=bool)
        project_points(np.ascontiguousarray(chunk, dtype=np.float64), placed, camera_parameters(model), pixels[0],
                       depth[0, :, 0], valid[0])
        return depth, pixels, valid

    projector = rolling_shutter_projector() if config.rolling_shutter else None
    # A camera whose shutter data say global shutter at every clip frame projects exactly like
    # the global path (rolling_shutter.shutter_state's fallback): skip the per-frame loop.
    rolling = projector is not None and _any_rolling_frame(frames_meta, frames)
    # the projection is kept by the result's TrackSource: without the camera's images (a
    # result crossing processes must not carry the segment's JPEGs)
    shutter_meta = dataclasses.replace(frames_meta, jpeg=[None] * len(frames_meta.jpeg))
    projection = _NumpyProjection(model, rolling, projector, shutter_meta, frames, camera_from_box,
                                  shift_camera, poses.world_from_box, poses.shift_world, poses.velocity_world,
                                  poses.yaw_rate_world)

    # Other objects (drivetrack.visibility.zbuffer): hidden[T, n] where another labelled object's
    # splatted returns lie nearer than the point, beyond the tolerance. The same numpy decision
    # for the kernel and numpy paths: at the image pose (global shutter), or under a rolling
    # shutter at each point's and each occluder return's pixel and depth at its capture time
    # (a parked car beside the ego moves ~10 px between two rows of a side camera). The margins of
    # both surface tests, float32 [T, n] (+inf where a test cannot hide the point), go into each
    # kept point-frame's occlusion margin (:func:`_occlusion_margins`).
    hidden_other = zbuffer_margin = face_margin = front_facing = None
    # The other labelled objects' boxes for the depth-map test (drivetrack.visibility.other_surface):
    # a map surface inside one of them (grown) on a ray that misses the box itself is that object's
    # depth spread past its outline, which the z-buffer draws from its own surface; posed like the
    # own box (the global-shutter image pose); [T, 0, 21]: off.
    others = np.zeros((0, 0, 21))
    occluders = []
    own_splats = None
    # the z-buffer's image, footprint and tolerance (drivetrack.visibility.zbuffer.hidden_by_others)
    zbuffer_args = (int(model.width), int(model.height), float(model.f_u), float(config.surfel_radius_m),
                    int(config.surfel_max_px), float(config.occluder_tolerance_m),
                    float(config.occluder_tolerance_rel))

    # The kernel's path (below) keeps one image's results of the z-buffer at a time (row 0 of
    # ``hidden_other`` / ``zbuffer_margin``, [1, n]): the tests write clip frame(s) ``at`` at row(s)
    # ``stored(at)``.
    one_row = False
    # Under a rolling shutter (the numpy path) they hold one chunk of candidates at a time, from
    # candidate ``held_from`` on (its columns): a candidate's column is its row - ``held_from``.
    held_from = 0

    def stored(at):
        """The row(s) of ``hidden_other`` / ``zbuffer_margin`` holding clip frame(s) ``at`` (int or slice)."""
        if not one_row:
            return at
        return slice(0, 1) if isinstance(at, slice) else 0

    def zbuffer_test(start: int, points_camera: np.ndarray, pixels: np.ndarray, valid: np.ndarray,
                     tau: int | None = None) -> None:
        """Fills ``hidden_other`` and ``zbuffer_margin`` of candidates ``start:`` from their
        projection float [T, k, 3] (depth) / [T, k, 2] (pixels) / bool [T, k]; with ``tau``, of
        clip frame ``tau`` alone from its projection [1, k, ...]."""
        stop = start + pixels.shape[1]
        at = slice(None) if tau is None else slice(tau, tau + 1)
        rescued = None if hull_test is None else np.zeros(valid.shape, dtype=bool)
        edge = None if edge_test is None else np.zeros(valid.shape, dtype=bool)
        cols = slice(start - held_from, stop - held_from)
        hidden_other[stored(at), cols], zbuffer_margin[stored(at), cols] = hidden_by_others(
            points_camera, pixels, valid, occluders[at], *zbuffer_args, int(config.occluder_fill_px),
            int(config.occluder_subpixels), use_kernel=use_kernel, rescued=rescued, edge=edge)
        tests = [(band_of, test) for band_of, test in ((rescued, hull_test), (edge, edge_test)) if band_of is not None]
        for i, frame_tau in enumerate(range(t_count)[at] if tests else ()):
            # both bands' rays placed at once (the other objects' hulls and poses are the frame's)
            bands = [(np.flatnonzero(band_of[i]), test) for band_of, test in tests]
            joined = np.concatenate([band for band, _ in bands])
            placed = hull_rays(frame_tau, start + joined, pixels[i, joined]) if joined.size else None
            if placed is None:
                continue
            first = 0
            for band, test in bands:
                part = slice(first, first + band.size)
                first += band.size
                if band.size:
                    rays = [(centres if centres.ndim == 1 else centres[part], points[part])
                            for centres, points in placed[1]]
                    test(frame_tau, start + band, points_camera[i, band, 0], (placed[0], rays))
        if own_splats is not None:
            sub = np.flatnonzero(t_pocket[start:stop])
            own_test(start + sub, sub, points_camera, pixels, valid, at)

    def own_test(pocket: np.ndarray, sub: np.ndarray, points_camera: np.ndarray, pixels: np.ndarray,
                 valid: np.ndarray, at: slice) -> None:
        """The object's own surface in front of candidates ``pocket`` int [k] (rows of ``p_box``;
        their projection is at columns ``sub`` int [k] of ``points_camera`` / ``pixels`` /
        ``valid``, frames ``at``): beyond the depth their own plane spans over the footprints
        (drivetrack.visibility.zbuffer.own_plane_slack); only points in its hull's pockets can be
        hidden so (pocket_points). The own buffer is not closed: on a surface seen obliquely a
        closing carries the nearer returns' depth over the farther ones between scan lines, and
        the object would hide itself."""
        if pocket.size == 0:
            return
        _, own_margin = hidden_by_others(points_camera[:, sub], pixels[:, sub], valid[:, sub], own_splats[at],
                                         *zbuffer_args, 0, int(config.occluder_subpixels), use_kernel=use_kernel)
        own_margin += own_plane_slack(t_box[pocket], t_normal[pocket], t_reliable[pocket],
                                      centres_box[at], float(config.surfel_radius_m))
        cols = pocket - held_from
        hidden_other[stored(at), cols] |= own_margin < 0
        zbuffer_margin[stored(at), cols] = np.minimum(zbuffer_margin[stored(at), cols], own_margin)

    depth = ctx.depth.get(job.camera)
    if depth is None or np.any(depth.slot[frames] < 0):
        raise ValueError(f"segment {scene.segment!r} camera {job.camera_name} object {job.object_id!r}: "
                         f"the segment context has no depth map for some clip frames")

    slots = depth.slot[frames]
    grow_px = depth_lookup_grow_px(plan)
    # A clip's frames are consecutive and all needed, so their maps are adjacent: a view, no copy.
    clip_maps = (depth.maps[slots[0]:slots[-1] + 1] if np.all(np.diff(slots) == 1) else depth.maps[slots])

    world_step = world_from_box[1:] - world_from_box[:-1]                    # affine differences [T-1]
    duration_s = (timestamps[-1] - timestamps[0]) * 1e-6

    box_speed = np.linalg.norm(boxes.speed[rows], axis=-1)
    box_speed_mean = float(np.nanmean(box_speed)) if np.isfinite(box_speed).any() else float("nan")
    speed_filter = (config.max_speed_deviation_mps is not None and np.isfinite(box_speed_mean))
    max_deviation = float(config.max_speed_deviation_mps) if speed_filter else float("nan")

    # The track kernel's path (global shutter): its screen (projection, depth-map test, speed
    # filter; ``status`` int8 [n]) runs first, and the surface tests look at the candidates it
    # keeps alone (``tested``, about half of them), one image at a time (below).
    fast = use_kernel and not rolling
    status = tested = None
    if fast:
        from drivetrack.tracks import kernel

        status = np.empty(n, dtype=np.int8)
        speeds = np.empty(n, dtype=np.float64)
        p_box = np.ascontiguousarray(p_box, dtype=np.float64)
        camera_from_box = np.ascontiguousarray(camera_from_box, dtype=np.float64)
        shift_camera = np.ascontiguousarray(shift_camera, dtype=np.float64)
        vehicle_from_box = np.ascontiguousarray(vehicle_from_box, dtype=np.float64)
        clip_maps = np.ascontiguousarray(clip_maps, dtype=np.float32)
        params = kernel.camera_parameters(model)

    def screen() -> np.ndarray:
        """The kernel's screen of every candidate (fills ``status`` and ``speeds``): the rows it keeps."""
        kernel.screen_points(p_box, camera_from_box, shift_camera, np.ascontiguousarray(world_step),
                             params, clip_maps, float(config.occlusion_ratio), own_box, own_points, others,
                             float(duration_s), box_speed_mean, max_deviation, status, speeds, grow_px)
        return np.flatnonzero(status == kernel.KEPT)

    # the candidates the surface tests look at: their box points, normals and pocket flags
    t_box, t_normal, t_reliable, t_pocket = p_box, None, None, None
    if surfels is not None:
        t_normal, t_reliable = surfels.normal, surfels.reliable

    hull_test = edge_test = None
    if by_surface:
        from drivetrack.visibility.zbuffer import hidden_by_others, own_plane_slack

        centre_camera = camera_from_box[:, :3, 3] + shift_camera
        in_pocket = None
        if config.self_occlusion and surfels is not None:
            in_pocket = _pocket_points(plan, job.object_id, poses, p_box, np.median(boxes.size[rows], axis=0))
        occluders, occluder_boxes, any_occluder, own_splats, occluder_ids = _occluders(
            plan, job, frames, centre_camera, 0.5 * np.linalg.norm(boxes.size[rows], axis=-1),
            shutter_meta if rolling else None, use_kernel, with_own=in_pocket is not None and bool(in_pocket.any()))
        if any_occluder and own_box.shape[0] and config.depth_defers_to_zbuffer:
            from drivetrack.visibility import other_boxes

            others = other_boxes(camera_from_box, shift_camera, occluder_boxes, float(config.own_surface_margin_m))
        t_pocket = in_pocket
        if fast:
            tested = screen()
            if tested.size < n:            # all kept (a near object): the candidates' own arrays
                t_box = np.ascontiguousarray(p_box[tested])
                if surfels is not None:
                    t_normal, t_reliable = surfels.normal[tested], surfels.reliable[tested]
                if in_pocket is not None:
                    t_pocket = in_pocket[tested]
        n_tested = t_box.shape[0]
        # the kernel's path tests one image at a time (below): one row of results; the rolling
        # shutter's, one chunk of candidates at a time (allocated there: none here)
        one_row = fast
        rows_held = 1 if fast else t_count
        cols_held = 0 if rolling else n_tested
        if any_occluder or own_splats is not None:
            hidden_other = np.zeros((rows_held, cols_held), dtype=bool)
            zbuffer_margin = np.empty((rows_held, cols_held), dtype=np.float32)
        if surfels is not None:
            from drivetrack.visibility.facing import facing_test

            face_margin = np.full((rows_held, cols_held), np.inf, dtype=np.float32)
            front_facing = np.ones((rows_held, cols_held), dtype=bool)
        if hidden_other is not None and config.occluder_hulls and poses.trajectory is not None:
            from drivetrack.visibility.zbuffer import box_points_at, hull_hidden, hull_missed

            def hull_rays(tau: int, rows: np.ndarray, pixels: np.ndarray):
                """``(hulls, rays)`` of :func:`hull_hidden` / :func:`hull_missed` for the points
                ``rows`` int [k] at clip frame ``tau`` (pixels float [k, 2]): the other objects'
                convex hulls and the rays to the points in each one's box frame, at the image pose
                under a global shutter; under a rolling shutter at each point's capture time in its
                row, camera, object and occluders moved there with their velocities and yaw
                rates, as the z-buffer's splats are. None when no other object is near."""
                found = occluder_ids[tau]
                if not found:
                    return None
                hulls = [segment_hull(plan, object_id, poses) for object_id, *_ in found]
                if not rolling:
                    placed_self = camera_from_box[tau].copy()
                    placed_self[:3, 3] += shift_camera[tau]
                    centre = invert_rigid(placed_self)[:3, 3]
                    rays = []
                    for placed_other in occluder_boxes[tau][0]:
                        other_from_box = invert_rigid(placed_other) @ placed_self
                        rays.append((np.einsum("ij,j->i", other_from_box[:3, :3], centre) + other_from_box[:3, 3],
                                     np.einsum("ij,nj->ni", other_from_box[:3, :3], t_box[rows]) + other_from_box[:3, 3]))
                else:
                    from drivetrack.camera.rolling_shutter import pixel_times, shutter_state

                    t = int(frames[tau])
                    state = shutter_state(shutter_meta, t)
                    dt = np.nan_to_num(pixel_times(shutter_meta, t, pixels) - state.pose_timestamp)
                    centres = state.pose_at(dt)[1] if state.rolling else np.broadcast_to(
                        state.world_from_camera[:3, 3], (rows.size, 3))
                    world = (np.einsum("ij,nj->ni", poses.world_from_box[tau, :3, :3], t_box[rows])
                             + poses.world_from_box[tau, :3, 3] + poses.shift_world[tau])
                    world = world + dt[:, None] * rigid_velocity_world(
                        world, poses.world_from_box[tau, :3, 3], poses.velocity_world[tau],
                        poses.yaw_rate_world[tau])
                    # each occluder at each point's capture time, moved as its splats are
                    rays = [(box_points_at(centres, world_from_other, velocity, yaw_rate, dt),
                             box_points_at(world, world_from_other, velocity, yaw_rate, dt))
                            for _, world_from_other, velocity, yaw_rate in found]
                return hulls, rays

            def hull_test(tau: int, rows: np.ndarray, depth: np.ndarray, placed) -> None:
                """The outline band's points ``rows`` int [k] at clip frame ``tau`` (z-depths
                ``depth`` float [k]; ``placed``: their :func:`hull_rays`) that the footprint rule
                left visible, hidden where they lie behind another object's convex hull
                (hull_hidden)."""
                hit, hull_margin = hull_hidden(placed[1], depth, placed[0], float(config.occluder_tolerance_m),
                                               float(config.occluder_tolerance_rel), use_kernel=use_kernel)
                cols = rows[hit] - held_from
                hidden_other[stored(tau), cols] = True
                zbuffer_margin[stored(tau), cols] = np.minimum(zbuffer_margin[stored(tau), cols], hull_margin[hit])

            def edge_test(tau: int, rows: np.ndarray, depth: np.ndarray, placed) -> None:
                """The points ``rows`` int [k] at clip frame ``tau`` (as :func:`hull_test`'s) that the
                footprint rule hides within a buffer pixel of an occluder's outline: visible again
                where the ray to them misses every other object's hull as spanned
                (hull_missed; ``TrackConfig.occluder_hull_edges``), with a z-buffer margin of 0
                (on the visible side, and ambiguous: a buffer pixel from an outline)."""
                missed = hull_missed(placed[1], depth, placed[0], float(config.occluder_tolerance_m),
                                     float(config.occluder_tolerance_rel), use_kernel=use_kernel)
                hidden_other[stored(tau), rows[missed] - held_from] = False
                zbuffer_margin[stored(tau), rows[missed] - held_from] = 0.0

            if not config.occluder_hull_edges:
                edge_test = None
        if hidden_other is not None and not rolling and not fast:   # rolling: in the numpy path's loop; kernel: below
            # one image at a time over all candidates: each image's z-buffer is drawn once per clip
            # (per chunk of candidates it was drawn once per chunk over much the same window)
            for tau in range(t_count):
                zbuffer_test(0, *(project_frame(t_box, tau) if use_kernel else project_global(t_box, tau)), tau=tau)
        # the back-face test of every candidate here on the numpy global-shutter path (per chunk
        # under a rolling shutter, per image on the kernel's path: below)
        for start in range(0, n if surfels is not None and not use_kernel and not rolling else 0, config.chunk_points):
            stop = min(start + config.chunk_points, n)
            # the back-face test and its margin from one cosine per point-frame
            front_facing[:, start:stop], face_margin[:, start:stop] = facing_test(
                p_box[start:stop], SurfelNormals(surfels.normal[start:stop], surfels.reliable[start:stop]),
                centres_box, float(config.back_face_max_deg))
        if not rolling and not fast:          # the kernel path draws them below
            occluders = []

    def facing(start: int, stop: int) -> np.ndarray | None:
        """bool [T, k]: not hidden by the surface tests (back faces, other objects) for candidates
        ``start:stop`` (the numpy path's); None when both are off."""
        faces = back_faces(start, stop)
        if hidden_other is None:
            return faces
        hidden = hidden_other[:, start - held_from:stop - held_from]
        return ~hidden if faces is None else faces & ~hidden

    if fast:
        kept_rows = tested if tested is not None else screen()
        kept = kept_rows.size
        kept_box = t_box if tested is not None else np.ascontiguousarray(p_box[kept_rows])
        kept_own = np.ascontiguousarray(own_points[kept_rows])
        # One image at a time over the kept candidates: the surface tests (z-buffer of the other
        # objects and the own surface, back faces) and the occlusion margin (theirs and the depth
        # map's: the kernel's ``depth_margins``, as :func:`_occlusion_margins`); only each point-frame's
        # outcome is held, one bit each (np.packbits over the candidates, uint8 [T, ceil(K / 8)]):
        # hidden by a surface test; ambiguous (|margin| < 1); and the margin itself in float16
        # [K, T] when it is kept. The margins are computed for every kept candidate, also those the
        # surface tests then hide everywhere (dropped below).
        packed = (kept + 7) // 8
        surface_hidden = (np.zeros((t_count, packed), dtype=np.uint8) if surfels is not None or hidden_other is not None
                          else None)
        ambiguous = np.empty((t_count, packed), dtype=np.uint8)
        frame_hidden = np.empty(kept, dtype=bool)
        margin16 = np.empty((kept, t_count), dtype=np.float16) if config.occlusion_margins else None
        if surfels is not None:
            from drivetrack.visibility import kernel as visibility_kernel

            kept_normal = np.ascontiguousarray(t_normal, dtype=np.float64)
            kept_reliable = np.ascontiguousarray(t_reliable, dtype=bool)
        centres_box_c = None if centres_box is None else np.ascontiguousarray(centres_box)
        frame_margin = np.empty((kept, 1), dtype=np.float32)
        for tau in range(t_count):
            frame_margin.fill(np.inf)
            frame_hidden.fill(False)
            if hidden_other is not None:
                zbuffer_test(0, *project_frame(kept_box, tau), tau=tau)
                frame_hidden |= hidden_other[0]
                np.minimum(frame_margin[:, 0], _scaled(zbuffer_margin[0], float(config.ambiguity_m)),
                           out=frame_margin[:, 0])
            if surfels is not None:
                visibility_kernel.facing_test(kept_box, kept_normal, kept_reliable, centres_box_c[tau:tau + 1],
                                              float(config.back_face_max_deg), front_facing, face_margin)
                frame_hidden |= ~front_facing[0]
                np.minimum(frame_margin[:, 0], _scaled(face_margin[0], float(config.ambiguity_deg)),
                           out=frame_margin[:, 0])
            kernel.depth_margins(kept_box, camera_from_box[tau:tau + 1], shift_camera[tau:tau + 1], params,
                                 clip_maps[tau:tau + 1], float(config.occlusion_ratio), own_box[tau:tau + 1],
                                 kept_own, others[tau:tau + 1], float(config.ambiguity_m), frame_margin, grow_px)
            ambiguous[tau] = np.packbits(np.abs(frame_margin[:, 0]) < 1.0)     # NaN (outside the image) compares False
            if surface_hidden is not None:
                surface_hidden[tau] = np.packbits(frame_hidden)
            if margin16 is not None:
                margin16[:, tau] = frame_margin[:, 0]
        del frame_margin, frame_hidden
        occluders = []
        query_source = source_clip[kept_rows]
        visibles = np.empty((kept, t_count), dtype=bool)
        query_pixels = np.empty((kept, 2), dtype=np.float32)
        # tracks a chunk of points at a time, kept only for visibles, the query pixels and the
        # sanity counts: the writers recompute tracks and points3d without the depth maps (TrackSource)
        step = max(8, points_per_chunk(t_count) // 8 * 8)        # whole bytes of the packed bits
        scratch_tracks = np.empty((min(step, kept), t_count, 2), dtype=np.float32)
        no_points3d = np.empty((0, t_count, 3), dtype=np.float32)          # not needed here
        checks = np.zeros(2, dtype=np.int64)
        for start in range(0, kept, step):
            stop = min(start + step, kept)
            tracks = scratch_tracks[:stop - start]
            kernel.fill_tracks(kept_box[start:stop], np.arange(stop - start, dtype=np.int64),
                               camera_from_box, shift_camera, vehicle_from_box, params, clip_maps,
                               float(config.occlusion_ratio), own_box, kept_own[start:stop],
                               others, tracks, visibles[start:stop], no_points3d, False, grow_px)
            if surface_hidden is not None:
                visibles[start:stop] &= ~_unpacked(surface_hidden, start, stop).T
            checks += kernel.summarise_tracks(tracks, visibles[start:stop], query_source[start:stop],
                                              float(model.width), float(model.height), query_pixels[start:stop])
        del scratch_tracks, surface_hidden
        seen = np.ones(kept, dtype=bool)
        if surfels is not None or hidden_other is not None:
            # points seen only on back faces or behind other objects are not kept (as points the depth test hides everywhere)
            seen = visibles.any(axis=1)
            if not seen.all():
                status[kept_rows[~seen]] = kernel.DROPPED_INVISIBLE
                kept_box, query_source = np.ascontiguousarray(kept_box[seen]), query_source[seen]
                visibles, query_pixels = visibles[seen], query_pixels[seen]
                margin16 = None if margin16 is None else margin16[seen]
        keep = status == kernel.KEPT
        source = TrackSource(kept_box, camera_from_box, shift_camera, vehicle_from_box, params)
        num_ambiguous = sum(int(_unpacked(ambiguous, start, min(start + step, kept))[:, seen[start:start + step]].sum())
                            for start in range(0, kept, step))
        del ambiguous
        dropped_invisible = int((status == kernel.DROPPED_INVISIBLE).sum())
        dropped_speed = int((status == kernel.DROPPED_SPEED).sum())
    else:
        parts: list[tuple[np.ndarray, np.ndarray]] = []
        margin_parts: list[np.ndarray] = []
        keep = np.zeros(n, dtype=bool)
        speeds = np.zeros(n, dtype=np.float64)
        checks = np.zeros(2, dtype=np.int64)
        dropped_invisible = dropped_speed = num_ambiguous = 0

        for start in range(0, n, config.chunk_points):
            chunk = p_box[start:start + config.chunk_points]                          # [n, 3]
            stop = start + chunk.shape[0]
            if rolling:
                # the surface tests' results of this chunk alone (its columns)
                held_from = start
                if hidden_other is not None:
                    hidden_other = np.zeros((t_count, chunk.shape[0]), dtype=bool)
                    zbuffer_margin = np.empty((t_count, chunk.shape[0]), dtype=np.float32)
            # under a rolling shutter the depths at the capture time (the depth maps and the
            # z-buffer are drawn there too)
            if rolling and surfels is not None:
                points_camera, pixels, valid, to_camera = projection.project(chunk, at_capture=True, towards=True)
                # the back-face test and its margin from one cosine per point-frame, the camera
                # where it was when its row saw the point
                from drivetrack.visibility.facing import facing_test_towards

                front_facing, face_margin = facing_test_towards(
                    to_camera, SurfelNormals(surfels.normal[start:stop], surfels.reliable[start:stop]),
                    float(config.back_face_max_deg))
                del to_camera
            else:
                points_camera, pixels, valid = projection.project(chunk, at_capture=True)
            if rolling and hidden_other is not None:
                zbuffer_test(start, points_camera, pixels, valid)
            ok = valid & model.inside_image(pixels) & np.isfinite(pixels).all(axis=-1)
            surface = lookup_max4(clip_maps, pixels, grow_px)                         # [T, n] float32
            occluded = (surface > 0) & (surface < config.occlusion_ratio * points_camera[..., 0])
            if own_box.shape[0]:
                occluded &= ~own_surface(chunk, surface / points_camera[..., 0], own_box, where=occluded,
                                         reliable=own_points[start:start + chunk.shape[0]])
                occluded &= ~other_surface(chunk, surface / points_camera[..., 0], own_box, others, where=occluded)
            visible = ok & ~occluded
            faces = facing(start, start + chunk.shape[0])
            if faces is not None:
                visible &= faces
            # world displacement between consecutive frames, (W B)_{tau+1} p - (W B)_tau p, in one pass
            if t_count > 1 and duration_s > 0:
                steps = _carry(world_step, chunk)                                      # [T-1, n, 3]
                speeds[start:stop] = np.linalg.norm(steps, axis=-1).sum(axis=0) / duration_s
            else:
                speeds[start:stop] = np.nan
            # only the kept points of the chunk are materialised in [n, T] order
            seen = visible.any(axis=0)
            chunk_keep = seen.copy()
            if speed_filter:
                chunk_keep &= np.abs(speeds[start:stop] - box_speed_mean) <= max_deviation
            dropped_invisible += int((~seen).sum())
            dropped_speed += int((seen & ~chunk_keep).sum())
            keep[start:stop] = chunk_keep
            idx = np.flatnonzero(chunk_keep)
            tracks = fill_invalid_positions(np.swapaxes(pixels[:, idx], 0, 1).astype(np.float32))
            chunk_visibles = np.ascontiguousarray(visible[:, idx].T)
            chunk_query, chunk_checks = _summarise_tracks(tracks, chunk_visibles, source_clip[start:stop][idx], model)
            checks += chunk_checks
            parts.append((chunk_visibles, chunk_query))
            # the kept point-frames' occlusion margins, while the chunk's test results, projection
            # and depth lookups are held (its columns)
            cols = slice(start - held_from, stop - held_from)
            margins = _occlusion_margins(
                config, model, t_count, lambda at: (points_camera[:, at], pixels[:, at], valid[:, at], surface[:, at]),
                chunk, idx, None if zbuffer_margin is None else zbuffer_margin[:, cols],
                None if face_margin is None else face_margin[:, cols], own_box, own_points[start:stop], others)
            num_ambiguous += int((np.abs(margins) < 1.0).sum())     # NaN (outside the image) compares False
            if config.occlusion_margins:
                margin_parts.append(margins.astype(np.float16))
            del margins
        if parts:
            visibles = np.concatenate([p[0] for p in parts], axis=0)
            query_pixels = np.concatenate([p[1] for p in parts], axis=0)
        else:
            visibles = np.empty((0, t_count), dtype=bool)
            query_pixels = np.empty((0, 2), dtype=np.float32)
        del parts
        margin16 = None
        if config.occlusion_margins:
            margin16 = (np.concatenate(margin_parts, axis=0) if margin_parts
                        else np.empty((0, t_count), dtype=np.float16))
        del margin_parts
        source = TrackSource(p_box[keep], camera_from_box, shift_camera, vehicle_from_box, None,
                             numpy_path=(projection, p_box, keep, int(config.chunk_points)))
        occluders = []
    errors = np.abs(speeds - box_speed_mean)
    kept_lidar = lidar_rows[keep]
    sources = np.stack([lidar.laser[kept_lidar], lidar.return_index[kept_lidar],
                        lidar.row[kept_lidar], lidar.col[kept_lidar]], axis=-1).astype(np.int32)
    result = ObjectTracks(
        split=scene.split, segment=scene.segment, camera=job.camera, object_id=job.object_id,
        object_type=job.object_type, frames=frames.copy(), timestamps_micros=timestamps,
        visibles=visibles, points_box=source.points_box,
        query_frames=source_clip[keep].astype(np.int32), lidar_sources=sources,
        track_speed_mps=speeds[keep], box_speed_mps=box_speed_mean, speed_error_mps=errors[keep],
        camera_model=model, camera_from_vehicle=geometry.camera_from_vehicle[frames].copy(),
        world_from_vehicle=scene.world_from_vehicle[frames].copy(),
        jpeg=[frames_meta.jpeg[t] for t in frames.tolist()], source=source, query_pixels=query_pixels,
        num_nonfinite_visible=int(checks[0]), num_visible_outside_image=int(checks[1]),
        min_camera_distance_m=job.min_camera_distance_m,
        # the projection model in use; a global-shutter camera under it projects as global
        projection="rolling_shutter" if projector is not None else "global_shutter",
        num_candidates=int(n_candidates), num_dropped_invisible=dropped_invisible,
        num_dropped_speed=dropped_speed,
        rejection=None if keep.any() else RejectionReason.NO_VISIBLE_POINTS,
        time_model=config.time_model,
        label_time=poses.trajectory.label_time if poses.trajectory is not None else "frame",
        time_residual_m=_outside_box_m(p_box, boxes.size[rows], source_clip),
        num_unreliable_normals=0 if surfels is None else surfels.num_unreliable,
        num_ambiguous_occlusion=num_ambiguous,
        occlusion_margin=margin16,
    )
    return result


def _scaled(margin: np.ndarray, unit: float) -> np.ndarray:
    """``margin`` in units of ``unit`` (> 0); with ``unit`` 0 only the sign is left (0 stays 0)."""
    if unit > 0:
        return margin / np.float32(unit)
    return np.where(margin == 0, np.float32(0.0), np.sign(margin) * np.float32(np.inf)).astype(np.float32)


def _unpacked(bits: np.ndarray, start: int, stop: int) -> np.ndarray:
    """bool [T, stop - start]: candidates ``start:stop`` (``start`` a multiple of 8) of bits packed
    over the candidates by ``np.packbits``, uint8 [T, ceil(K / 8)]."""
    return np.unpackbits(bits[:, start // 8:(stop + 7) // 8], axis=1)[:, :stop - start].view(bool)


def _occlusion_margins(config, model: CameraModel, t_count: int, project, p_box: np.ndarray,
                       rows: np.ndarray, zbuffer_margin: np.ndarray | None,
                       face_margin: np.ndarray | None, own_box: np.ndarray, own_points: np.ndarray,
                       others: np.ndarray | None = None) -> np.ndarray:
    """float32 [K, T]: the occlusion margin of the kept candidates ``rows`` int [K] of ``p_box``
    (see :class:`ObjectTracks`' ``occlusion_margin``).

    ``t_count`` the clip's frames T; ``project(rows int [k])`` returns ``(points_camera [T, k, 3],
    pixels [T, k, 2], valid [T, k], surface float32 [T, k])`` of those rows of ``p_box`` float
    [n, 3] as the track path projected them and looked them up in the clip's depth maps
    (``lookup_max4``: the numpy path passes its chunk's, computed once); ``zbuffer_margin``
    (metres) and ``face_margin`` (degrees) float32 [T, n] over ``p_box``'s rows, None when that
    test is off; ``own_box`` float64 [T, 13] or [0, 13] (off) and
    ``own_points`` bool [n]: where the depth map's surface is the object's own
    (:func:`drivetrack.visibility.own_surface`) at a point it applies to, or another labelled
    object's spread beyond its outline (``others`` float64 [T, K, 21],
    :func:`drivetrack.visibility.other_surface`), the depth-map test cannot hide the point (+inf).
    """
    out = np.empty((rows.size, t_count), dtype=np.float32)
    for start in range(0, rows.size, config.chunk_points):
        idx = rows[start:start + config.chunk_points]
        points_camera, pixels, valid, surface = project(idx)
        inside = valid & model.inside_image(pixels) & np.isfinite(pixels).all(axis=-1)
        margin = np.where(surface > 0, surface - float(config.occlusion_ratio) * points_camera[..., 0],
                          np.inf).astype(np.float32)
        margin = _scaled(margin, float(config.ambiguity_m))
        face = None if face_margin is None else _scaled(face_margin[:, idx], float(config.ambiguity_deg))
        if own_box.shape[0]:
            # the depth-map term only matters where it is smaller than the back-face term (+inf
            # at an unreliable normal; exact, and few point-frames to place)
            own = own_surface(p_box[idx], surface / points_camera[..., 0], own_box, where=margin < face,
                              reliable=own_points[idx])
            margin[own] = np.inf
        zbuffer = None if zbuffer_margin is None else _scaled(zbuffer_margin[:, idx], float(config.ambiguity_m))
        if own_box.shape[0] and others is not None and others.shape[1]:
            # the depth-map term where it is the smallest (the decision and the margin as above)
            rest = np.full(margin.shape, np.inf, dtype=np.float32)
            for term in (face, zbuffer):
                if term is not None:
                    np.minimum(rest, term, out=rest)
            margin[other_surface(p_box[idx], surface / points_camera[..., 0], own_box, others,
                                 where=margin < rest)] = np.inf
        if zbuffer is not None:
            margin = np.minimum(margin, zbuffer)
        if face is not None:
            margin = np.minimum(margin, face)
        margin[~inside] = np.nan
        out[start:start + idx.size] = margin.T
    return out


def _outside_box_m(points_box: np.ndarray, size: np.ndarray, box: np.ndarray, step: int = 1 << 16) -> float:
    """Mean distance (metres) of box-frame points float [n, 3] outside their boxes, point ``i`` of
    the box of size ``size[box[i]]`` (``size`` float [T, 3], ``box`` int [n]); NaN if none. The
    distances are computed ``step`` points at a time (bounded temporaries), their mean at once."""
    if points_box.shape[0] == 0:
        return float("nan")
    distance = np.empty(points_box.shape[0], dtype=np.float64)
    for start in range(0, points_box.shape[0], step):
        part = slice(start, start + step)
        distance[part] = np.linalg.norm(np.maximum(np.abs(points_box[part]) - size[box[part]] / 2.0, 0.0), axis=-1)
    return float(distance.mean())


def _summarise_tracks(tracks: np.ndarray, visibles: np.ndarray, source_frames: np.ndarray,
                      model: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """Query pixels and sanity counts of a chunk of tracks (numpy; as ``kernel.summarise_tracks``).

    Args: tracks float32 [k, T, 2], visibles bool [k, T], source_frames int [k] (clip frames).
    Returns: ``(query_pixels float32 [k, 2], int64 [2] = (visible but not finite, visible and
    finite but outside the image))``; the query frame is the source frame when visible there,
    else the first visible frame (TAPVid-3D ``queries_xyt``).
    """
    rows = np.arange(tracks.shape[0])
    source = source_frames.astype(np.int64)
    frame = np.where(visibles[rows, source], source, np.argmax(visibles, axis=1))
    finite = np.isfinite(tracks).all(axis=-1)
    with np.errstate(invalid="ignore"):
        inside = ((tracks[..., 0] >= 0) & (tracks[..., 0] < model.width)
                  & (tracks[..., 1] >= 0) & (tracks[..., 1] < model.height))
    counts = np.array([(visibles & ~finite).sum(), (visibles & finite & ~inside).sum()], dtype=np.int64)
    return tracks[rows, frame].astype(np.float32), counts
