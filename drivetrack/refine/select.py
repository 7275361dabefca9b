"""Which returns take part in an iteration: inside the current box, capped per frame."""
from __future__ import annotations

import numpy as np

from drivetrack.geometry import vectors_to_box


def _body_points(center: np.ndarray, heading: np.ndarray, points: np.ndarray, frame: np.ndarray,
                 tilt: np.ndarray | None = None) -> np.ndarray:
    """float64 [M, 3]: ``box_from_vehicle(s_frame) x`` for points x [M, 3] of frames ``frame``
    (tilt [T, 2] = per-frame (pitch, roll), None: yaw-only boxes)."""
    if tilt is None:
        return vectors_to_box(points - center[frame], heading, rows=frame)
    return vectors_to_box(points - center[frame], heading, tilt[:, 0], tilt[:, 1], rows=frame)


def _inside(q: np.ndarray, half: np.ndarray, margin: float, clearance: float) -> np.ndarray:
    """bool [M]: body points q [M, 3] inside boxes of half-size half [M, 3] grown by ``margin``,
    at least ``clearance`` above the (ungrown) bottom."""
    inside = np.all(np.abs(q[:, :2]) <= half[:, :2] + margin, axis=-1)
    return inside & (q[:, 2] <= half[:, 2] + margin) & (q[:, 2] >= -half[:, 2] + clearance)


def point_priority(points: np.ndarray) -> np.ndarray:
    """float64 [M] in [0, 1): each point's fixed priority for the per-frame cap, a hash of its
    coordinates ``points`` float [M, 3] (so that a selection does not depend on the rows' order)."""
    return np.modf(np.abs(np.asarray(points) @ np.array([12.9898, 78.233, 37.719])) * 43758.5453)[0]


def _runs(frame: np.ndarray) -> list[tuple[int, int]]:
    """[(start, stop)]: the runs of equal values of ``frame`` int [M] (non-decreasing: one per frame)."""
    cuts = np.flatnonzero(frame[1:] != frame[:-1]) + 1
    return list(zip(np.concatenate([[0], cuts]).tolist(), np.append(cuts, frame.size).tolist()))


def first_per_frame(frame: np.ndarray, priority: np.ndarray, cap: int) -> np.ndarray:
    """int64 [k], ascending: the rows of the ``cap`` lowest ``priority`` float [M] of each frame
    ``frame`` int [M] (all of a frame that has fewer; among equal priorities the earlier rows).

    When ``frame`` is non-decreasing (the callers' order) each frame's run is partitioned on its
    own (``np.argpartition``: linear, ~50x faster than the sort on a near object's ~10^5 rows);
    a run whose cut falls among equal priorities is sorted instead, so the rows are the same."""
    frame, priority = np.asarray(frame), np.asarray(priority)
    n = frame.size
    if n == 0 or cap <= 0:
        return np.zeros(0, np.int64)
    if n > 1 and not np.all(frame[1:] >= frame[:-1]):
        order = np.lexsort((priority, frame))
        sorted_frame = frame[order]
        starts = np.searchsorted(sorted_frame, sorted_frame, side="left")
        return np.sort(order[np.arange(order.size) - starts < cap])
    parts = []
    for a, b in _runs(frame):
        if b - a <= cap:
            parts.append(np.arange(a, b, dtype=np.int64))
            continue
        run = priority[a:b]
        kept = np.argpartition(run, cap)[:cap + 1]       # the cap lowest, then the next one
        inner = kept[:cap]
        if run[inner].max() >= run[kept[cap]]:              # a tie at the cut: the stable sort decides
            inner = np.argsort(run, kind="stable")[:cap]
        parts.append(a + np.sort(inner).astype(np.int64))
    return np.concatenate(parts)


def _frame_priority_order(frame: np.ndarray, priority: np.ndarray) -> np.ndarray:
    """int64 [M]: ``np.lexsort((priority, frame))`` (by frame, then priority, ties by index); when
    ``frame`` is already non-decreasing (the caller's order), each frame's run is sorted on its own,
    the same permutation at about half the cost on a near object's ~10^5 candidates."""
    n = frame.size
    if n > 1 and np.all(frame[1:] >= frame[:-1]):
        return np.concatenate([a + _argsort_ties_by_index(priority[a:b]) for a, b in _runs(frame)])
    return np.lexsort((priority, frame))


def _argsort_ties_by_index(values: np.ndarray) -> np.ndarray:
    """``np.argsort(values, kind="stable")``: numpy's default sort (about twice as fast on 10^5
    floats) when it leaves no two equal values, the stable one otherwise (ties keep index order)."""
    order = np.argsort(values)
    ordered = values[order]
    if ordered.size > 1 and not np.all(ordered[1:] > ordered[:-1]):
        return np.argsort(values, kind="stable")
    return order


def spread_priority(points: np.ndarray, frame: np.ndarray, priority: np.ndarray, voxel_m: float) -> np.ndarray:
    """float64 [M]: per-frame priorities of ``points`` float [M, 3] (metres, frames ``frame`` int
    [M]) that spread the per-frame cap evenly over the object's surface: each return's rank among
    the returns of its frame in its cube of side ``voxel_m`` (ordered by ``priority`` float [M] in
    [0, 1), a fixed pseudo-random hash), plus that hash. A cap of k then takes one return from
    each of k cubes before a second from any.

    Uniform sampling takes each part of the surface in proportion to its returns: a car seen
    side-on from a few metres has tens of thousands of returns on its side and a few hundred on
    its front or rear face seen at a grazing angle, so a random 120 of them hold one or two on
    the only faces that fix its position along the road (Rusinkiewicz & Levoy's normal-space
    sampling is the same idea in the normals' space; cubes need no normals yet)."""
    if points.shape[0] == 0:
        return priority.astype(np.float64)
    cell = np.floor(points / voxel_m).astype(np.int64)
    cell -= cell.min(axis=0)
    span = cell.max(axis=0) + 1
    key = (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]
    return _rank_priority(key, frame, priority)


def normal_priority(points: np.ndarray, frame: np.ndarray, priority: np.ndarray, heading: np.ndarray,
                    screen: int, neighbours: int = 12, use_kernel: bool = False) -> np.ndarray:
    """float64 [M]: per-frame priorities that share the cap among the directions the returns'
    surfaces face: normal-space sampling (Rusinkiewicz & Levoy 2001).

    The ``screen`` returns of lowest ``priority`` (float [M] in [0, 1)) of each frame (``frame``
    int [M]) get a PCA normal from their ``neighbours`` nearest returns of the same frame
    (``points`` float [M, 3], metres, vehicle frame); each is keyed by the axis of its frame's
    label box (``heading`` float [T], radians) its normal lies closest to: along the object,
    across it, or up. Its new priority is its rank among its frame's screened returns of the same
    key, plus its hash; the unscreened returns follow all of them (hash + 10^6). A cap of k
    then takes about k/3 from each direction that has them: a car seen side-on from a few metres
    gives its front or rear face, seen at a grazing angle and holding a few hundred of its tens
    of thousands of returns, as large a share as its side, and those are the only returns that
    fix its position along the road. Frames with fewer than ``neighbours`` screened returns
    keep uniform ranks (key 0). ``use_kernel``: the neighbours and normals by the numba kernels
    (:mod:`drivetrack.refine.kernel`), frame by frame; the same up to ties and rounding."""
    out = priority.astype(np.float64) + 1e6
    rows = first_per_frame(frame, priority, screen)
    if rows.size == 0:
        return out
    f = frame[rows]
    counts = np.bincount(f)
    key = np.zeros(rows.size, dtype=np.int64)
    enough = counts[f] >= neighbours
    if enough.any():
        r = rows[enough]
        key[enough] = np.argmax(np.abs(vectors_to_box(_frame_normals(points[r], frame[r], neighbours, use_kernel),
                                                      heading, rows=frame[r])), axis=1)
    out[rows] = _rank_priority(key, f, priority[rows])
    return out


def _frame_normals(points: np.ndarray, frame: np.ndarray, neighbours: int, use_kernel: bool) -> np.ndarray:
    """float64 [P, 3]: unit PCA normals of ``points`` float [P, 3] from their ``neighbours``
    nearest of the same frame (``frame`` int [P]; each frame at least ``neighbours`` rows)."""
    from drivetrack.refine.terms import _normals          # (terms imports this module)

    if not use_kernel:
        from scipy.spatial import cKDTree

        # one tree over every frame's returns, frames kept apart by 10 km along x; the normals
        # from the un-offset coordinates (the offset would cost their precision)
        q = points + (frame * 1e4)[:, None] * np.array([1.0, 0.0, 0.0])
        _, nbr = cKDTree(q).query(q, k=neighbours)
        return _normals(points, nbr)[0]
    from drivetrack.refine import kernel

    order = np.argsort(frame, kind="stable")
    ordered, f = points[order], frame[order]
    nbr = np.empty((points.shape[0], neighbours), np.int64)
    for a, b in _runs(f):
        nbr[a:b] = kernel.knn(ordered[a:b], neighbours)[1] + a
    out = np.empty_like(ordered)
    out[order] = kernel.normals(ordered, nbr)[0]
    return out


def _rank_priority(key: np.ndarray, frame: np.ndarray, priority: np.ndarray) -> np.ndarray:
    """float64 [M]: each point's rank among the points of its frame ``frame`` int [M] with its
    ``key`` int [M] (ordered by ``priority`` float [M] in [0, 1)), plus that priority."""
    order = np.lexsort((priority, key, frame))
    run_key = np.stack([frame[order], key[order]], axis=-1)
    new_run = np.concatenate([[True], np.any(run_key[1:] != run_key[:-1], axis=-1)])
    starts = np.flatnonzero(new_run)
    rank = np.arange(order.size) - np.repeat(starts, np.diff(np.append(starts, order.size)))
    out = np.empty(key.shape[0], dtype=np.float64)
    out[order] = rank + priority[order]
    return out


class _Selection:
    """The returns that may take part, ordered by (frame, priority), with per-frame ranks.

    The per-frame cap keeps the ``cap`` returns of lowest priority that are inside the current
    box. Points are held sorted by (frame, priority), so that subset always lies among the first
    few of its frame that are inside: each iteration tests only the first ``screen`` (a small
    multiple of the cap) of every frame and widens to the whole frame only where those hold
    fewer than ``cap`` inside. The result is exactly the cap over all points, at a cost bounded
    by ``screen x T`` instead of the candidate count (tens of thousands on near objects).
    """

    def __init__(self, points: np.ndarray, frame: np.ndarray, priority: np.ndarray, half: np.ndarray,
                 cap: int, t_count: int, kernel: bool = False):
        order = _frame_priority_order(frame, priority)
        self.points, self.frame = points[order], frame[order]
        self.half_frame = np.ascontiguousarray(half, dtype=np.float64)        # [T, 3]
        self.cap, self.t_count, self.kernel = cap, t_count, kernel
        counts = np.bincount(self.frame, minlength=t_count)
        self.counts = counts.astype(np.int64)
        self.start = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        self.screen = 3 * cap
        if not kernel:                                  # the numpy path's per-point screen
            self.half = half[self.frame]
            self.rank = np.arange(self.frame.size) - self.start[self.frame]
            self.screened = np.flatnonzero(self.rank < self.screen)
            self.frame_full = counts > self.screen      # frames with returns beyond the screen

    def select(self, center: np.ndarray, heading: np.ndarray, margin: float, clearance: float,
               tilt: np.ndarray | None = None):
        """(body points float64 [P, 3], frames int64 [P], rows int64 [P] into ``self.points``) of
        the capped returns inside the boxes (center [T, 3], heading [T], tilt [T, 2] or None)
        grown by ``margin``, in (frame, priority) order. With ``kernel``: one pass per frame in
        priority order that stops at the cap (``drivetrack.refine.kernel.select``), the same subset."""
        if self.kernel:
            from drivetrack.refine import kernel

            return kernel.select(self.points, self.start, self.counts, self.half_frame, self.cap,
                                 center, heading, tilt, margin, clearance)
        idx = self.screened
        f = self.frame[idx]
        q = _body_points(center, heading, self.points[idx], f, tilt)
        inside = _inside(q, self.half[idx], margin, clearance)
        short = self.frame_full & (np.bincount(f[inside], minlength=self.t_count) < self.cap)
        if short.any():                                 # widen to whole frames where needed
            more = np.flatnonzero(short[self.frame] & (self.rank >= self.screen))
            q_more = _body_points(center, heading, self.points[more], self.frame[more], tilt)
            in_more = _inside(q_more, self.half[more], margin, clearance)
            idx = np.concatenate([idx[inside], more[in_more]])
            q = np.concatenate([q[inside], q_more[in_more]])
            order = np.argsort(idx, kind="stable")
            idx, q = idx[order], q[order]
        else:
            idx, q = idx[inside], q[inside]
        f = self.frame[idx]
        counts = np.bincount(f, minlength=self.t_count)
        start = np.concatenate([[0], np.cumsum(counts)[:-1]])
        keep = (np.arange(idx.size) - start[f]) < self.cap
        return q[keep], f[keep], idx[keep]
