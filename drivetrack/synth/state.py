"""One segment's generation state: world, sensors, exact poses at any instant, camera timing.

The camera rendering and the lidar casting live in :mod:`drivetrack.synth.render` and
:mod:`drivetrack.synth.lidar_cast` (mixins of :class:`_Generator`); see
:mod:`drivetrack.synth.generate` for the timing conventions.
"""
from __future__ import annotations

import numpy as np

from drivetrack.camera.model import CameraModel
from drivetrack.geometry import invert_rigid
from drivetrack.synth.boxes import _box_matrix, _rotate_rpy, _screen_rect
from drivetrack.synth.config import (FRAME_PERIOD_S, LABEL_RANGE_M, T0_MICROS, SynthConfig, segment_name,
                                     sweep_offset)
from drivetrack.synth.lidar_cast import _LidarCasting
from drivetrack.synth.render import _CameraRendering
from drivetrack.synth.sensors import GLOBAL_SHUTTER, PRESETS, READOUT_S, SHUTTER_S, camera_models, lidar_specs
from drivetrack.synth.world import World, make_world, with_car_shape, with_pedestrian_shape


class _Generator(_CameraRendering, _LidarCasting):
    """State of one segment's generation (one instance per segment, not shared)."""

    def __init__(self, config: SynthConfig, index: int):
        if config.preset not in PRESETS:
            raise ValueError(f"unknown preset {config.preset!r}; choose from {sorted(PRESETS)}")
        if config.frames < 1:
            raise ValueError(f"frames must be >= 1, got {config.frames}")
        self.config = config
        self.preset = PRESETS[config.preset]
        # the fourth child leaves the first three (and so every world before it) as they were
        world_seq, id_seq, noise_seq, speed_seq = np.random.SeedSequence([config.seed, index]).spawn(4)
        self.segment = segment_name(config.seed, index)
        self.T = config.frames
        self.times = np.arange(self.T) * FRAME_PERIOD_S
        self.timestamps = (T0_MICROS + index * 10**9 + np.arange(self.T) * 100_000).astype(np.int64)
        self.world: World = with_car_shape(make_world(np.random.default_rng(world_seq), self.T * FRAME_PERIOD_S,
                                                      config.world, config.speed_changes_mps2,
                                                      np.random.default_rng(speed_seq),
                                                      config.rear_axle_fraction), config.car_shape)
        self.world = with_pedestrian_shape(self.world, config.pedestrian_shape)
        self.id_rng = np.random.default_rng(id_seq)
        self.noise_rng = np.random.default_rng(noise_seq)
        self.rolling = bool(config.rolling_shutter)
        self.cameras = camera_models(self.preset, tuple(config.cameras),
                                     None if self.rolling else GLOBAL_SHUTTER)
        self.lidars = lidar_specs(self.preset)
        #: seconds from the frame time to each camera's pose_timestamp (0 unless triggered by the sweep)
        self.camera_offsets = {cam: (float(sweep_offset(np.arctan2(m.vehicle_from_camera[1, 0],
                                                                   m.vehicle_from_camera[0, 0])))
                                     if config.trigger == "sweep" else 0.0)
                               for cam, m in self.cameras.items()}
        K = len(self.world.objects)
        self.K = K
        self.world_from_vehicle = self.world.world_from_vehicle(self.times)          # [T,4,4]
        self.centers = np.stack([o.center(self.times) for o in self.world.objects])  # [K,T,3]
        self.headings = np.stack([o.heading(self.times) for o in self.world.objects])  # [K,T]
        self.sizes = np.array([o.size for o in self.world.objects])                  # [K,3]
        ego_xy = self.world_from_vehicle[:, :2, 3]
        dist = np.linalg.norm(self.centers[:, :, :2] - ego_xy[None], axis=-1)
        self.labelled = dist < LABEL_RANGE_M                                         # [K,T]
        # filled while generating
        self.rects: dict[tuple[int, int], list] = {}
        self.visible_pixels = np.zeros((len(self.cameras), self.T, K), np.int64)
        self.camera_boxes: list[tuple] = []
        self.camera_frames = {cam: self._camera_frames(model, self.camera_offsets[cam])
                              for cam, model in self.cameras.items()}
        self._laws: dict[tuple[int, int], tuple | None] = {}

    # ----------------------------------------------------------------- camera timing
    def _camera_frames(self, model: CameraModel, offset: float = 0.0):
        """:class:`CameraFrames` (no images) holding exactly the ``camera_image`` values written;
        ``offset`` (s) moves the pose time (and the pose, velocity, trigger and readout times) from
        the frame time."""
        from drivetrack.scene import CameraFrames

        if offset == 0.0:
            world_from_vehicle = self.world_from_vehicle
            lin, ang = self.world.ego_velocity(self.times)
            pose_ts = self.timestamps / 1e6
        else:
            world_from_vehicle = self.world.world_from_vehicle(self.times + offset)
            lin, ang = self.world.ego_velocity(self.times + offset)
            pose_ts = self.timestamps / 1e6 + offset
        if self.rolling:   # the official model reads the angular velocity in the vehicle frame
            ang = np.einsum("tji,tj->ti", world_from_vehicle[:, :3, :3], ang)
        return CameraFrames(
            model=model, jpeg=[None] * self.T, world_from_vehicle=world_from_vehicle,
            pose_timestamp=pose_ts, velocity=np.concatenate([lin, ang], axis=-1),
            shutter=np.full(self.T, SHUTTER_S),
            trigger_time=pose_ts - SHUTTER_S / 2 - READOUT_S / 2,
            readout_done_time=pose_ts + SHUTTER_S / 2 + READOUT_S / 2)

    def sweep_label_times(self, iterations: int = 6) -> np.ndarray:
        """float64 [K, T] s since frame 0: when the TOP sweep passed each object's box centre.

        Fixed point of ``t = times[t] + sweep_offset(azimuth of the centre at t, seen from the
        TOP lidar at t)`` (the column-time law of ``cast_lidar``; azimuths in the lidar frame plus
        its mount yaw, as ``beam_azimuths`` has it). The map contracts by (angular rate of the
        object around the lidar) x 0.1 s / (2 pi), far below 1; 6 iterations reach 1e-9 s."""
        from drivetrack.waymo.schema import LaserName

        spec = self.lidars[int(LaserName.TOP)]
        mount_yaw = np.arctan2(spec.vehicle_from_lidar[1, 0], spec.vehicle_from_lidar[0, 0])
        base = np.broadcast_to(self.times[None, :], (self.K, self.T))
        tl = base.copy()
        index = np.broadcast_to(np.arange(self.K)[:, None], (self.K, self.T)).ravel()
        for _ in range(iterations):
            center, _ = self.object_poses_at(index, tl.ravel())
            world_from_lidar = self.world.world_from_vehicle(tl.ravel()) @ spec.vehicle_from_lidar
            rel = center - world_from_lidar[:, :3, 3]
            p = np.einsum("nji,nj->ni", world_from_lidar[:, :3, :3], rel)
            tl = base + sweep_offset(np.arctan2(p[:, 1], p[:, 0]) + mount_yaw).reshape(self.K, self.T)
        return tl

    def time_law(self, cam: int, t: int) -> tuple[int, float, float] | None:
        """Capture-time law of image ``t`` of camera ``cam``, None for a global shutter.

        ``(axis, time_per_normalised, offset)``: a camera-frame ray or point with undistorted
        normalised coordinate ``n = -p[1 + axis] / p[0]`` (axis 0: u, columns; 1: v, rows) is
        captured at ``self.times[t] + offset + time_per_normalised * n`` (seconds since frame 0).
        """
        key = (cam, t)
        if key not in self._laws:
            from drivetrack.camera.rolling_shutter import shutter_state

            state = shutter_state(self.camera_frames[cam], t)
            offset = self.camera_offsets[cam]
            if state.rolling:
                self._laws[key] = (0 if state.horizontal else 1, float(state.time_per_normalised),
                                   offset - float(state.pose_offset))
            else:   # a global shutter away from the frame time: a law with zero readout rate
                self._laws[key] = None if offset == 0.0 else (0, 0.0, offset)
        return self._laws[key]

    def camera_poses_at(self, model: CameraModel, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(world_rot_camera float64 [n, 3, 3], camera_centre_world float64 [n, 3])`` at times [n] (s)."""
        world_from_vehicle = self.world.world_from_vehicle(times)
        rot = world_from_vehicle[:, :3, :3] @ model.vehicle_from_camera[:3, :3]
        centre = world_from_vehicle[:, :3, :3] @ model.vehicle_from_camera[:3, 3] + world_from_vehicle[:, :3, 3]
        return rot, centre

    def camera_centres_rays_at(self, model: CameraModel, times: np.ndarray, rays_camera: np.ndarray):
        """``(camera_centre_world float64 [n, 3], rays_world float64 [n, 3])``: camera-frame
        vectors [n, 3] turned into the world frame by the camera pose at times [n] (s).

        Elementwise (no [n, 4, 4] matrices): the per-pixel poses of a readout cost little."""
        rpy_xyz = self.world.ego_rpy_xyz(times)
        rays_vehicle = rays_camera @ model.vehicle_from_camera[:3, :3].T
        rays = _rotate_rpy(rays_vehicle, rpy_xyz)
        lever = _rotate_rpy(np.broadcast_to(model.vehicle_from_camera[:3, 3], rays.shape), rpy_xyz)
        return lever + rpy_xyz[:, 3:], rays

    def camera_from_world_at(self, model: CameraModel, times: np.ndarray, points_world: np.ndarray):
        """float64 [n, 3]: world points [n, 3] in the camera frame of the pose at times [n] (s)."""
        rpy_xyz = self.world.ego_rpy_xyz(times)
        points_vehicle = _rotate_rpy(points_world - rpy_xyz[:, 3:], rpy_xyz, inverse=True)
        return (points_vehicle - model.vehicle_from_camera[:3, 3]) @ model.vehicle_from_camera[:3, :3]

    def object_poses_at(self, object_index: np.ndarray, times: np.ndarray):
        """``(center float64 [n, 3], heading float64 [n])`` of objects [n] at times [n] (s)."""
        center = np.empty((object_index.size, 3))
        heading = np.empty(object_index.size)
        for k in np.unique(object_index):
            m = object_index == k
            obj = self.world.objects[int(k)]
            center[m], heading[m] = obj.center(times[m]), obj.heading(times[m])
        return center, heading

    def rolling_rect(self, model: CameraModel, extent, k: int, times: np.ndarray):
        """Screen rectangle of object k over a readout: the union of :func:`_screen_rect` with
        camera and object at ``times`` (float [S] samples spanning the image's capture times).

        Poses are smooth and the readout lasts tens of ms, so a silhouette moves by a near-linear
        path: the union of its rectangles at 9 samples, padded by 3 px, contains it."""
        rot, centre = self.camera_poses_at(model, times)
        obj = self.world.objects[k]
        union = None
        for i, s in enumerate(times):
            world_from_camera = np.eye(4)
            world_from_camera[:3, :3], world_from_camera[:3, 3] = rot[i], centre[i]
            camera_from_box = invert_rigid(world_from_camera) @ _box_matrix(obj.center(s), obj.heading(s))
            rect = _screen_rect(model, extent, camera_from_box, self.sizes[k])
            if rect is None:
                continue
            union = rect if union is None else (min(union[0], rect[0]), max(union[1], rect[1]),
                                                min(union[2], rect[2]), max(union[3], rect[3]))
        return union
