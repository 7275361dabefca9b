"""The extent term: where an object's side returns end, frame by frame.

A box-like car seen side-on shows the lidar one flat face: point-to-plane registration pins it
across the road and in height, but nothing in a plane says where the car is *along* it. The
face's returns still end where the car ends. In each frame, the first and last returns along the
body's x axis on the visible side are the car's two ends as that frame sees them (inside by at
most a beam spacing, about a centimetre at 4-6 m); the median over the frames is the car's
extent in the common body frame; a frame whose ends sit ``s`` further forward than the median
is off by ``s`` along its heading. That is a measurement along the road in every frame that sees
the side, where the labels give only their noise (docs/refinement.md, "Extent").

A frame is used only when its two ends agree: its measured length within
:data:`EXTENT_LENGTH_TOLERANCE_M` of the median length (an end cut short by an occluder, or
returns of something else past an end, change the length and drop the frame).
"""
from __future__ import annotations

import numpy as np

from drivetrack.refine.select import _body_points, _inside

#: side-face band: returns within this of the visible side's plane (body y = +-half width)
EXTENT_BAND_M = 0.1
#: the last few returns at each end are passed over (stray returns)
EXTENT_SKIP = 2
#: a frame needs this many side-face returns
EXTENT_MIN_POINTS = 30
#: a frame's length (last minus first return along x) within this of the median length
EXTENT_LENGTH_TOLERANCE_M = 0.03
#: at least this many frames must agree for the term to apply
EXTENT_MIN_FRAMES = 3
#: :func:`end_candidates` keeps returns within this (plus its margin) of either end
END_WINDOW_M = 0.5


def end_candidates(points: np.ndarray, frame: np.ndarray, center: np.ndarray, heading: np.ndarray,
                   tilt: np.ndarray | None, half: np.ndarray, margin_m: float) -> np.ndarray:
    """int64 [P]: the rows of ``points`` (float [M, 3], vehicle frame of each row's ``frame``)
    that may be a side's first or last return: within ``margin_m`` plus the band of either side
    plane and within ``margin_m`` plus :data:`END_WINDOW_M` of either end, at the poses (``center`` [T, 3],
    ``heading`` [T], ``tilt`` [T, 2] or None, ``half`` [T, 3] half sizes) given. Computed once
    per object at its labels, so each iteration looks at a small subset."""
    body = _body_points(center, heading, points, frame, tilt)
    h = half[frame]
    side = np.abs(np.abs(body[:, 1]) - h[:, 1]) <= EXTENT_BAND_M + margin_m
    ends = np.abs(body[:, 0]) >= h[:, 0] - END_WINDOW_M - margin_m
    return np.flatnonzero(side & ends).astype(np.int64)


def extent_shifts(points: np.ndarray, frame: np.ndarray, center: np.ndarray, heading: np.ndarray,
                  tilt: np.ndarray | None, half: np.ndarray, t_count: int, inlier_margin_m: float,
                  clearance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """``(shift float64 [T] m, used bool [T])``: how far each frame's body-frame ends lie ahead of
    the frames' median ends (along the body x axis), at the poses given.

    Args:
        points: float [M, 3], vehicle frame of each row's frame (the candidates of
            :func:`end_candidates`, or all of them).
        frame: int [M] in [0, T).
        center, heading, tilt, half: the current poses, [T, 3] / [T] / [T, 2] or None / [T, 3].
        inlier_margin_m: returns further than this outside the box are not the object's.
        clearance_m: returns lower than this over the box bottom are the road's.
    Returns: shift 0 where ``used`` is False. Moving frame t's box forward by ``shift[t]`` along
    its heading puts its ends on the median ends.
    """
    shift = np.zeros(t_count)
    used = np.zeros(t_count, dtype=bool)
    if points.shape[0] == 0:
        return shift, used
    body = _body_points(center, heading, points, frame, tilt)
    h = half[frame]
    band = _inside(body, h, inlier_margin_m, clearance_m) & (np.abs(np.abs(body[:, 1]) - h[:, 1]) <= EXTENT_BAND_M)
    # the visible side: the one with more returns in its band, frame by frame
    left = np.bincount(frame[band & (body[:, 1] > 0)], minlength=t_count)
    right = np.bincount(frame[band & (body[:, 1] < 0)], minlength=t_count)
    visible = np.where(left >= right, 1.0, -1.0)
    keep = band & (np.sign(body[:, 1]) == visible[frame])
    f, x = frame[keep], body[keep, 0]
    order = np.lexsort((x, f))
    f, x = f[order], x[order]
    count = np.bincount(f, minlength=t_count)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    ok = count >= max(EXTENT_MIN_POINTS, 2 * EXTENT_SKIP + 2)
    if ok.sum() < EXTENT_MIN_FRAMES:
        return shift, used
    lo = np.full(t_count, np.nan)
    hi = np.full(t_count, np.nan)
    first, last = start[ok] + EXTENT_SKIP, start[ok] + count[ok] - 1 - EXTENT_SKIP
    lo[ok], hi[ok] = x[first], x[last]
    length = hi - lo
    agree = ok & (np.abs(length - np.median(length[ok])) <= EXTENT_LENGTH_TOLERANCE_M)
    if agree.sum() < EXTENT_MIN_FRAMES:
        return shift, used
    shift[agree] = 0.5 * ((lo[agree] - np.median(lo[agree])) + (hi[agree] - np.median(hi[agree])))
    return shift, agree
