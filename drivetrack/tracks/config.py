"""Every knob of the track stage, in one dataclass built once at the entry point."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

from drivetrack.waymo.schema import BoxType, CameraName, LaserName

__all__ = ["TrackConfig", "FOV_RUN_POLICIES", "TRACK_KERNELS"]

#: What to do when an object's in-view frames form more than one continuous run.
#: ``reject``: the paper's rule (the object may not leave the image and come back), counted under
#: ``label_gap`` / ``image_gap`` / ``left_and_returned``; ``longest``: keep the longest run.
FOV_RUN_POLICIES = ("reject", "longest")

#: Implementations of the track stage's global-shutter inner loop (``TrackConfig.kernel``).
TRACK_KERNELS = ("numba", "numpy")


@dataclass(frozen=True)
class TrackConfig:
    """Configuration of the depth and track stages (defaults follow the DriveTrack paper).

    Attributes:
        object_types: ``BoxType`` names annotated (default vehicles only).
        cameras: ``CameraName`` names annotated (default the three front cameras).
        lasers: ``LaserName`` names whose returns form the object point clouds (default all).
        returns: return indices used for object points (1 = first, 2 = second).
        min_frames: minimum length, in frames, of the continuous run in view (paper: 24).
        fov_runs: see :data:`FOV_RUN_POLICIES`.
        fov_samples_per_axis: a box is "in view" at a frame when one of its
            ``n**3`` grid samples (corners, edges, faces, interior) projects inside the image in
            front of the camera with trusted distortion.
        max_camera_distance_m: the box centre must come within this distance of the *camera
            centre* at some frame of the clip (paper: 20 m; the released code used 50 m).
        box_margin_m: grows (> 0) or shrinks (< 0) the box when selecting its LiDAR points.
        ground_clearance_m: points less than this above the box bottom are dropped (ground).
        occlusion_ratio: a point is occluded at a frame when the depth map there is known and
            ``depth < occlusion_ratio * z`` (z = the point's z-depth from the camera). 0.95 is the
            released code's factor; 1.0 is a strict test.
        depth_completer: name in the ``drivetrack.depth`` completer registry.
        depth_completer_options: keyword arguments of that completer (e.g. ``max_reach_px``).
        depth_batch: frames per completion batch (the GPU-queue unit).
        depth_lasers: ``LaserName`` names whose returns build the occlusion depth maps (default
            all five lidars).
        depth_returns: return indices that build the depth maps. Default first returns only:
            second returns at object edges put the surface *behind* an occluder into the map
            and make occluded points look visible (measured: docs/benchmarks.md).
        see_through_window_deg: drop from the sparse maps, before completion, the returns the
            camera cannot see because the LiDAR saw them past a nearer surface (over a car
            beside the camera, round a pole): :func:`drivetrack.depth.see_through_returns` with
            quadrant windows of this angle (``f_u * tan(angle)`` pixels) and ``occlusion_ratio``.
            The default 0.5 degree (18 px at Waymo's 1920 px width) spans about two scan lines
            of the TOP LiDAR (64 beams over ~20 degrees). None keeps every return.
        see_through_min_quadrants: quadrants (of 4) that must hold a nearer return.
        blind_zone_laser: ``LaserName`` of the roof LiDAR beside the cameras (one of
            ``depth_lasers``), or None. Below its lowest scan line in an image (its blind zone round
            the vehicle), the sparse maps are bounded by that line's depth
            (:func:`drivetrack.depth.bound_blind_zone`, column cells of
            ``see_through_window_deg``, 0.5 degree when that is None): a car beside the camera
            that no LiDAR sees there occludes instead of being unknown, and what other lidars
            saw under or round it is dropped.
        compensate_sweep_motion: when the scene has ``lidar.capture_offset_s``, select points in
            boxes and compute box-frame points with each box moved to the return's capture time
            (object motion during the LiDAR sweep, :mod:`drivetrack.tracks.sweep_motion`).
        rolling_shutter: project with ``drivetrack.rolling_shutter`` when it is available;
            global-shutter projection at the image pose otherwise.
        max_speed_deviation_mps: if set, drop tracks whose mean world speed deviates from the
            box's annotated mean speed by more than this (paper's remedy for non-rigid parts).
        max_tracks_per_object: if set, keep a seeded random subset of this many candidate points.
        seed: seed of that subset.
        chunk_points: points processed at once (bounds the [T, chunk, 3] float64 temporaries).
        kernel: inner loop of the global-shutter projection, ``numba`` (fused kernel,
            :mod:`drivetrack.tracks.kernel`) or ``numpy`` (the reference; rolling-shutter cameras
            always use it).
        writers: output writers (registry names in :mod:`drivetrack.tracks.writers`).
    """
    object_types: tuple[str, ...] = ("VEHICLE",)
    cameras: tuple[str, ...] = ("FRONT", "FRONT_LEFT", "FRONT_RIGHT")
    lasers: tuple[str, ...] = ("TOP", "FRONT", "SIDE_LEFT", "SIDE_RIGHT", "REAR")
    returns: tuple[int, ...] = (1, 2)
    min_frames: int = 24
    fov_runs: str = "reject"
    fov_samples_per_axis: int = 5
    max_camera_distance_m: float = 20.0
    box_margin_m: float = 0.0
    ground_clearance_m: float = 0.2
    occlusion_ratio: float = 0.95
    depth_completer: str = "nearest"
    depth_completer_options: dict = field(default_factory=dict, hash=False)
    depth_batch: int = 16
    depth_lasers: tuple[str, ...] = ("TOP", "FRONT", "SIDE_LEFT", "SIDE_RIGHT", "REAR")
    depth_returns: tuple[int, ...] = (1,)
    see_through_window_deg: float | None = 0.5
    see_through_min_quadrants: int = 3
    blind_zone_laser: str | None = "TOP"
    rolling_shutter: bool = True
    compensate_sweep_motion: bool = True
    max_speed_deviation_mps: float | None = None
    max_tracks_per_object: int | None = None
    seed: int = 0
    chunk_points: int = 8192
    kernel: str = "numba"
    writers: tuple[str, ...] = ("drivetrack", "tapvid3d")

    def __post_init__(self):
        for name, enum_type in (("object_types", BoxType), ("cameras", CameraName),
                                ("lasers", LaserName), ("depth_lasers", LaserName)):
            values = getattr(self, name)
            if isinstance(values, str):
                raise ValueError(f"TrackConfig.{name} must be a sequence of names, got the string {values!r}")
            object.__setattr__(self, name, tuple(values))
            for value in values:
                if value not in enum_type.__members__:
                    raise ValueError(f"TrackConfig.{name}: unknown {enum_type.__name__} {value!r}; "
                                     f"expected one of {sorted(enum_type.__members__)}")
        object.__setattr__(self, "returns", tuple(int(r) for r in self.returns))
        object.__setattr__(self, "depth_returns", tuple(int(r) for r in self.depth_returns))
        if not set(self.depth_returns) <= {1, 2} or not self.depth_returns:
            raise ValueError(f"TrackConfig.depth_returns must be a non-empty subset of (1, 2), "
                             f"got {self.depth_returns}")
        if self.see_through_window_deg is not None and not 0 < self.see_through_window_deg < 45:
            raise ValueError(f"TrackConfig.see_through_window_deg must be None or in (0, 45) degrees, "
                             f"got {self.see_through_window_deg}")
        if self.see_through_min_quadrants not in (1, 2, 3, 4):
            raise ValueError(f"TrackConfig.see_through_min_quadrants must be 1..4, got {self.see_through_min_quadrants}")
        if self.blind_zone_laser is not None and self.blind_zone_laser not in self.depth_lasers:
            raise ValueError(f"TrackConfig.blind_zone_laser must be None or one of depth_lasers "
                             f"{self.depth_lasers}, got {self.blind_zone_laser!r}")
        object.__setattr__(self, "writers", tuple(self.writers))
        object.__setattr__(self, "depth_completer_options", dict(self.depth_completer_options))
        if not set(self.returns) <= {1, 2}:
            raise ValueError(f"TrackConfig.returns must be among (1, 2), got {self.returns}")
        if self.fov_runs not in FOV_RUN_POLICIES:
            raise ValueError(f"TrackConfig.fov_runs must be one of {FOV_RUN_POLICIES}, got {self.fov_runs!r}")
        if self.min_frames < 1:
            raise ValueError(f"TrackConfig.min_frames must be >= 1, got {self.min_frames}")
        if self.fov_samples_per_axis < 2:
            raise ValueError(f"TrackConfig.fov_samples_per_axis must be >= 2, got {self.fov_samples_per_axis}")
        if not self.occlusion_ratio > 0:
            raise ValueError(f"TrackConfig.occlusion_ratio must be > 0, got {self.occlusion_ratio}")
        if self.kernel not in TRACK_KERNELS:
            raise ValueError(f"TrackConfig.kernel must be one of {TRACK_KERNELS}, got {self.kernel!r}")
        if self.chunk_points < 1 or self.depth_batch < 1:
            raise ValueError("TrackConfig.chunk_points and depth_batch must be >= 1")
        if self.max_tracks_per_object is not None and self.max_tracks_per_object < 1:
            raise ValueError(f"TrackConfig.max_tracks_per_object must be >= 1 or None, "
                             f"got {self.max_tracks_per_object}")

    @property
    def object_type_values(self) -> tuple[int, ...]:
        return tuple(int(BoxType[name]) for name in self.object_types)

    @property
    def camera_values(self) -> tuple[int, ...]:
        return tuple(int(CameraName[name]) for name in self.cameras)

    @property
    def laser_values(self) -> tuple[int, ...]:
        return tuple(int(LaserName[name]) for name in self.lasers)

    @property
    def depth_laser_values(self) -> tuple[int, ...]:
        return tuple(int(LaserName[name]) for name in self.depth_lasers)

    def to_dict(self) -> dict:
        """JSON-ready dict (tuples become lists) for run.json / manifests."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, values: dict) -> "TrackConfig":
        """Inverse of :meth:`to_dict`; unknown keys raise, naming them."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"TrackConfig: unknown keys {unknown}")
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in values.items()})
