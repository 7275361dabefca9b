"""Generate one synthetic segment: sensors by ray casting, Waymo v2 components, exact truth.

Timing: frame ``t`` is at ``t * 0.1`` s. Cameras are global-shutter at the frame time (their
``pose_timestamp``) unless ``SynthConfig.rolling_shutter`` is on (see below); the TOP lidar sweeps during ``[t - 0.05, t + 0.05]`` s, column ``c`` at
``t + ((c + 0.5) / W - 0.5) * 0.1`` s, cast from the vehicle pose of that instant with moving
objects at their pose of that instant (written per pixel to ``lidar_pose``); the short lidars
fire at the frame time.

Rolling shutter (``SynthConfig.rolling_shutter``): each camera gets a real readout direction
(:data:`~drivetrack.synth.sensors.ROLLING_SHUTTER_DIRECTIONS`), and every pixel is rendered at
its own capture time with the ego pose and every object's pose of that instant (closed-form world
model, no linearisation). The capture time follows the Waymo camera model exactly as
:mod:`drivetrack.rolling_shutter` implements it: linear in the undistorted normalised coordinate
of the pixel's ray along the readout axis (``v = -z/x`` for row readouts, ``u = -y/x`` for column
readouts), ``t = pose_timestamp - pose_offset + time_per_normalised * coordinate``, constants from
:func:`drivetrack.rolling_shutter.shutter_state` of the written ``camera_image`` fields. The
ground truth uses the same law: each body point's capture time is solved by fixed-point
iteration on ``t = law(coordinate of the point at t, seen by the camera at t)`` to 1e-12 s, so
truth pixels, visibility and dense depth are exact with respect to the rendered images.
``camera_image.velocity`` then carries the angular velocity in the vehicle frame (the official
model's convention; the global-shutter output keeps its previous bytes).
``lidar_camera_projection`` and ``projected_lidar_box`` stay global-shutter projections at the
frame pose.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from drivetrack.camera.model import CameraModel
from drivetrack.geometry import invert_rigid, points_in_box_mask, transform_points
from drivetrack.synth import ground_truth as gt
from drivetrack.synth.raycast import GROUND, Hits, cast, intersect_box, surface_albedo_normal
from drivetrack.synth.sensors import (DEFAULT_CAMERAS, GLOBAL_SHUTTER, PRESETS, READOUT_S,
                                      SHUTTER_S, LidarSpec, camera_models, lidar_specs)
from drivetrack.synth.texture import SKY_HORIZON, SKY_TOP
from drivetrack.synth.world import World, make_world
from drivetrack.waymo import lidar as lidar_geometry
from drivetrack.waymo.schema import COMPONENTS, BoxType, CameraName, LaserName
from drivetrack.waymo.writer import fixed_list_array, list_array, write_component

__all__ = ["SynthConfig", "generate_segment", "segment_name", "FRAME_PERIOD_S", "SWEEP_S",
           "LABEL_RANGE_M"]

FRAME_PERIOD_S = 0.1
SWEEP_S = 0.1
LABEL_RANGE_M = 75.0
T0_MICROS = 1_557_000_000_000_000
SUN = np.array([0.45, -0.35, 0.82]) / np.linalg.norm([0.45, -0.35, 0.82])


@dataclass(frozen=True)
class SynthConfig:
    """What to generate. ``box_noise_m`` is the sigma (metres, per axis) of Gaussian noise added
    to the *written* box centres; ``heading_noise_rad`` defaults to 1 degree per 5 cm of it.
    ``rolling_shutter`` renders rolling-shutter cameras (module docstring); off by default, which
    keeps the global-shutter output byte-identical to earlier versions."""
    seed: int = 7
    frames: int = 40
    preset: str = "small"
    cameras: tuple[str, ...] = DEFAULT_CAMERAS
    split: str = "training"
    box_noise_m: float = 0.0
    heading_noise_rad: float | None = None
    rolling_shutter: bool = False

    @property
    def heading_sigma(self) -> float:
        if self.heading_noise_rad is not None:
            return float(self.heading_noise_rad)
        return float(np.deg2rad(1.0) * self.box_noise_m / 0.05)


def segment_name(seed: int, index: int) -> str:
    """Deterministic ``key.segment_context_name`` of synthetic segment ``index`` of ``seed``."""
    return f"drivetrack_synth_s{seed}_{index:04d}"


_EDGES = np.array([(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7),
                   (0, 4), (1, 5), (2, 6), (3, 7)])
_CORNER_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)


def _box_corners(size) -> np.ndarray:
    """float64 [8, 3] corners of a box of ``size`` in its own frame (index bits: x, y, z)."""
    return _CORNER_SIGNS * (np.asarray(size, np.float64) / 2.0)


def _box_edge_samples(size, n: int = 9) -> np.ndarray:
    """float64 [12 * n, 3] points on the 12 edges of a box of ``size`` (box frame)."""
    c = _box_corners(size)
    s = np.linspace(0.0, 1.0, n)[:, None]
    return np.concatenate([c[a] + s * (c[b] - c[a]) for a, b in _EDGES])


_RAY_CACHE: dict[tuple, np.ndarray] = {}


def _pixel_rays(model: CameraModel) -> np.ndarray:
    """float64 [H * W, 3] unit camera-frame rays of every pixel centre (row-major), from
    :meth:`CameraModel.rays_from_pixels` with 10 iterations (they reproject onto their pixel
    centre within 1e-8 px for these calibrations); computed in chunks, cached per intrinsics."""
    key = (model.f_u, model.f_v, model.c_u, model.c_v, model.k1, model.k2, model.p1, model.p2,
           model.k3, model.width, model.height)
    rays = _RAY_CACHE.get(key)
    if rays is None:
        H, W = model.height, model.width
        rays = np.empty((H * W, 3))
        step = max(1, 65536 // W)
        xs = np.arange(W) + 0.5
        for y0 in range(0, H, step):
            ys = np.arange(y0, min(H, y0 + step)) + 0.5
            px = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None]), -1).reshape(-1, 2)
            rays[y0 * W:y0 * W + px.shape[0]] = model.rays_from_pixels(px, iterations=10)
        if len(_RAY_CACHE) > 8:
            _RAY_CACHE.clear()
        _RAY_CACHE[key] = rays
    return rays


def _undistorted_extent(model: CameraModel, rays: np.ndarray) -> tuple[float, float, float, float]:
    """(u_min, u_max, v_min, v_max) of the image border in undistorted coordinates
    (u = -y/x, v = -z/x), grown by 2 %."""
    r = rays.reshape(model.height, model.width, 3)
    border = np.concatenate([r[0], r[-1], r[:, 0], r[:, -1]])
    u, v = -border[:, 1] / border[:, 0], -border[:, 2] / border[:, 0]
    du, dv = 0.02 * (u.max() - u.min()), 0.02 * (v.max() - v.min())
    return u.min() - du, u.max() + du, v.min() - dv, v.max() + dv


def _screen_rect(model: CameraModel, extent, camera_from_box: np.ndarray, size, pad: int = 3):
    """(x0, x1, y0, y1) pixel columns/rows (inclusive-exclusive) containing the projection of a box,
    or None when no part of it can appear in the image.

    Exact construction: the box is clipped to the plane x = 0.01 m in front of the camera; the
    bounding rectangle of the clipped vertices in undistorted coordinates contains the silhouette;
    that rectangle (cut to the image's extent) is mapped through the distortion by sampling its
    border densely, and padded by ``pad`` pixels.
    """
    eps = 0.01
    corners = transform_points(camera_from_box, _box_corners(size))
    a, b = corners[_EDGES[:, 0]], corners[_EDGES[:, 1]]
    xa, xb = a[:, 0], b[:, 0]
    pts = [corners[corners[:, 0] >= eps]]
    cross = (xa - eps) * (xb - eps) < 0
    if cross.any():
        s = (eps - xa[cross]) / (xb[cross] - xa[cross])
        pts.append(a[cross] + s[:, None] * (b[cross] - a[cross]))
    pts = np.concatenate(pts)
    if pts.shape[0] == 0:
        return None
    u, v = -pts[:, 1] / pts[:, 0], -pts[:, 2] / pts[:, 0]
    u0, u1 = max(u.min(), extent[0]), min(u.max(), extent[1])
    v0, v1 = max(v.min(), extent[2]), min(v.max(), extent[3])
    if u0 >= u1 or v0 >= v1:
        return None
    s = np.linspace(0.0, 1.0, 65)
    bu = np.concatenate([u0 + s * (u1 - u0), u0 + s * (u1 - u0), np.full(65, u0), np.full(65, u1)])
    bv = np.concatenate([np.full(65, v0), np.full(65, v1), v0 + s * (v1 - v0), v0 + s * (v1 - v0)])
    px, valid = model.pixels_from_camera(np.stack([np.ones_like(bu), -bu, -bv], -1))
    if not valid.all():
        return (0, model.width, 0, model.height)
    x0 = max(int(np.floor(px[:, 0].min())) - pad, 0)
    x1 = min(int(np.ceil(px[:, 0].max())) + pad, model.width)
    y0 = max(int(np.floor(px[:, 1].min())) - pad, 0)
    y1 = min(int(np.ceil(px[:, 1].max())) + pad, model.height)
    if x0 >= x1 or y0 >= y1:
        return None
    return (x0, x1, y0, y1)


def _apply(dst_from_src: np.ndarray, points: np.ndarray) -> np.ndarray:
    """float64 [n, 3]: one rigid transform [4, 4] applied to points [n, 3] (BLAS, no einsum)."""
    return (dst_from_src[:3, :3] @ points.T).T + dst_from_src[:3, 3]


def _yaw_transform(points_box: np.ndarray, center: np.ndarray, heading) -> np.ndarray:
    """World points float64 [n, 3] of box-frame points, box at ``center`` [n, 3] / ``heading`` [n]."""
    c, s = np.cos(heading), np.sin(heading)
    x = c * points_box[..., 0] - s * points_box[..., 1] + center[..., 0]
    y = s * points_box[..., 0] + c * points_box[..., 1] + center[..., 1]
    return np.stack([x, y, points_box[..., 2] + center[..., 2]], axis=-1)


def _rotate_rpy(vectors: np.ndarray, rpy: np.ndarray, inverse: bool = False) -> np.ndarray:
    """float64 [n, 3]: ``Rz(yaw) Ry(pitch) Rx(roll)`` (``geometry.rotation_from_rpy``) applied to
    vectors [n, 3] with angles ``rpy[:, :3]`` (radians), or its transpose when ``inverse``."""
    cr, sr = np.cos(rpy[:, 0]), np.sin(rpy[:, 0])
    cp, sp = np.cos(rpy[:, 1]), np.sin(rpy[:, 1])
    cy, sy = np.cos(rpy[:, 2]), np.sin(rpy[:, 2])
    x, y, z = vectors[:, 0], vectors[:, 1], vectors[:, 2]
    if not inverse:
        y, z = cr * y - sr * z, sr * y + cr * z
        x, z = cp * x + sp * z, -sp * x + cp * z
        x, y = cy * x - sy * y, sy * x + cy * y
    else:
        x, y = cy * x + sy * y, -sy * x + cy * y
        x, z = cp * x - sp * z, sp * x + cp * z
        y, z = cr * y + sr * z, -sr * y + cr * z
    return np.stack([x, y, z], axis=-1)


def _rect_indices(rect, width: int) -> np.ndarray:
    x0, x1, y0, y1 = rect
    return (np.arange(y0, y1)[:, None] * width + np.arange(x0, x1)[None, :]).ravel()


def _shade(albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
    lambert = np.clip(normal @ SUN.astype(np.float32), 0.0, 1.0)
    return albedo * (0.45 + 0.6 * lambert)[:, None]


def _encode_jpeg(rgb: np.ndarray, quality: int) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]),
                           [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


class _Generator:
    """State of one segment's generation (one instance per segment, not shared)."""

    def __init__(self, config: SynthConfig, index: int):
        if config.preset not in PRESETS:
            raise ValueError(f"unknown preset {config.preset!r}; choose from {sorted(PRESETS)}")
        if config.frames < 1:
            raise ValueError(f"frames must be >= 1, got {config.frames}")
        self.config = config
        self.preset = PRESETS[config.preset]
        world_seq, id_seq, noise_seq = np.random.SeedSequence([config.seed, index]).spawn(3)
        self.segment = segment_name(config.seed, index)
        self.T = config.frames
        self.times = np.arange(self.T) * FRAME_PERIOD_S
        self.timestamps = (T0_MICROS + index * 10**9 + np.arange(self.T) * 100_000).astype(np.int64)
        self.world: World = make_world(np.random.default_rng(world_seq), self.T * FRAME_PERIOD_S)
        self.id_rng = np.random.default_rng(id_seq)
        self.noise_rng = np.random.default_rng(noise_seq)
        self.rolling = bool(config.rolling_shutter)
        self.cameras = camera_models(self.preset, tuple(config.cameras),
                                     None if self.rolling else GLOBAL_SHUTTER)
        self.lidars = lidar_specs(self.preset)
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
        self.camera_frames = {cam: self._camera_frames(model) for cam, model in self.cameras.items()}
        self._laws: dict[tuple[int, int], tuple | None] = {}

    # ----------------------------------------------------------------- camera timing
    def _camera_frames(self, model: CameraModel):
        """:class:`CameraFrames` (no images) holding exactly the ``camera_image`` values written."""
        from drivetrack.scene import CameraFrames

        lin, ang = self.world.ego_velocity(self.times)
        if self.rolling:   # the official model reads the angular velocity in the vehicle frame
            ang = np.einsum("tji,tj->ti", self.world_from_vehicle[:, :3, :3], ang)
        pose_ts = self.timestamps / 1e6
        return CameraFrames(
            model=model, jpeg=[None] * self.T, world_from_vehicle=self.world_from_vehicle,
            pose_timestamp=pose_ts, velocity=np.concatenate([lin, ang], axis=-1),
            shutter=np.full(self.T, SHUTTER_S),
            trigger_time=pose_ts - SHUTTER_S / 2 - READOUT_S / 2,
            readout_done_time=pose_ts + SHUTTER_S / 2 + READOUT_S / 2)

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
            self._laws[key] = (None if not state.rolling else
                               (0 if state.horizontal else 1, float(state.time_per_normalised),
                                -float(state.pose_offset)))
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

    # ----------------------------------------------------------------- cameras
    def render_cameras(self, progress: Callable[[], None] | None = None, workers: int = 1):
        """Render every camera frame; returns (jpegs {cam: [T] bytes}, depth {cam: [T,H,W]}).

        ``workers`` > 1 renders cameras in threads (numpy releases the GIL in its kernels);
        results do not depend on it.
        """
        jpegs, depths = {}, {}

        def one_camera(ci, cam, model):
            H, W = model.height, model.width
            rays_cam = _pixel_rays(model)                                             # [P,3]
            extent = _undistorted_extent(model, rays_cam)
            rays_t = np.ascontiguousarray(rays_cam.T)                                  # [3,P]
            depth = np.zeros((self.T, H, W), np.float32)
            images = []
            for t in range(self.T):
                law = self.time_law(cam, t)
                if law is None:
                    world_from_camera = self.world_from_vehicle[t] @ model.vehicle_from_camera
                    camera_from_world = invert_rigid(world_from_camera)
                    dirs = (world_from_camera[:3, :3] @ rays_t).T                 # [P,3] F-order
                    origins = np.broadcast_to(world_from_camera[:3, 3], dirs.shape)
                    candidates = []
                    for k in range(self.K):
                        camera_from_box = camera_from_world @ _box_matrix(self.centers[k, t], self.headings[k, t])
                        rect = _screen_rect(model, extent, camera_from_box, self.sizes[k])
                        self.rects[(ci, t, k)] = rect
                        candidates.append(None if rect is None else _rect_indices(rect, W))

                    def pose_of(k, idx, t=t):
                        return self.centers[k, t], self.headings[k, t]
                else:
                    axis, rate, offset = law
                    normalised = -rays_cam[:, 1 + axis] / rays_cam[:, 0]
                    pixel_time = self.times[t] + offset + rate * normalised          # [P] s
                    origins, dirs = np.empty_like(rays_cam), np.empty_like(rays_cam)
                    for p0 in range(0, pixel_time.size, 1 << 18):               # bounded memory
                        sl = slice(p0, p0 + (1 << 18))
                        origins[sl], dirs[sl] = self.camera_centres_rays_at(model, pixel_time[sl], rays_cam[sl])
                    samples = np.linspace(pixel_time.min(), pixel_time.max(), 9)
                    candidates = []
                    for k in range(self.K):
                        rect = self.rolling_rect(model, extent, k, samples)
                        self.rects[(ci, t, k)] = rect
                        candidates.append(None if rect is None else _rect_indices(rect, W))

                    def pose_of(k, idx, pixel_time=pixel_time):
                        obj = self.world.objects[k]
                        return obj.center(pixel_time[idx]), obj.heading(pixel_time[idx])

                hits = cast(origins, dirs, self.world, pose_of, candidates)
                depth[t] = np.where(np.isfinite(hits.t), hits.t * rays_t[0], 0.0).reshape(H, W)
                albedo, normal = surface_albedo_normal(hits, origins, dirs, self.world, pose_of)
                rgb = _shade(albedo, normal)
                sky = np.flatnonzero(hits.obj < GROUND)
                if sky.size:
                    elev = np.clip(dirs[:, 2][sky], 0.0, 1.0)[:, None].astype(np.float32)
                    rgb[sky] = SKY_HORIZON + (SKY_TOP - SKY_HORIZON) * np.sqrt(elev)
                img = (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8).reshape(H, W, 3)
                images.append(_encode_jpeg(img, self.preset.jpeg_quality))
                self._camera_boxes_from_ids(ci, cam, t, hits.obj.reshape(H, W))
                if progress:
                    progress()
            return cam, images, depth

        jobs = [(ci, cam, model) for ci, (cam, model) in enumerate(self.cameras.items())]
        if workers > 1:
            from concurrent.futures import ThreadPoolExecutor
            with ThreadPoolExecutor(max_workers=workers) as pool:
                results = list(pool.map(lambda job: one_camera(*job), jobs))
        else:
            results = [one_camera(*job) for job in jobs]
        for cam, images, depth in results:
            jpegs[cam], depths[cam] = images, depth
        self.camera_boxes.sort(key=lambda r: (r[0], r[1], r[2]))
        return jpegs, depths

    def _camera_boxes_from_ids(self, ci, cam, t, ids):
        for k in range(self.K):
            rect = self.rects[(ci, t, k)]
            if rect is None:
                continue
            x0, x1, y0, y1 = rect
            mask = ids[y0:y1, x0:x1] == k
            count = int(mask.sum())
            self.visible_pixels[ci, t, k] = count
            if count < 4 or not self.labelled[k, t]:
                continue
            ys = np.flatnonzero(mask.any(axis=1))
            xs = np.flatnonzero(mask.any(axis=0))
            bx0, bx1 = x0 + xs[0], x0 + xs[-1] + 1
            by0, by1 = y0 + ys[0], y0 + ys[-1] + 1
            self.camera_boxes.append((t, cam, k, (bx0 + bx1) / 2.0, (by0 + by1) / 2.0,
                                      float(bx1 - bx0), float(by1 - by0)))

    # ----------------------------------------------------------------- lidars
    def _column_window(self, spec: LidarSpec, azimuths, lidar_from_world, k, t) -> np.ndarray | None:
        """Columns whose rays may hit object k during the sweep (exactness kept by margins)."""
        obj = self.world.objects[k]
        c = transform_points(lidar_from_world, self.centers[k, t][None])[0]
        d = float(np.hypot(c[0], c[1]))
        r = 0.5 * float(np.hypot(obj.size[0], obj.size[1])) + 2.0
        if d - r > spec.max_range:
            return None
        if d <= r + 0.5:
            return np.arange(spec.width)
        half = np.arcsin(min(r / d, 1.0)) + 0.05
        diff = np.angle(np.exp(1j * (azimuths - np.arctan2(c[1], c[0]))))
        cols = np.flatnonzero(np.abs(diff) <= half)
        return cols if cols.size else None

    def cast_lidar(self, spec: LidarSpec, t: int):
        """Cast both returns of one lidar at frame t.

        Returns a dict with ``range`` float32 [2, H, W], ``intensity``, ``elongation``,
        ``obj`` int32 [2, H, W], ``points_world`` float64 [2, H, W, 3], ``capture_time`` [W],
        ``pose`` float64 [W, 6] (world_from_vehicle per column, TOP only).
        """
        H, W = spec.height, spec.width
        incl = lidar_geometry.beam_inclinations(H, spec.inclination_values, spec.inclination_min,
                                                spec.inclination_max)
        az = lidar_geometry.beam_azimuths(W, spec.vehicle_from_lidar)
        dirs_sensor = lidar_geometry.sensor_directions(incl, az)                     # [H,W,3]
        if spec.laser == int(LaserName.TOP):
            col_time = self.times[t] + ((np.arange(W) + 0.5) / W - 0.5) * SWEEP_S
        else:
            col_time = np.full(W, self.times[t])
        pose = self.world.ego_rpy_xyz(col_time)                                        # [W,6]
        world_from_lidar = self.world.world_from_vehicle(col_time) @ spec.vehicle_from_lidar  # [W,4,4]
        dirs = np.einsum("wij,hwj->hwi", world_from_lidar[:, :3, :3], dirs_sensor)
        origins = np.broadcast_to(world_from_lidar[None, :, :3, 3], (H, W, 3))
        active_cols = np.flatnonzero(np.abs(np.angle(np.exp(1j * az))) <= spec.half_fov)
        rays_idx = (np.arange(H)[:, None] * W + active_cols[None, :]).ravel()
        o_all = origins.reshape(-1, 3)[rays_idx]
        d_all = dirs.reshape(-1, 3)[rays_idx]
        col_of_ray = rays_idx % W
        obj_centers = [o.center(col_time) for o in self.world.objects]                # K x [W,3]
        obj_heads = [o.heading(col_time) for o in self.world.objects]
        lidar_from_world_t = invert_rigid(self.world_from_vehicle[t] @ spec.vehicle_from_lidar)
        pos_in_active = np.full(W, -1, np.int64)
        pos_in_active[active_cols] = np.arange(active_cols.size)
        candidates = []
        for k in range(self.K):
            cols = self._column_window(spec, az, lidar_from_world_t, k, t)
            if cols is None:
                candidates.append(None)
                continue
            cols = cols[pos_in_active[cols] >= 0]
            p = pos_in_active[cols]
            candidates.append((np.arange(H)[:, None] * active_cols.size + p[None, :]).ravel())

        def pose_of(k, idx):
            cols = col_of_ray[idx]
            return obj_centers[k][cols], obj_heads[k][cols]

        first = cast(o_all, d_all, self.world, pose_of, candidates, t_max=spec.max_range)
        n = rays_idx.size
        # second returns: object-edge pixels see what lies beyond the object
        obj_img = np.full((H, W), -3, np.int32)
        obj_img.reshape(-1)[rays_idx] = first.obj
        edge = np.zeros((H, W), bool)
        for axis, shift in ((0, 1), (0, -1), (1, 1), (1, -1)):
            edge |= np.roll(obj_img, shift, axis=axis) != obj_img
        edge &= obj_img >= 0
        second_local = np.flatnonzero(edge.reshape(-1)[rays_idx])
        second = Hits.empty(n)
        if second_local.size:
            def pose_sub(k, i):
                return pose_of(k, second_local[i])
            sub = cast(o_all[second_local], d_all[second_local], self.world, pose_sub,
                       [np.arange(second_local.size)] * self.K,
                       t_min=first.t_exit[second_local] + 0.05, t_max=spec.max_range)
            for name in ("t", "obj", "axis", "t_exit"):
                getattr(second, name)[second_local] = getattr(sub, name)
        out = {"range": np.zeros((2, H, W), np.float32), "intensity": np.zeros((2, H, W), np.float32),
               "elongation": np.zeros((2, H, W), np.float32), "obj": np.full((2, H, W), -2, np.int32),
               "points_world": np.zeros((2, H, W, 3)), "capture_time": col_time, "pose": pose}
        for r, hits in enumerate((first, second)):
            ok = np.isfinite(hits.t)
            albedo, normal = surface_albedo_normal(hits, o_all, d_all, self.world, pose_of)
            cos_inc = np.abs(np.sum(normal * d_all, axis=-1))
            flat = rays_idx[ok]
            out["range"][r].reshape(-1)[flat] = hits.t[ok]
            out["intensity"][r].reshape(-1)[flat] = (0.02 + albedo[ok].mean(-1) * cos_inc[ok]
                                                     * (0.6 if r else 1.0))
            out["elongation"][r].reshape(-1)[flat] = 0.05 + 0.3 * (1.0 - cos_inc[ok])
            out["obj"][r].reshape(-1)[flat] = hits.obj[ok]
            out["points_world"][r].reshape(-1, 3)[flat] = o_all[ok] + hits.t[ok, None] * d_all[ok]
        return out


def _flat16(m: np.ndarray) -> np.ndarray:
    return np.asarray(m, np.float64).reshape(-1, 16)


def generate_segment(root: str, config: SynthConfig, index: int = 0,
                     progress: Callable[[str, int, int], None] | None = None,
                     workers: int = 1) -> dict:
    """Generate segment ``index`` of ``config`` under ``root``; returns a summary dict
    (segment name, files written with byte sizes, counts).

    ``progress(stage, done, total)`` is called as work advances (stages ``cameras``, ``lidar``,
    ``truth``, ``write``). ``workers`` threads render the cameras (output does not depend on it).
    """
    g = _Generator(config, index)
    seg, T, K = g.segment, g.T, g.K
    world = g.world
    cams = list(g.cameras.items())
    total_cam = len(cams) * T
    done = [0]

    def tick_cam():
        done[0] += 1
        if progress:
            progress("cameras", done[0], total_cam)

    jpegs, depths = g.render_cameras(tick_cam, workers=workers)
    gt_url = gt.ground_truth_url(root, config.split, seg)
    sizes = {}
    for cam in list(depths):
        name = f"depth_{CameraName(cam).name}.npz"
        sizes[name] = gt.write_npz(f"{gt_url}/{name}", {"depth": depths.pop(cam)})

    # ------------------------------------------------------------- lidar
    lidar_rows, pose_rows, proj_rows = [], [], []
    hit_records = []
    points_vehicle_all = {}   # (t) -> list of (laser, points_vehicle)
    lasers = sorted(g.lidars)
    for t in range(T):
        vehicle_from_world_t = invert_rigid(g.world_from_vehicle[t])
        for laser in lasers:
            spec = g.lidars[laser]
            res = g.cast_lidar(spec, t)
            H, W = spec.height, spec.width
            ri = np.stack([res["range"], res["intensity"], res["elongation"],
                           np.where(res["range"] > 0, -1.0, 0.0).astype(np.float32)], axis=-1)  # [2,H,W,4]
            lidar_rows.append((t, laser, ri))
            if laser == int(LaserName.TOP):
                pose_img = np.broadcast_to(res["pose"][None], (H, W, 6)).astype(np.float32)
                pose_rows.append((t, laser, pose_img))
            proj = np.zeros((2, H, W, 6), np.float32)
            for r in range(2):
                valid = res["range"][r] > 0
                pw = res["points_world"][r][valid]
                slot = np.zeros(pw.shape[0], np.int64)
                vals = proj[r][valid]
                for cam, model in cams:
                    camera_from_world = invert_rigid(g.world_from_vehicle[t] @ model.vehicle_from_camera)
                    px, ok = model.pixels_from_camera(_apply(camera_from_world, pw))
                    ok &= model.inside_image(px)
                    for s in (0, 1):
                        put = ok & (slot == s)
                        vals[put, 3 * s] = cam
                        vals[put, 3 * s + 1] = np.floor(px[put, 0])
                        vals[put, 3 * s + 2] = np.floor(px[put, 1])
                        slot[put] += 1
                        ok &= ~put
                proj[r][valid] = vals
                pv = _apply(vehicle_from_world_t, pw)
                points_vehicle_all.setdefault(t, []).append((laser, pv))
                obj = res["obj"][r][valid]
                hit = obj >= 0
                if hit.any():
                    rows, cols = np.nonzero(valid)
                    ct = res["capture_time"][cols[hit]]
                    ko = obj[hit]
                    pb = np.zeros((int(hit.sum()), 3))
                    for k in np.unique(ko):
                        m = ko == k
                        o = world.objects[k]
                        c, h = o.center(ct[m]), o.heading(ct[m])
                        rel = pw[hit][m] - c
                        ch, sh = np.cos(h), np.sin(h)
                        pb[m] = np.stack([ch * rel[:, 0] + sh * rel[:, 1],
                                          -sh * rel[:, 0] + ch * rel[:, 1], rel[:, 2]], -1)
                    hit_records.append(dict(
                        frame=np.full(ko.size, t, np.int32), laser=np.full(ko.size, laser, np.int8),
                        return_index=np.full(ko.size, r + 1, np.int8), row=rows[hit].astype(np.int32),
                        col=cols[hit].astype(np.int32), object_index=ko.astype(np.int32),
                        capture_time=ct, point_vehicle=pv[hit], point_box=pb))
            proj_rows.append((t, laser, proj))
        if progress:
            progress("lidar", t + 1, T)

    # ------------------------------------------------------------- boxes (truth, then labels)
    vehicle_from_world = invert_rigid(g.world_from_vehicle)                          # [T,4,4]
    center_v = np.einsum("tij,ktj->kti", vehicle_from_world[:, :3, :3], g.centers) + vehicle_from_world[None, :, :3, 3]
    box_x_world = np.stack([np.cos(g.headings), np.sin(g.headings), np.zeros_like(g.headings)], -1)
    box_x_v = np.einsum("tij,ktj->kti", vehicle_from_world[:, :3, :3], box_x_world)
    heading_v = np.arctan2(box_x_v[..., 1], box_x_v[..., 0])                          # [K,T]
    vel_world = np.stack([o.velocity(g.times) for o in world.objects])               # [K,T,3]
    acc_world = np.stack([o.acceleration(g.times) for o in world.objects])
    speed_v = np.einsum("tij,ktj->kti", vehicle_from_world[:, :3, :3], vel_world)
    accel_v = np.einsum("tij,ktj->kti", vehicle_from_world[:, :3, :3], acc_world)
    num_pts = np.zeros((K, T), np.int64)
    num_top = np.zeros((K, T), np.int64)
    for t in range(T):
        box_from_vehicle = invert_rigid(_box_matrix(center_v[:, t], heading_v[:, t]))       # [K,4,4]
        for laser, pv in points_vehicle_all.get(t, []):
            pb = (np.matmul(box_from_vehicle[:, :3, :3], pv.T) + box_from_vehicle[:, :3, 3:]).transpose(0, 2, 1)
            inside = points_in_box_mask(pb, g.sizes, margin=1e-6).sum(-1)       # [K]
            num_pts[:, t] += inside
            if laser == int(LaserName.TOP):
                num_top[:, t] += inside
    label_center = center_v.copy()
    label_heading = heading_v.copy()
    if config.box_noise_m > 0:
        label_center += g.noise_rng.normal(0.0, config.box_noise_m, size=label_center.shape)
    if config.heading_sigma > 0:
        label_heading += g.noise_rng.normal(0.0, config.heading_sigma, size=label_heading.shape)
        label_heading = np.angle(np.exp(1j * label_heading))

    tables = _build_tables(g, jpegs, lidar_rows, pose_rows, proj_rows, label_center, label_heading,
                           speed_v, accel_v, num_pts, num_top)
    files = {}
    for i, (name, cols) in enumerate(tables.items()):
        url = write_component(cols, root, config.split, name, seg)
        files[name] = url
        if progress:
            progress("write", i + 1, len(tables))
    del tables, jpegs, lidar_rows, pose_rows, proj_rows, points_vehicle_all   # bound peak memory

    # ------------------------------------------------------------- exact ground truth
    hits = {k: np.concatenate([h[k] for h in hit_records]) if hit_records else None
            for k in ("frame", "laser", "return_index", "row", "col", "object_index",
                      "capture_time", "point_vehicle", "point_box")}
    if not hit_records:
        hits = _empty_hits()
    pixels, visible = _carry_and_check(g, hits["object_index"], hits["point_box"], progress)
    hits["pixels"] = pixels
    hits["visible"] = visible
    world_from_box = np.stack([o.world_from_box(g.times) for o in world.objects])
    sizes["objects.npz"] = gt.write_npz(f"{gt_url}/objects.npz", dict(
        object_id=np.array([o.object_id for o in world.objects]),
        type=np.array([o.type for o in world.objects], np.int8), size=g.sizes,
        world_from_box=world_from_box, velocity_world=vel_world, labelled=g.labelled,
        timestamps_micros=g.timestamps, world_from_vehicle=g.world_from_vehicle,
        camera_names=np.array([c for c, _ in cams], np.int8)))
    sizes["lidar_hits.npz"] = gt.write_npz(f"{gt_url}/lidar_hits.npz", hits)
    return {"segment": seg, "files": files, "ground_truth": gt_url, "ground_truth_bytes": sizes,
            "num_frames": T, "num_objects": K, "num_object_returns": int(hits["frame"].size),
            "num_visible": int(visible.sum())}


def _empty_hits():
    return dict(frame=np.zeros(0, np.int32), laser=np.zeros(0, np.int8),
                return_index=np.zeros(0, np.int8), row=np.zeros(0, np.int32),
                col=np.zeros(0, np.int32), object_index=np.zeros(0, np.int32),
                capture_time=np.zeros(0), point_vehicle=np.zeros((0, 3)), point_box=np.zeros((0, 3)))


def _box_matrix(center, heading):
    from drivetrack.geometry import box_from_center_heading
    return box_from_center_heading(center, heading)


def _carry_and_check(g: _Generator, object_index: np.ndarray, point_box: np.ndarray, progress):
    """Pixels float32 [N, C, T, 2] and visibility bool [N, C, T] of every body point."""
    N, C, T = object_index.size, len(g.cameras), g.T
    pixels = np.full((N, C, T, 2), np.nan, np.float32)
    visible = np.zeros((N, C, T), bool)
    if N == 0:
        return pixels, visible
    half = g.sizes / 2.0
    for tau in range(T):
        pw_frame = _yaw_transform(point_box, g.centers[object_index, tau], g.headings[object_index, tau])
        for ci, (cam, model) in enumerate(g.cameras.items()):
            law = g.time_law(cam, tau)
            if law is None:
                world_from_camera = g.world_from_vehicle[tau] @ model.vehicle_from_camera
                pw = pw_frame
                pc = _apply(invert_rigid(world_from_camera), pw)
                px, ok = model.pixels_from_camera(pc)
                point_time = None
            else:
                point_time, pw, pc, solved = _solve_capture_times(g, model, law, tau, object_index, point_box)
                px, ok = model.pixels_from_camera(pc)
                ok &= solved
                px[~ok] = np.nan
            pixels[:, ci, tau] = px
            inside = ok & model.inside_image(px)
            cand = np.flatnonzero(inside)
            if cand.size == 0:
                continue
            if point_time is None:
                origin = np.broadcast_to(world_from_camera[:3, 3], (cand.size, 3))
            else:
                origin = g.camera_centres_rays_at(model, point_time[cand], np.zeros((cand.size, 3)))[0]
            vec = pw[cand] - origin
            dist = np.linalg.norm(vec, axis=-1)
            dirs = vec / dist[:, None]
            best = np.full(cand.size, np.inf)
            best_obj = np.full(cand.size, -1)
            with np.errstate(divide="ignore", invalid="ignore"):
                tg = -origin[:, 2] / dirs[:, 2]
            ground_first = (dirs[:, 2] < 0) & (tg > 0)
            best = np.where(ground_first, tg, best)
            pxc = px[cand]
            own = object_index[cand]
            by_x = np.argsort(pxc[:, 0], kind="stable")
            xs_sorted = pxc[by_x, 0]
            by_own = np.argsort(own, kind="stable")
            own_bounds = np.searchsorted(own[by_own], np.arange(g.K + 1))
            origins = origin
            for k in range(g.K):
                rect = g.rects[(ci, tau, k)]
                own_k = by_own[own_bounds[k]:own_bounds[k + 1]]
                if rect is None:
                    sel = own_k
                else:
                    x0, x1, y0, y1 = rect
                    lo, hi = np.searchsorted(xs_sorted, [x0, x1], side="left")
                    in_x = by_x[lo:hi]
                    in_rect = in_x[(pxc[in_x, 1] >= y0) & (pxc[in_x, 1] < y1)]
                    sel = np.union1d(in_rect, own_k)
                if sel.size == 0:
                    continue
                if point_time is None:
                    center_k, heading_k = g.centers[k, tau], g.headings[k, tau]
                else:
                    obj = g.world.objects[k]
                    center_k, heading_k = obj.center(point_time[cand[sel]]), obj.heading(point_time[cand[sel]])
                t_in, _, _ = intersect_box(origins[sel], dirs[sel], center_k, heading_k, half[k], 0.0)
                better = t_in < best[sel]
                best[sel[better]] = t_in[better]
                best_obj[sel[better]] = k
            vis = (best_obj == own) & (np.abs(best - dist) <= gt.VISIBILITY_TOLERANCE_M)
            visible[cand, ci, tau] = vis
        if progress:
            progress("truth", tau + 1, T)
    return pixels, visible


#: fixed-point iteration on a body point's capture time: stop below this change (s) ...
_TIME_TOLERANCE_S = 1e-12
#: ... or after this many iterations; points still moving by more than 1e-9 s are unsolved.
_TIME_ITERATIONS = 60


def _solve_capture_times(g: _Generator, model: CameraModel, law, tau: int, object_index: np.ndarray,
                         point_box: np.ndarray):
    """When the rolling-shutter camera sees each body point in image ``tau``.

    Solves ``t = times[tau] + offset + rate * n(t)``, with ``n(t)`` the undistorted normalised
    coordinate (along the readout axis) of the point at ``t`` (object pose at ``t``) in the camera
    at ``t`` (ego pose at ``t``), by fixed-point iteration on the still-moving points; the map
    contracts with factor ``rate * dn/dt`` (readout seconds per unit n times the angular rate of
    the point in the camera, below 0.5 even for a car passing 2 m from the lens). Times are
    clipped to 1 s around the frame (points far outside the view; never trusted pixels).

    Returns ``(time float64 [N] s since frame 0, points_world float64 [N, 3] at that time,
    points_camera float64 [N, 3] at that time, solved bool [N])``; ``solved`` is False for
    points behind the camera or whose time still changed by more than 1e-9 s at the end.
    """
    axis, rate, offset = law
    n = object_index.size
    base = g.times[tau]
    dt = np.full(n, offset)
    change = np.full(n, np.inf)
    front = np.ones(n, bool)
    active = np.arange(n)
    for _ in range(_TIME_ITERATIONS):
        if active.size == 0:
            break
        tt = base + dt[active]
        center, heading = g.object_poses_at(object_index[active], tt)
        pw = _yaw_transform(point_box[active], center, heading)
        pc = g.camera_from_world_at(model, tt, pw)
        x = pc[:, 0]
        ok = x > 1e-6
        new = np.clip(offset + rate * (-pc[:, 1 + axis] / np.where(ok, x, 1.0)), -1.0, 1.0)
        new = np.where(ok, new, dt[active])
        change[active] = np.abs(new - dt[active])
        front[active] = ok
        dt[active] = new
        active = active[ok & (change[active] > _TIME_TOLERANCE_S)]
    time = base + dt
    center, heading = g.object_poses_at(object_index, time)
    pw = _yaw_transform(point_box, center, heading)
    pc = g.camera_from_world_at(model, time, pw)
    solved = front & (change <= 1e-9) & (pc[:, 0] > 0)
    return time, pw, pc, solved


def _build_tables(g: _Generator, jpegs, lidar_rows, pose_rows, proj_rows, label_center,
                  label_heading, speed_v, accel_v, num_pts, num_top) -> dict[str, dict]:
    seg, T, K = g.segment, g.T, g.K
    world = g.world
    ts = g.timestamps
    tables: dict[str, dict] = {}
    C = COMPONENTS

    def key_cols(comp, n):
        return {"key.segment_context_name": [seg] * n}

    # vehicle_pose
    vp = C["vehicle_pose"]
    tables["vehicle_pose"] = {**key_cols(vp, T), "key.frame_timestamp_micros": ts,
                              vp.col("world_from_vehicle.transform"): _flat16(g.world_from_vehicle)}
    # camera_calibration
    cc = C["camera_calibration"]
    models = list(g.cameras.items())
    tables["camera_calibration"] = {
        **key_cols(cc, len(models)), "key.camera_name": [c for c, _ in models],
        **{cc.col(f"intrinsic.{p}"): [float(getattr(m, p)) for _, m in models]
           for p in ("f_u", "f_v", "c_u", "c_v", "k1", "k2", "p1", "p2", "k3")},
        cc.col("extrinsic.transform"): _flat16(np.stack([m.vehicle_from_camera for _, m in models])),
        cc.col("width"): [m.width for _, m in models], cc.col("height"): [m.height for _, m in models],
        cc.col("rolling_shutter_direction"): [m.rolling_shutter_direction for _, m in models]}
    # camera_image
    ci_ = C["camera_image"]
    cam_t = [(cam, t) for cam, _ in models for t in range(T)]
    lin, ang = g.world.ego_velocity(g.times)
    if g.rolling:
        ang = g.camera_frames[models[0][0]].velocity[:, 3:]      # vehicle frame (official model)
    pose_ts = ts / 1e6
    shutter, readout = SHUTTER_S, READOUT_S
    tables["camera_image"] = {
        **key_cols(ci_, len(cam_t)), "key.frame_timestamp_micros": [int(ts[t]) for _, t in cam_t],
        "key.camera_name": [cam for cam, _ in cam_t],
        ci_.col("image"): [jpegs[cam][t] for cam, t in cam_t],
        ci_.col("pose.transform"): _flat16(np.stack([g.world_from_vehicle[t] for _, t in cam_t])),
        **{ci_.col(f"velocity.linear_velocity.{a}"): [float(lin[t, i]) for _, t in cam_t]
           for i, a in enumerate("xyz")},
        **{ci_.col(f"velocity.angular_velocity.{a}"): [float(ang[t, i]) for _, t in cam_t]
           for i, a in enumerate("xyz")},
        ci_.col("pose_timestamp"): [float(pose_ts[t]) for _, t in cam_t],
        ci_.col("rolling_shutter_params.shutter"): [shutter] * len(cam_t),
        ci_.col("rolling_shutter_params.camera_trigger_time"):
            [float(pose_ts[t] - shutter / 2 - readout / 2) for _, t in cam_t],
        ci_.col("rolling_shutter_params.camera_readout_done_time"):
            [float(pose_ts[t] + shutter / 2 + readout / 2) for _, t in cam_t]}
    # lidar_calibration
    lc = C["lidar_calibration"]
    specs = [g.lidars[k] for k in sorted(g.lidars)]
    tables["lidar_calibration"] = {
        **key_cols(lc, len(specs)), "key.laser_name": [s.laser for s in specs],
        lc.col("extrinsic.transform"): _flat16(np.stack([s.vehicle_from_lidar for s in specs])),
        lc.col("beam_inclination.min"): [s.inclination_min for s in specs],
        lc.col("beam_inclination.max"): [s.inclination_max for s in specs],
        lc.col("beam_inclination.values"): list_array(
            [None if s.inclination_values is None else s.inclination_values for s in specs], pa_double())}
    # lidar, lidar_pose, lidar_camera_projection

    def range_image_table(name, rows, returns=2):
        comp = C[name]
        out = {**key_cols(comp, len(rows)), "key.frame_timestamp_micros": [int(ts[t]) for t, _, _ in rows],
               "key.laser_name": [laser for _, laser, _ in rows]}
        for r in range(returns):
            imgs = [img[r] if returns == 2 else img for _, _, img in rows]
            vtype = comp.by_name[comp.col(f"range_image_return{r + 1}.values")].type.value_type
            out[comp.col(f"range_image_return{r + 1}.values")] = list_array(imgs, vtype)
            out[comp.col(f"range_image_return{r + 1}.shape")] = np.array([img.shape for img in imgs], np.int32)
        return out

    tables["lidar"] = range_image_table("lidar", lidar_rows)
    tables["lidar_pose"] = range_image_table("lidar_pose", pose_rows, returns=1)
    tables["lidar_camera_projection"] = range_image_table("lidar_camera_projection", proj_rows)
    # lidar_box
    lb = C["lidar_box"]
    kt = [(k, t) for t in range(T) for k in range(K) if g.labelled[k, t]]
    ks = np.array([k for k, _ in kt], np.int64)
    tt = np.array([t for _, t in kt], np.int64)
    npts = num_pts[ks, tt] if kt else np.zeros(0, np.int64)
    difficulty = np.where(npts > 5, 1, 2).astype(np.int8)
    tables["lidar_box"] = {
        **key_cols(lb, len(kt)), "key.frame_timestamp_micros": ts[tt] if kt else [],
        "key.laser_object_id": [world.objects[k].object_id for k in ks],
        **{lb.col(f"box.center.{a}"): label_center[ks, tt, i] for i, a in enumerate("xyz")},
        **{lb.col(f"box.size.{a}"): g.sizes[ks, i] for i, a in enumerate("xyz")},
        lb.col("box.heading"): label_heading[ks, tt],
        lb.col("type"): np.array([world.objects[k].type for k in ks], np.int8),
        lb.col("num_lidar_points_in_box"): npts, lb.col("num_top_lidar_points_in_box"): num_top[ks, tt],
        **{lb.col(f"speed.{a}"): speed_v[ks, tt, i] for i, a in enumerate("xyz")},
        **{lb.col(f"acceleration.{a}"): accel_v[ks, tt, i] for i, a in enumerate("xyz")},
        lb.col("difficulty_level.detection"): difficulty, lb.col("difficulty_level.tracking"): difficulty}
    # lidar_camera_synced_box (cameras fire at the frame time: synced box = frame box)
    sb = C["lidar_camera_synced_box"]
    most = g.visible_pixels.argmax(axis=0)                                          # [T,K]
    most_any = g.visible_pixels.max(axis=0) > 0
    cam_values = np.array([c for c, _ in models], np.int8)
    tables["lidar_camera_synced_box"] = {
        **key_cols(sb, len(kt)), "key.frame_timestamp_micros": ts[tt] if kt else [],
        "key.laser_object_id": [world.objects[k].object_id for k in ks],
        sb.col("most_visible_camera_name"): np.where(most_any[tt, ks], cam_values[most[tt, ks]], 0).astype(np.int8),
        **{sb.col(f"camera_synced_box.center.{a}"): label_center[ks, tt, i] for i, a in enumerate("xyz")},
        **{sb.col(f"camera_synced_box.size.{a}"): g.sizes[ks, i] for i, a in enumerate("xyz")},
        sb.col("camera_synced_box.heading"): label_heading[ks, tt]}
    # projected_lidar_box: the written (possibly noisy) label box projected into each camera
    pb_rows = []
    for ci, (cam, model) in enumerate(models):
        for k, t in kt:
            box = _box_matrix(label_center[k, t], label_heading[k, t])
            samples_v = transform_points(box, _box_edge_samples(g.sizes[k]))
            pc = transform_points(model.camera_from_vehicle, samples_v)
            if not (pc[:, 0] > 0.05).all():
                continue
            px, ok = model.pixels_from_camera(pc)
            if not ok.all():
                continue
            x0, y0 = np.clip(px.min(0), 0, [model.width, model.height])
            x1, y1 = np.clip(px.max(0), 0, [model.width, model.height])
            if x1 - x0 <= 0 or y1 - y0 <= 0:
                continue
            pb_rows.append((t, cam, k, (x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0))
    pl = C["projected_lidar_box"]
    tables["projected_lidar_box"] = {
        **key_cols(pl, len(pb_rows)), "key.frame_timestamp_micros": [int(ts[r[0]]) for r in pb_rows],
        "key.camera_name": [r[1] for r in pb_rows],
        "key.laser_object_id": [world.objects[r[2]].object_id for r in pb_rows],
        pl.col("box.center.x"): [float(r[3]) for r in pb_rows], pl.col("box.center.y"): [float(r[4]) for r in pb_rows],
        pl.col("box.size.x"): [float(r[5]) for r in pb_rows], pl.col("box.size.y"): [float(r[6]) for r in pb_rows],
        pl.col("type"): [world.objects[r[2]].type for r in pb_rows]}
    # camera_box + association
    cam_ids = {(cam, k): _camera_object_id(g.id_rng) for cam, _ in models for k in range(K)}
    cb = C["camera_box"]
    rows = g.camera_boxes
    tables["camera_box"] = {
        **key_cols(cb, len(rows)), "key.frame_timestamp_micros": [int(ts[r[0]]) for r in rows],
        "key.camera_name": [r[1] for r in rows], "key.camera_object_id": [cam_ids[(r[1], r[2])] for r in rows],
        cb.col("box.center.x"): [r[3] for r in rows], cb.col("box.center.y"): [r[4] for r in rows],
        cb.col("box.size.x"): [r[5] for r in rows], cb.col("box.size.y"): [r[6] for r in rows],
        cb.col("type"): [world.objects[r[2]].type for r in rows],
        cb.col("difficulty_level.detection"): [1] * len(rows), cb.col("difficulty_level.tracking"): [1] * len(rows)}
    tables["camera_to_lidar_box_association"] = {
        "key.segment_context_name": [seg] * len(rows), "key.frame_timestamp_micros": [int(ts[r[0]]) for r in rows],
        "key.camera_name": [r[1] for r in rows], "key.camera_object_id": [cam_ids[(r[1], r[2])] for r in rows],
        "key.laser_object_id": [world.objects[r[2]].object_id for r in rows]}
    # stats
    st = C["stats"]
    types = sorted({o.type for o in world.objects})
    lidar_counts = [[int(sum(1 for k in range(K) if g.labelled[k, t] and world.objects[k].type == ty))
                     for ty in types] for t in range(T)]
    cam_counts = [[int(sum(1 for r in rows if r[0] == t and world.objects[r[2]].type == ty)) for ty in types]
                  for t in range(T)]
    tables["stats"] = {
        **key_cols(st, T), "key.frame_timestamp_micros": ts, st.col("time_of_day"): ["Day"] * T,
        st.col("location"): ["location_synthetic"] * T, st.col("weather"): ["sunny"] * T,
        st.col("lidar_object_counts.types"): [types] * T, st.col("lidar_object_counts.counts"): lidar_counts,
        st.col("camera_object_counts.types"): [types] * T, st.col("camera_object_counts.counts"): cam_counts}
    return tables


def pa_double():
    import pyarrow as pa
    return pa.float64()


def _camera_object_id(rng: np.random.Generator) -> str:
    hexdigits = np.array(list("0123456789abcdef"))
    s = "".join(rng.choice(hexdigits, size=32))
    return f"{s[:8]}-{s[8:12]}-{s[12:16]}-{s[16:20]}-{s[20:]}"
