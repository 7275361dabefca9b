"""The Waymo v2 component tables of one generated segment (columns from the schema)."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from drivetrack.geometry import transform_points
from drivetrack.synth.boxes import _box_edge_samples, _box_matrix
from drivetrack.waymo.schema import COMPONENTS
from drivetrack.waymo.writer import list_array

if TYPE_CHECKING:
    from drivetrack.synth.state import _Generator


def _flat16(m: np.ndarray) -> np.ndarray:
    return np.asarray(m, np.float64).reshape(-1, 16)


def _build_tables(g: _Generator, jpegs, lidar_rows, pose_rows, proj_rows, label_center,
                  label_heading, synced_center, synced_heading, speed_v, accel_v, num_pts,
                  num_top) -> dict[str, dict]:
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
    # camera_image: exactly the values of g.camera_frames (the timing the images were rendered with)
    ci_ = C["camera_image"]
    cam_t = [(cam, t) for cam, _ in models for t in range(T)]
    frames = g.camera_frames
    tables["camera_image"] = {
        **key_cols(ci_, len(cam_t)), "key.frame_timestamp_micros": [int(ts[t]) for _, t in cam_t],
        "key.camera_name": [cam for cam, _ in cam_t],
        ci_.col("image"): [jpegs[cam][t] for cam, t in cam_t],
        ci_.col("pose.transform"): _flat16(np.stack([frames[cam].world_from_vehicle[t] for cam, t in cam_t])),
        **{ci_.col(f"velocity.linear_velocity.{a}"): [float(frames[cam].velocity[t, i]) for cam, t in cam_t]
           for i, a in enumerate("xyz")},
        **{ci_.col(f"velocity.angular_velocity.{a}"): [float(frames[cam].velocity[t, 3 + i]) for cam, t in cam_t]
           for i, a in enumerate("xyz")},
        ci_.col("pose_timestamp"): [float(frames[cam].pose_timestamp[t]) for cam, t in cam_t],
        ci_.col("rolling_shutter_params.shutter"): [float(frames[cam].shutter[t]) for cam, t in cam_t],
        ci_.col("rolling_shutter_params.camera_trigger_time"):
            [float(frames[cam].trigger_time[t]) for cam, t in cam_t],
        ci_.col("rolling_shutter_params.camera_readout_done_time"):
            [float(frames[cam].readout_done_time[t]) for cam, t in cam_t]}
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
    # lidar_box: boxes drawn box_slack_m wider than their objects on every side (0: their extent)
    label_sizes = g.sizes + 2.0 * float(g.config.box_slack_m)
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
        **{lb.col(f"box.size.{a}"): label_sizes[ks, i] for i, a in enumerate("xyz")},
        lb.col("box.heading"): label_heading[ks, tt],
        lb.col("type"): np.array([world.objects[k].type for k in ks], np.int8),
        lb.col("num_lidar_points_in_box"): npts, lb.col("num_top_lidar_points_in_box"): num_top[ks, tt],
        **{lb.col(f"speed.{a}"): speed_v[ks, tt, i] for i, a in enumerate("xyz")},
        **{lb.col(f"acceleration.{a}"): accel_v[ks, tt, i] for i, a in enumerate("xyz")},
        lb.col("difficulty_level.detection"): difficulty, lb.col("difficulty_level.tracking"): difficulty}
    # lidar_camera_synced_box: the label box, moved to the most visible camera's pose time when
    # the cameras fire with the sweep (synced_center / synced_heading, see generate_segment)
    sb = C["lidar_camera_synced_box"]
    most = g.visible_pixels.argmax(axis=0)                                          # [T,K]
    most_any = g.visible_pixels.max(axis=0) > 0
    cam_values = np.array([c for c, _ in models], np.int8)
    tables["lidar_camera_synced_box"] = {
        **key_cols(sb, len(kt)), "key.frame_timestamp_micros": ts[tt] if kt else [],
        "key.laser_object_id": [world.objects[k].object_id for k in ks],
        sb.col("most_visible_camera_name"): np.where(most_any[tt, ks], cam_values[most[tt, ks]], 0).astype(np.int8),
        **{sb.col(f"camera_synced_box.center.{a}"): synced_center[ks, tt, i] for i, a in enumerate("xyz")},
        **{sb.col(f"camera_synced_box.size.{a}"): label_sizes[ks, i] for i, a in enumerate("xyz")},
        sb.col("camera_synced_box.heading"): synced_heading[ks, tt]}
    # projected_lidar_box: the written (possibly noisy) label box projected into each camera
    pb_rows = []
    for ci, (cam, model) in enumerate(models):
        for k, t in kt:
            box = _box_matrix(label_center[k, t], label_heading[k, t])
            samples_v = transform_points(box, _box_edge_samples(label_sizes[k]))
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
