"""Speed consistency of the tracks under the *labelled* box poses (paper Table 3, labels' side).

The track stage computes each track's speed with the poses it carries points with: the refined
poses when pose refinement (:mod:`drivetrack.refine`) ran, else the labels. To show what the
refinement did to the consistency check, this module recomputes the same statistic for the same
tracks with the labels' poses: a track's source return ``X`` (vehicle frame of its source frame
``s``) has box-frame point ``q = box_from_vehicle_label[s] X``; its labelled world path is
``world_from_vehicle[tau] vehicle_from_box_label[tau] q`` and its speed the path length over the
clip's duration. The error is ``|speed - annotated box speed|``, the box speed being the same
annotated ``speed`` field the track stage uses.

numpy, and the track stage's numba path-length kernel for the speeds
(:func:`drivetrack.tracks.kernel.path_speeds`); nothing here imports Prefect. Used by
:mod:`drivetrack.annotate` to fill the ``label_speed_err_p*`` columns of ``stats/objects.parquet``
(gate ``object.refine_speed_err_not_worse``).
"""
from __future__ import annotations

import numpy as np

from drivetrack.geometry import box_from_center_heading, invert_rigid
from drivetrack.tracks.kernel import NUMBA_AVAILABLE, path_speeds
from drivetrack.waymo.lidar import return_keys

__all__ = ["lidar_rows_from_sources", "label_speed_errors", "sorted_return_keys", "CHUNK_POINTS"]

#: Points carried at once (bounds the [T, chunk, 3] float64 temporaries: 48 MB at 200 frames).
CHUNK_POINTS = 32768


def sorted_return_keys(lidar, where: str = "") -> tuple[np.ndarray, np.ndarray]:
    """(order int64 [M], keys int64 [M] ascending): the return keys of ``lidar``
    (:func:`drivetrack.waymo.lidar.return_keys`) sorted, and the rows that give them. Build it once
    per segment and pass it to :func:`lidar_rows_from_sources` / :func:`label_speed_errors` for
    every clip: rebuilding it per clip was a fifth of a medium segment's annotation time. The
    reader returns them in key order already (``drivetrack.waymo.reader``): then no sort."""
    table = return_keys(lidar.frame, lidar.laser, lidar.return_index, lidar.row, lidar.col, where)
    if table.size < 2 or bool(np.all(table[1:] >= table[:-1])):
        return np.arange(table.size), table
    order = np.argsort(table, kind="stable")
    return order, table[order]


def lidar_rows_from_sources(lidar, frames: np.ndarray, lidar_sources: np.ndarray, where: str = "",
                            keys: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Row indices into ``lidar`` (:class:`drivetrack.scene.LidarReturns`) of tracks' source returns.

    Args:
        lidar: the segment's returns.
        frames: int [N], segment frame of each track's source return.
        lidar_sources: int [N, 4], (laser_name, return 1|2, range-image row, col).
        where: named in the error.
        keys: :func:`sorted_return_keys` of ``lidar`` (built here when None).

    Raises:
        ValueError naming ``where`` and the first source that is not a return of ``lidar``.
    """
    sources = np.asarray(lidar_sources, np.int64).reshape(-1, 4)
    frames = np.asarray(frames, np.int64).reshape(-1)
    if sources.shape[0] != frames.shape[0]:
        raise ValueError(f"{where}: {frames.shape[0]} source frames for {sources.shape[0]} lidar_sources")
    order, ordered = keys if keys is not None else sorted_return_keys(lidar, where)
    wanted = return_keys(frames, sources[:, 0], sources[:, 1], sources[:, 2], sources[:, 3], where)
    pos = np.minimum(np.searchsorted(ordered, wanted), max(ordered.size - 1, 0))
    found = ordered[pos] == wanted if ordered.size else np.zeros(wanted.size, bool)
    if not np.all(found):
        i = int(np.flatnonzero(~found)[0])
        raise ValueError(f"{where}: track {i} names a LiDAR return (frame {int(frames[i])}, laser "
                         f"{int(sources[i, 0])}, return {int(sources[i, 1])}, row {int(sources[i, 2])}, "
                         f"col {int(sources[i, 3])}) that the segment does not have")
    return order[pos] if ordered.size else np.zeros(0, np.int64)


def label_speed_errors(scene, labels, tracks, keys: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """float64 [N]: ``|track speed under the labelled poses - annotated box speed|`` per track.

    Args:
        scene: :class:`drivetrack.scene.Scene` the tracks come from (its LiDAR and vehicle poses;
            its boxes may be the refined ones: they are not used).
        labels: :class:`drivetrack.scene.Boxes`, the labelled boxes (before refinement).
        tracks: :class:`drivetrack.tracks.ObjectTracks` of one clip.
        keys: :func:`sorted_return_keys` of ``scene.lidar``, shared by the segment's clips.

    NaN for every track when a clip frame has no label for the object, when the clip has a
    single frame or zero duration, or when the object has no annotated speed.
    """
    n = int(tracks.num_tracks)
    where = f"segment {scene.segment!r} camera {tracks.camera_name} object {tracks.object_id!r}"
    out = np.full(n, np.nan)
    frames = np.asarray(tracks.frames, np.int64)
    t_count = frames.size
    duration_s = (float(tracks.timestamps_micros[-1]) - float(tracks.timestamps_micros[0])) * 1e-6 if t_count else 0.0
    if n == 0 or t_count < 2 or not duration_s > 0 or not np.isfinite(tracks.box_speed_mps):
        return out
    mine = np.flatnonzero(labels.object_id == tracks.object_id)
    row_of_frame = np.full(int(max(frames.max(), labels.frame[mine].max(initial=0))) + 1, -1, np.int64)
    row_of_frame[labels.frame[mine]] = mine
    rows = row_of_frame[frames]
    if np.any(rows < 0):
        return out
    vehicle_from_box = box_from_center_heading(labels.center[rows], labels.heading[rows])      # [T,4,4]
    world_from_box = scene.world_from_vehicle[frames] @ vehicle_from_box
    world_step = world_from_box[1:] - world_from_box[:-1]                                       # [T-1,4,4]
    box_from_vehicle = invert_rigid(vehicle_from_box)

    source_clip = np.asarray(tracks.query_frames, np.int64)
    lidar_rows = lidar_rows_from_sources(scene.lidar, frames[source_clip], tracks.lidar_sources, where, keys)
    x = scene.lidar.points_vehicle[lidar_rows]                                                  # [N,3]
    q = np.einsum("nij,nj->ni", box_from_vehicle[source_clip, :3, :3], x) + box_from_vehicle[source_clip, :3, 3]
    speeds = np.empty(n)
    if NUMBA_AVAILABLE:          # one pass, no [T, chunk, 3] temporaries (the track stage's own speed)
        path_speeds(np.ascontiguousarray(q), np.ascontiguousarray(world_step), duration_s, speeds)
    else:
        for start in range(0, n, CHUNK_POINTS):
            chunk = q[start:start + CHUNK_POINTS]
            steps = np.einsum("tij,nj->tni", world_step[:, :3, :3], chunk) + world_step[:, None, :3, 3]
            speeds[start:start + chunk.shape[0]] = np.linalg.norm(steps, axis=-1).sum(axis=0) / duration_s
    return np.abs(speeds - float(tracks.box_speed_mps))
