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
:mod:`drivetrack.camera.rolling_shutter` implements it: linear in the undistorted normalised coordinate
of the pixel's ray along the readout axis (``v = -z/x`` for row readouts, ``u = -y/x`` for column
readouts), ``t = pose_timestamp - pose_offset + time_per_normalised * coordinate``, constants from
:func:`drivetrack.camera.rolling_shutter.shutter_state` of the written ``camera_image`` fields. The
ground truth uses the same law: each body point's capture time is solved by fixed-point
iteration on ``t = law(coordinate of the point at t, seen by the camera at t)`` to 1e-12 s, so
truth pixels, visibility and dense depth are exact with respect to the rendered images.
``camera_image.velocity`` then carries the angular velocity in the vehicle frame (the official
model's convention; the global-shutter output keeps its previous bytes).
``lidar_camera_projection`` and ``projected_lidar_box`` stay global-shutter projections at the
frame pose.

Sweep-triggered cameras (``SynthConfig.camera_trigger`` "sweep", the hard world's default): each
camera's pose time is the frame time plus ``config.sweep_offset(camera yaw)`` (where the TOP
sweep crosses its axis); images, dense depth and truth are at that instant (a global shutter is
a time law with zero readout rate there). ``SynthConfig.label_time`` "sweep" writes ``lidar_box``
where each object was when the sweep passed its centre.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from drivetrack.geometry import invert_rigid, points_in_box_mask
from drivetrack.synth import ground_truth as gt
from drivetrack.synth.boxes import (_apply, _box_matrix, _pixel_rays, _rect_indices, _screen_rect,
                                    _undistorted_extent)
from drivetrack.synth.config import (FRAME_PERIOD_S, LABEL_RANGE_M, SWEEP_S, SynthConfig,
                                     segment_name)
from drivetrack.synth.state import _Generator
from drivetrack.synth.tables import _build_tables
from drivetrack.synth.truth import _carry_and_check, _empty_hits
from drivetrack.waymo.schema import CameraName, LaserName
from drivetrack.waymo.writer import write_component

__all__ = ["SynthConfig", "generate_segment", "segment_name", "FRAME_PERIOD_S", "SWEEP_S",
           "LABEL_RANGE_M"]

#: private names other modules and tests reach through this module
_REEXPORTED = (_box_matrix, _pixel_rays, _rect_indices, _screen_rect, _undistorted_extent)


#: Frames on each side of a box in a labeller's speed estimate (:func:`_labeller_motion`).
LABELLER_WINDOW_HALF = 5


def _labeller_motion(g, label_center: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(speed float64 [K, T, 3] m/s, acceleration float64 [K, T, 3] m/s^2)``, vehicle frame of
    each frame: a local quadratic in frame time through the written (noisy) box centres
    ``label_center`` (float64 [K, T, 3], vehicle frame) in the world, over the object's labelled
    frames up to :data:`LABELLER_WINDOW_HALF` before and after."""
    from drivetrack.tracks.trajectory import local_quadratic

    K, T = label_center.shape[:2]
    world = (np.einsum("tij,ktj->kti", g.world_from_vehicle[:, :3, :3], label_center)
             + g.world_from_vehicle[None, :, :3, 3])                                    # [K,T,3]
    steps = np.array([s for s in range(-LABELLER_WINDOW_HALF, LABELLER_WINDOW_HALF + 1) if s])
    other = np.arange(T)[:, None] + steps[None, :]                                       # [T,W]
    inside = (other >= 0) & (other < T)
    other = np.clip(other, 0, T - 1)
    valid = inside[None] & g.labelled[:, other] & g.labelled[:, :, None]                 # [K,T,W]
    delta = world[:, other] - world[:, :, None]                                          # [K,T,W,3]
    tau = np.broadcast_to((g.times[other] - g.times[:, None])[None], valid.shape)
    velocity, acceleration = local_quadratic(delta.reshape(K * T, -1, 3), tau.reshape(K * T, -1),
                                             valid.reshape(K * T, -1))
    rotate = lambda a: np.einsum("tji,ktj->kti", g.world_from_vehicle[:, :3, :3], a.reshape(K, T, 3))  # noqa: E731
    return rotate(velocity), rotate(acceleration)


def _synced_offsets(g, label_center: np.ndarray, speed_v: np.ndarray) -> np.ndarray:
    """float64 [K, T], seconds: ``t_capture - t_frame`` of each box (``label_center``, ``speed_v``
    float64 [K, T, 3], vehicle frame), t_capture the time its most visible camera captures its
    centre moving at ``speed_v`` (:func:`drivetrack.camera.rolling_shutter.capture_offsets` on the
    written ``camera_image`` values); the camera's pose time where the centre does not project
    (behind the camera), 0 where no camera sees the object."""
    from drivetrack.camera.rolling_shutter import capture_offsets

    K, T = label_center.shape[:2]
    out = np.zeros((K, T))
    seen = g.visible_pixels.max(axis=0) > 0                                              # [T,K]
    most = g.visible_pixels.argmax(axis=0)                                               # [T,K]
    frame_s = g.timestamps / 1e6
    for ci, cam in enumerate(g.cameras):
        frames = g.camera_frames[cam]
        for t in range(T):
            ks = np.flatnonzero(seen[t] & (most[t] == ci))
            if ks.size == 0:
                continue
            offset = capture_offsets(frames, t, label_center[ks, t], speed_v[ks, t], g.world_from_vehicle[t], frame_s[t])
            out[ks, t] = np.where(np.isfinite(offset), offset, frames.pose_timestamp[t] - frame_s[t])
    return out


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
    # its own stream: the other draws (box noise, ids) stay the same with or without range noise
    range_noise = ((np.random.default_rng(np.random.SeedSequence([config.seed, index, 5])), config.range_noise_m)
                   if config.range_noise_m > 0 else None)
    for t in range(T):
        vehicle_from_world_t = invert_rigid(g.world_from_vehicle[t])
        for laser in lasers:
            spec = g.lidars[laser]
            res = g.cast_lidar(spec, t, range_noise)
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
                pw = res["points_world"][r][valid]            # where the rays hit (the truth)
                pm = res["measured_world"][r][valid]          # the returns as written
                slot = np.zeros(pw.shape[0], np.int64)
                vals = proj[r][valid]
                for cam, model in cams:
                    camera_from_world = invert_rigid(g.world_from_vehicle[t] @ model.vehicle_from_camera)
                    px, ok = model.pixels_from_camera(_apply(camera_from_world, pm))
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
                points_vehicle_all.setdefault(t, []).append((laser, _apply(vehicle_from_world_t, pm)))
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
    vel_world = np.stack([o.velocity(g.times) for o in world.objects])               # [K,T,3]
    if config.label_time == "sweep":   # the box where the object was when the sweep passed it
        label_times = g.sweep_label_times()                                          # [K,T]
        label_centers = np.stack([o.center(label_times[k]) for k, o in enumerate(world.objects)])
        label_headings = np.stack([o.heading(label_times[k]) for k, o in enumerate(world.objects)])
        label_vel = np.stack([o.velocity(label_times[k]) for k, o in enumerate(world.objects)])
        acc_world = np.stack([o.acceleration(label_times[k]) for k, o in enumerate(world.objects)])
    else:
        label_times = np.broadcast_to(g.times[None, :], (K, T))
        label_centers, label_headings, label_vel = g.centers, g.headings, vel_world
        acc_world = np.stack([o.acceleration(g.times) for o in world.objects])
    center_v = np.einsum("tij,ktj->kti", vehicle_from_world[:, :3, :3], label_centers) + vehicle_from_world[None, :, :3, 3]
    box_x_world = np.stack([np.cos(label_headings), np.sin(label_headings), np.zeros_like(label_headings)], -1)
    box_x_v = np.einsum("tij,ktj->kti", vehicle_from_world[:, :3, :3], box_x_world)
    heading_v = np.arctan2(box_x_v[..., 1], box_x_v[..., 0])                          # [K,T]
    speed_v = np.einsum("tij,ktj->kti", vehicle_from_world[:, :3, :3], label_vel)
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

    if config.box_noise_m > 0:
        # a labeller's speed: the slope of its own noisy boxes (Waymo's speed labels are derived
        # from the box centres over time), not the truth's; objects that never move keep speed 0
        # (Waymo's parked cars carry 0, up to rounding)
        fitted = _labeller_motion(g, label_center)
        moves = (vel_world != 0).any(axis=(1, 2))[:, None, None]                        # [K,1,1]
        speed_v, accel_v = np.where(moves, fitted[0], speed_v), np.where(moves, fitted[1], accel_v)
    # lidar_camera_synced_box, by label.proto: the label box living at the frame time with its
    # speed v, moved to t_capture, when its most visible camera captures the box centre (rolling
    # shutter and ego motion solved by the camera model): c + v (t_capture - t_frame), same heading
    synced_center = label_center + speed_v * _synced_offsets(g, label_center, speed_v)[..., None]
    synced_heading = label_heading
    tables = _build_tables(g, jpegs, lidar_rows, pose_rows, proj_rows, label_center, label_heading,
                           synced_center, synced_heading,
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
    pixels, visible, facing = _carry_and_check(g, hits["object_index"], hits["point_box"], progress)
    hits["pixels"] = pixels
    hits["visible"] = visible
    if config.extended_truth:   # kept out of the default output, whose bytes stay the same
        hits["facing"] = facing
    world_from_box = np.stack([o.world_from_box(g.times) for o in world.objects])
    objects = dict(
        object_id=np.array([o.object_id for o in world.objects]),
        type=np.array([o.type for o in world.objects], np.int8), size=g.sizes,
        world_from_box=world_from_box, velocity_world=vel_world, labelled=g.labelled,
        timestamps_micros=g.timestamps, world_from_vehicle=g.world_from_vehicle,
        camera_names=np.array([c for c, _ in cams], np.int8))
    if config.extended_truth:   # kept out of the default output, whose bytes stay the same
        objects.update(
            role=np.array([o.role for o in world.objects]),
            label_time_offset_s=np.asarray(label_times - g.times[None, :], np.float64),
            camera_time_offset_s=np.array([g.camera_offsets[c] for c, _ in cams], np.float64),
            world_from_camera_vehicle=np.stack([g.camera_frames[c].world_from_vehicle for c, _ in cams]))
    sizes["objects.npz"] = gt.write_npz(f"{gt_url}/objects.npz", objects)
    sizes["lidar_hits.npz"] = gt.write_npz(f"{gt_url}/lidar_hits.npz", hits)
    return {"segment": seg, "files": files, "ground_truth": gt_url, "ground_truth_bytes": sizes,
            "num_frames": T, "num_objects": K, "num_object_returns": int(hits["frame"].size),
            "num_visible": int(visible.sum())}
