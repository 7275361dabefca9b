"""Returns per box: which LiDAR returns of a frame lie in each labelled box.

Two stages ask, with different tolerances, so there are two gathers over the same pieces:

- :func:`returns_in_boxes` (the track stage's per-box selection, ``tracks/plan.py``): the returns
  of the selected lasers / return indices inside each box grown by a margin and above a ground
  clearance, with the box moved to each return's capture time (``tracks/sweep_motion.py``). A box
  tests the slab of its frame's returns within its horizontal radius (a scan of the frame, or a
  search in the frame sorted by x once when it has many boxes), then the exact box test
  (:func:`inside_box`).
- :func:`gather_candidates` (the pose refinement's candidates, ``refine/scene.py``): the returns
  within each box's bounding *cube*, in (box, row) order; the refinement applies the exact test
  itself (its boxes are grown by ``candidate_margin_m``, with no ground clearance). Its fused twin
  is ``drivetrack.refine.kernel.gather`` (same result, tested equal).

Both filter returns with :func:`return_mask` and test body-frame points with :func:`inside_box`.
The two coarse passes are not interchangeable bit for bit (horizontal slab, half-open in x, vs
closed cube in x, y and z), so each stage keeps its own; only the exact test decides membership.
"""
from __future__ import annotations

import numpy as np

from drivetrack.geometry import invert_rigid, transform_points
from drivetrack.parallel import pool_map

__all__ = ["return_mask", "inside_box", "returns_in_boxes", "gather_candidates"]

SCAN_MAX_BOXES = 24
""":func:`returns_in_boxes` scans a frame's returns once per box when it has at most this many
boxes to fill, and sorts the frame by x for more (the slab is the same either way)."""


def return_mask(laser: np.ndarray, return_index: np.ndarray, lasers=None, returns=None) -> np.ndarray:
    """bool [M]: returns whose ``laser`` (int [M], ``LaserName`` values) is in ``lasers`` and whose
    ``return_index`` (int [M], 1 | 2) is in ``returns``; None accepts all."""
    selected = np.ones(np.shape(laser)[0], dtype=bool)
    for values, wanted in ((laser, lasers), (return_index, returns)):
        if wanted is None:
            continue
        values, wanted = np.asarray(values), np.asarray(wanted).reshape(-1)
        if values.dtype.itemsize == 1 and values.dtype.kind in "iu":   # the reader's int8: a 256-entry table
            info = np.iinfo(values.dtype)
            representable = wanted[(wanted >= info.min) & (wanted <= info.max)].astype(values.dtype)
            table = np.zeros(256, dtype=bool)
            table[representable.view(np.uint8)] = True
            selected &= table[values.view(np.uint8)]
        else:
            selected &= np.isin(values, wanted)
    return selected


def inside_box(points_box: np.ndarray, size: np.ndarray, margin: float, clearance: float | None = None) -> np.ndarray:
    """bool [N]: body-frame points float [N, 3] (metres) inside boxes of ``size`` ([N, 3] or [3])
    grown by ``margin`` on every face (shrunk when negative) and, with ``clearance``, at least
    ``clearance`` above the ungrown bottom (ground)."""
    inside = np.all(np.abs(points_box) <= size / 2.0 + margin, axis=-1)
    if clearance is not None:
        inside &= points_box[:, 2] >= -size[..., 2] / 2.0 + clearance
    return inside


def returns_in_boxes(scene, rows: np.ndarray, lasers, returns, margin: float, clearance: float,
                     compensate_sweep_motion: bool = True,
                     label_offset_s: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """LiDAR returns inside box rows ``rows`` (int [R]) of ``scene.boxes``, as CSR over all K rows.

    A return belongs to a box when it is of ``lasers`` / ``returns`` (:func:`return_mask`), lies
    inside the box grown by ``margin`` (metres, < 0 shrinks) and at least ``clearance`` above the
    box bottom (:func:`inside_box`). With ``compensate_sweep_motion`` and
    ``lidar.capture_offset_s``, the box is moved to each return's capture time first
    (:func:`drivetrack.tracks.sweep_motion.points_box_at_capture`), from the box's label time:
    ``label_offset_s`` float [K] (label time minus frame time, s; None: 0, boxes at the frame
    time; :func:`drivetrack.tracks.trajectory.scene_label_times`). Each box tests only the slab of
    its frame's returns whose x is within its horizontal radius: found by a scan of the frame for
    up to :data:`SCAN_MAX_BOXES` boxes in the frame, else in the frame's returns sorted by x once.

    Returns:
        ``(offsets int64 [K + 1], index int64 [P])``: rows of ``scene.lidar`` of box row k are
        ``index[offsets[k]:offsets[k + 1]]``, ascending (rows not in ``rows`` get no points).
    """
    from drivetrack.tracks.sweep_motion import points_box_at_capture, scene_box_motion

    lidar, boxes = scene.lidar, scene.boxes
    k = len(boxes)
    selected = return_mask(lidar.laser, lidar.return_index, lasers, returns)
    rows = np.unique(np.asarray(rows, dtype=np.int64))
    grow = max(margin, 0.0)
    offsets_s = lidar.capture_offset_s if compensate_sweep_motion else None
    if offsets_s is not None:   # boxes moved to each return's capture time (tracks/sweep_motion.py)
        velocity, yaw_rate = scene_box_motion(scene)

    def frame_members(t: int) -> list[tuple[int, np.ndarray]]:
        part = lidar.of_frame(int(t))
        frame_index = np.arange(part.start, part.stop)[selected[part]]
        if frame_index.size == 0:
            return []
        points = lidar.points_vehicle[frame_index]
        frame_rows = rows[boxes.frame[rows] == t]
        # a few boxes: one comparison pass over the frame each costs less than sorting it by x
        # (the same slab, half-open in x, so the same members)
        order = None if frame_rows.size <= SCAN_MAX_BOXES else np.argsort(points[:, 0])
        xs = points[:, 0] if order is None else points[order, 0]   # any order of ties: sorted below
        dt = None if offsets_s is None else offsets_s[frame_index]
        max_dt = 0.0 if dt is None else float(np.max(np.abs(dt)))
        members = []
        for row in frame_rows:
            center, size = boxes.center[row], boxes.size[row]
            # half the diagonal of the grown box (its corners; a tilted box reaches further)
            grown = size + 2.0 * grow
            radius = 0.5 * float(np.hypot(grown[0], grown[1]) if boxes.pitch is None and boxes.roll is None
                                 else np.linalg.norm(grown))
            if dt is not None:
                lag = 0.0 if label_offset_s is None else abs(float(label_offset_s[row]))
                radius += (max_dt + lag) * float(np.linalg.norm(velocity[row, :2]))   # rotation keeps distance
            if order is None:
                candidates = np.flatnonzero((xs >= center[0] - radius) & (xs < center[0] + radius))
            else:
                lo, hi = np.searchsorted(xs, [center[0] - radius, center[0] + radius], side="left")
                candidates = order[lo:hi]
            near = np.abs(points[candidates, 1] - center[1]) <= radius
            candidates = candidates[near]
            if dt is None:
                box_from_vehicle = invert_rigid(boxes.vehicle_from_box(row))
                local = transform_points(box_from_vehicle, points[candidates])
            else:
                row_dt = dt[candidates] if label_offset_s is None else dt[candidates] - label_offset_s[row]
                local = points_box_at_capture(points[candidates], row_dt, center, boxes.heading[row],
                                              velocity[row], yaw_rate[row], *boxes.tilt(row))
            inside = inside_box(local, size, margin, clearance)
            members.append((int(row), np.sort(frame_index[candidates[inside]])))
        return members

    # frames are independent: on the segment's pool when annotate installed one (drivetrack.parallel)
    per_row = {row: index for members in pool_map(frame_members, np.unique(boxes.frame[rows]).tolist())
               for row, index in members}
    counts = np.zeros(k, dtype=np.int64)
    for row, index in per_row.items():
        counts[row] = index.size
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    index = (np.concatenate([per_row[r] for r in sorted(per_row)]).astype(np.int64)
             if per_row else np.zeros(0, dtype=np.int64))
    return offsets, index


def gather_candidates(points: np.ndarray, laser: np.ndarray, return_index: np.ndarray, lasers, returns,
                      frame_offsets: np.ndarray, box_frame: np.ndarray, box_center: np.ndarray,
                      box_radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(index int64 [K], owner int64 [K]): the returns within each box's bounding cube.

    ``points`` float64 [M, 3] sorted by frame (``frame_offsets`` int64 [T + 1]: rows of frame t are
    ``[frame_offsets[t], frame_offsets[t+1])``), ``laser`` / ``return_index`` int [M]; only rows of
    ``lasers`` / ``returns`` (None: all, :func:`return_mask`) take part. Per box b (``box_frame``
    int [B], ``box_center`` float64 [B, 3], ``box_radius`` float64 [B], metres): the rows i of its
    frame with ``|points[i] - box_center[b]| <= box_radius[b]`` on every axis, in (box, row) order;
    ``owner`` is b. The selected returns are sorted once by (frame, vehicle x), so a box's
    candidates are a contiguous run (a searchsorted on x), then tested on y and z. The numba kernel
    ``drivetrack.refine.kernel.gather`` gives the same result."""
    frame = np.repeat(np.arange(frame_offsets.size - 1), np.diff(frame_offsets))
    chosen = np.flatnonzero(return_mask(laser, return_index, lasers, returns))
    x = points[chosen, 0]
    reach = float(np.abs(box_center[:, 0]).max(initial=0.0)) + float(box_radius.max(initial=0.0))
    span = 2.0 * (max(float(np.abs(x).max(initial=0.0)), reach) + 1.0)      # frames never overlap
    key = frame[chosen].astype(np.float64) * span + x                         # increasing in (frame, x)
    order = np.argsort(key, kind="stable")
    chosen, key = chosen[order], key[order]
    box_frame = np.asarray(box_frame, dtype=np.int64)
    # the runs are widened by a millimetre (the key's rounding), the exact test follows
    lo = np.searchsorted(key, box_frame * span + box_center[:, 0] - box_radius - 1e-3, side="left")
    hi = np.searchsorted(key, box_frame * span + box_center[:, 0] + box_radius + 1e-3, side="right")
    length = np.maximum(hi - lo, 0)
    owner = np.repeat(np.arange(box_frame.size), length)
    first = np.concatenate([[0], np.cumsum(length)[:-1]]).astype(np.int64)
    index = chosen[np.repeat(lo, length) + np.arange(owner.size) - first[owner]]
    near = np.all(np.abs(points[index] - box_center[owner]) <= box_radius[owner, None], axis=-1)
    index, owner = index[near], owner[near]
    order = np.lexsort((index, owner))
    return index[order].astype(np.int64), owner[order].astype(np.int64)
