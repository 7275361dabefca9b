"""Camera rendering by ray casting (global or rolling shutter) and the camera boxes of the hits."""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from drivetrack.geometry import invert_rigid
from drivetrack.synth.boxes import _box_matrix, _pixel_rays, _rect_indices, _screen_rect, _undistorted_extent
from drivetrack.synth.raycast import GROUND, cast, surface_albedo_normal
from drivetrack.synth.texture import SKY_HORIZON, SKY_TOP

SUN = np.array([0.45, -0.35, 0.82]) / np.linalg.norm([0.45, -0.35, 0.82])


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


class _CameraRendering:
    """Camera half of :class:`drivetrack.synth.state._Generator` (uses its state)."""

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
