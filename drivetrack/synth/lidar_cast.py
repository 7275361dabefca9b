"""Lidar casting: every laser's two returns per frame, the rows of ``lidar``, ``lidar_pose``,
``lidar_camera_projection`` and the truth's object returns."""
from __future__ import annotations

import numpy as np

from drivetrack.geometry import invert_rigid, transform_points
from drivetrack.synth.config import SWEEP_S
from drivetrack.synth.raycast import Hits, cast, surface_albedo_normal
from drivetrack.synth.sensors import LidarSpec
from drivetrack.waymo import lidar as lidar_geometry
from drivetrack.waymo.schema import LaserName


class _LidarCasting:
    """Lidar half of :class:`drivetrack.synth.state._Generator` (uses its state)."""

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

    def cast_lidar(self, spec: LidarSpec, t: int, range_noise=None):
        """Cast both returns of one lidar at frame t.

        Returns a dict with ``range`` float32 [2, H, W], ``intensity``, ``elongation``,
        ``obj`` int32 [2, H, W], ``points_world`` float64 [2, H, W, 3] (where each ray hit the
        surface), ``measured_world`` float64 [2, H, W, 3] (the return as measured, at the written
        range), ``capture_time`` [W], ``pose`` float64 [W, 6] (world_from_vehicle per column, TOP
        only). ``range_noise``: None, or ``(rng, sigma_m)``: each written range is the true one
        plus Gaussian noise of ``sigma_m`` metres (the return moves along its ray; the truth keeps
        the surface point).
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
            for name in ("t", "obj", "axis", "t_exit", "part"):
                getattr(second, name)[second_local] = getattr(sub, name)
        out = {"range": np.zeros((2, H, W), np.float32), "intensity": np.zeros((2, H, W), np.float32),
               "elongation": np.zeros((2, H, W), np.float32), "obj": np.full((2, H, W), -2, np.int32),
               "points_world": np.zeros((2, H, W, 3)), "measured_world": np.zeros((2, H, W, 3)),
               "capture_time": col_time, "pose": pose}
        for r, hits in enumerate((first, second)):
            ok = np.isfinite(hits.t)
            albedo, normal = surface_albedo_normal(hits, o_all, d_all, self.world, pose_of)
            cos_inc = np.abs(np.sum(normal * d_all, axis=-1))
            flat = rays_idx[ok]
            measured = hits.t[ok]
            if range_noise is not None:
                rng, sigma_m = range_noise
                # at least 1 cm: a return never moves behind the sensor
                measured = np.maximum(measured + rng.normal(0.0, sigma_m, size=measured.shape), 0.01)
            out["range"][r].reshape(-1)[flat] = measured
            out["intensity"][r].reshape(-1)[flat] = (0.02 + albedo[ok].mean(-1) * cos_inc[ok]
                                                     * (0.6 if r else 1.0))
            out["elongation"][r].reshape(-1)[flat] = 0.05 + 0.3 * (1.0 - cos_inc[ok])
            out["obj"][r].reshape(-1)[flat] = hits.obj[ok]
            out["points_world"][r].reshape(-1, 3)[flat] = o_all[ok] + hits.t[ok, None] * d_all[ok]
            out["measured_world"][r].reshape(-1, 3)[flat] = o_all[ok] + measured[:, None] * d_all[ok]
        return out
