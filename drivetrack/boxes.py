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

Two rules keep returns that are not the object's out of the refinement's candidates (labels drawn
loosely reach below the ground and round their neighbours):

- :func:`ground_under_boxes`: the height of the ground under each box, measured from the returns
  in a ring round its footprint, so that returns near it are left out even when the box's bottom
  lies below the ground;
- :func:`claimed_by_other_boxes`: a return that another object's box of the same frame holds more
  deeply than its own box is that object's.

Both filter returns with :func:`return_mask` and test body-frame points with :func:`inside_box`.
The two coarse passes are not interchangeable bit for bit (horizontal slab, half-open in x, vs
closed cube in x, y and z), so each stage keeps its own; only the exact test decides membership.
"""
from __future__ import annotations

import numpy as np

from drivetrack.geometry import invert_rigid, transform_points, vectors_to_box
from drivetrack.parallel import pool_map

__all__ = ["return_mask", "inside_box", "returns_in_boxes", "gather_candidates", "ground_reach", "ground_under_boxes",
           "fill_ground_over_time", "claimed_by_other_boxes", "box_depth"]

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


#: :func:`ground_under_boxes`: the ring round a box's footprint whose returns measure the ground:
#: from this far outside its side faces to this far (metres). Its inner edge keeps the object's
#: own returns out (they lie inside the box or within a label's slack of it).
GROUND_RING_M = (0.3, 1.5)
#: ... the returns of the ring within this of the box's bottom (metres, body z) ...
GROUND_WINDOW_M = 0.5
#: ... at least this many (fewer: the ground is unknown, NaN) ...
GROUND_MIN_RETURNS = 5
#: ... and this quantile of their heights: the ground is the lowest large surface round an object;
#: the lower parts of neighbours (a parked car's sill, legs) in the ring lie above it.
GROUND_QUANTILE = 0.25


def box_depth(points_box: np.ndarray, half: np.ndarray) -> np.ndarray:
    """float64 [N]: how deep body-frame points float [N, 3] lie inside boxes of half-size ``half``
    ([N, 3] or [3], metres): the distance to the nearest face, negative outside (then the largest
    excess over the faces, not the Euclidean distance)."""
    return np.min(half - np.abs(points_box), axis=-1)


def ground_reach(size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(half float64 [B, 3], radius float64 [B])``: boxes of ``size`` [B, 3]'s half sizes and the
    half side of the cube round each centre that holds its ground ring (:data:`GROUND_RING_M`,
    :data:`GROUND_WINDOW_M`) whole: the candidates :func:`ground_under_boxes` reads."""
    half = 0.5 * np.asarray(size, np.float64)
    outer = GROUND_RING_M[1]
    return half, np.maximum(np.hypot(half[:, 0] + outer, half[:, 1] + outer), half[:, 2] + GROUND_WINDOW_M)


def ground_under_boxes(points: np.ndarray, laser: np.ndarray, return_index: np.ndarray, frame_offsets: np.ndarray,
                       box_frame: np.ndarray, center: np.ndarray, heading: np.ndarray, size: np.ndarray,
                       lasers=None, returns=None, gather=gather_candidates) -> np.ndarray:
    """float64 [B]: the ground's height under each box, as body-frame z (metres; the box's bottom
    is ``-size[:, 2] / 2``), NaN where it cannot be measured.

    The ground is measured from box b's frame's returns (``points`` float64 [M, 3] vehicle frame,
    sorted by frame, ``frame_offsets`` int64 [T + 1]; ``laser`` / ``return_index`` with ``lasers`` /
    ``returns`` as in :func:`return_mask`) in a ring round its footprint (:data:`GROUND_RING_M`
    outside its side faces) within :data:`GROUND_WINDOW_M` of its bottom: the
    :data:`GROUND_QUANTILE` quantile of their heights when there are at least
    :data:`GROUND_MIN_RETURNS`. Boxes: ``box_frame`` int [B], ``center`` float [B, 3], ``heading``
    float [B] rad, ``size`` float [B, 3] (yaw-only: the labels). ``gather``:
    :func:`gather_candidates` or its fused twin ``drivetrack.refine.kernel.gather``.

    Why: a label drawn a little wider than its object reaches below the road, and its lowest
    returns are the road's; the ground clearance of the stages is kept above the ground measured
    here as well as above the box's bottom."""
    count = np.shape(box_frame)[0]
    out = np.full(count, np.nan)
    if count == 0:
        return out
    inner, outer = GROUND_RING_M
    half, radius = ground_reach(size)
    index, owner = gather(points, laser, return_index, lasers, returns, frame_offsets,
                          np.asarray(box_frame, np.int64), np.asarray(center, np.float64), radius)
    q = vectors_to_box(points[index] - center[owner], np.asarray(heading, np.float64), rows=owner)
    h = half[owner]
    ring = (np.all(np.abs(q[:, :2]) <= h[:, :2] + outer, axis=-1)
            & ~np.all(np.abs(q[:, :2]) <= h[:, :2] + inner, axis=-1)
            & (np.abs(q[:, 2] + h[:, 2]) <= GROUND_WINDOW_M))
    owner, z = owner[ring], q[ring, 2]
    order = np.lexsort((z, owner))
    owner, z = owner[order], z[order]
    counts = np.bincount(owner, minlength=count)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    known = counts >= GROUND_MIN_RETURNS
    out[known] = z[start[known] + np.floor(GROUND_QUANTILE * (counts[known] - 1)).astype(np.int64)]
    return out


def fill_ground_over_time(ground: np.ndarray, box_frame: np.ndarray, box_object: np.ndarray, center: np.ndarray,
                          world_from_vehicle: np.ndarray) -> np.ndarray:
    """float64 [B]: ``ground`` (:func:`ground_under_boxes`, body-frame z, NaN where unmeasured)
    with each object's unmeasured boxes given the ground's world height under their centre
    interpolated over its measured boxes (linearly in frame index, held beyond the ends).

    Boxes: ``box_frame`` int [B], ``box_object`` [B] ids, ``center`` float [B, 3] vehicle frame of
    the box's frame (yaw-only: body z is vehicle z); ``world_from_vehicle`` float [T, 4, 4]. An
    object with no measured box stays NaN. Why: the ring round a box can be empty in a frame (a
    neighbour or the sweep's gap hides the road) while the label's depth under the road is the
    same as in the frames round it, up to its noise."""
    ground = np.array(ground, dtype=np.float64)
    box_frame = np.asarray(box_frame, np.int64)
    pose = np.asarray(world_from_vehicle, np.float64)[box_frame]                   # [B, 4, 4]
    base = np.einsum("bj,bj->b", pose[:, 2, :3], center) + pose[:, 2, 3]           # world z of the centre
    up = pose[:, 2, 2]                                                              # world z per body z
    world = base + up * ground
    box_object = np.asarray(box_object)
    for oid in np.unique(box_object[~np.isfinite(ground)]):
        rows = np.flatnonzero(box_object == oid)
        known = np.isfinite(ground[rows])
        if not known.any():
            continue
        order = np.argsort(box_frame[rows[known]], kind="stable")
        filled = np.interp(box_frame[rows[~known]], box_frame[rows[known]][order], world[rows[known]][order])
        ground[rows[~known]] = (filled - base[rows[~known]]) / up[rows[~known]]
    return ground


def claimed_by_other_boxes(points: np.ndarray, owner: np.ndarray, box_frame: np.ndarray, box_object: np.ndarray,
                           center: np.ndarray, heading: np.ndarray, size: np.ndarray,
                           tolerance_m: float = 0.02) -> np.ndarray:
    """bool [N]: points another object's box holds more deeply than their own box does.

    Point n (``points`` float [N, 3], vehicle frame of its box's frame) belongs to box row
    ``owner[n]`` of the box arrays (``box_frame`` int [B], ``box_object`` [B] any comparable ids,
    ``center`` [B, 3], ``heading`` [B] rad, ``size`` [B, 3] m: yaw-only). It is claimed when a box
    of the same frame and another object holds it at a depth (:func:`box_depth`) above
    ``-tolerance_m`` (a return exactly on a label's face counts as inside) and above its depth in
    its own box. Only box pairs whose footprints' circles overlap the points' reach are tested.

    Why: labels drawn loosely, and the margins the stages grow them by, overlap where objects stand
    close (a pedestrian beside a car, cars queueing): the neighbour's returns, which do not move
    with the object, would be registered and tracked as its own."""
    points = np.asarray(points, np.float64)
    owner = np.asarray(owner, np.int64)
    claimed = np.zeros(owner.size, dtype=bool)
    if owner.size == 0:
        return claimed
    box_frame = np.asarray(box_frame, np.int64)
    box_object = np.asarray(box_object)
    half = 0.5 * np.asarray(size, np.float64)
    own_depth = box_depth(vectors_to_box(points - center[owner], np.asarray(heading, np.float64), rows=owner),
                          half[owner])
    # each owner row's reach (its points' farthest horizontal distance from its centre) against
    # every box of its frame and another object
    rows = np.unique(owner)
    reach = np.zeros(box_frame.size)
    np.maximum.at(reach, owner, np.hypot(*(points[:, :2] - center[owner, :2]).T))
    other_radius = np.hypot(half[:, 0], half[:, 1])
    pair_a, pair_b = [], []
    for t in np.unique(box_frame[rows]):
        a = rows[box_frame[rows] == t]
        b = np.flatnonzero(box_frame == t)
        gap = np.hypot(*(center[a, None, :2] - center[None, b, :2]).transpose(2, 0, 1))
        near = (gap <= reach[a, None] + other_radius[None, b]) & (box_object[a, None] != box_object[None, b])
        ia, ib = np.nonzero(near)
        pair_a.append(a[ia])
        pair_b.append(b[ib])
    if not pair_a:
        return claimed
    pair_a, pair_b = np.concatenate(pair_a), np.concatenate(pair_b)
    if pair_a.size == 0:
        return claimed
    # the points of each pair's owner row: owner need not be sorted
    order = np.argsort(owner, kind="stable")
    counts = np.bincount(owner, minlength=box_frame.size)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    length = counts[pair_a]
    which = np.repeat(np.arange(pair_a.size), length)
    offset = np.arange(which.size) - np.repeat(np.cumsum(length) - length, length)
    point = order[starts[pair_a][which] + offset]
    other = pair_b[which]
    depth = box_depth(vectors_to_box(points[point] - center[other], np.asarray(heading, np.float64), rows=other),
                      half[other])
    hit = (depth > -tolerance_m) & (depth > own_depth[point])
    claimed[point[hit]] = True
    return claimed
