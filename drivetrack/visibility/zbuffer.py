"""Z-buffer of the other labelled objects' own surfaces (issue 15).

The depth-ratio test (``d_map < occlusion_ratio * z``) cannot see an occluder less than
``1 - occlusion_ratio`` of the distance in front of a point (at 50 m and 0.95: 2.5 m, a car behind
a car), and the completed LiDAR map bleeds across object outlines. Every labelled object's own
returns, in its box frame and carried by its pose at the image's capture time
(:func:`drivetrack.tracks.core.clip_poses`, the poses the tracks use), give its surface in each
image: each return is splatted as a square footprint of ``radius_m`` at its depth (``f * radius_m /
z`` pixels, at most ``max_px``) into a per-pixel nearest-depth buffer. A point of the tracked object
is hidden by another object when that buffer at its pixel is nearer than its own depth by more than
``abs_m + rel * z``. The tracked object's own surface is splatted into a buffer of its own and
hides a point in a pocket of its hull (:func:`pocket_points`) beyond that tolerance plus the depth
the point's own plane spans over a footprint (:func:`own_plane_slack`): a cabin before its deck.
The other objects' surfaces also hold the parts of their roofs the lidar did not sample
(:func:`roof_fill`).

Shapes: T frames, n tracked points, m occluder returns; metres, camera frame (x forward = depth).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["OccluderHull", "box_points_at", "close_holes", "first_of_cells", "hidden_by_others", "hull_hidden", "occluder_hull", "nearest_depth", "occluder_buffer", "own_plane_slack", "pocket_points", "roof_fill",
           "surfel_cells", "surfel_first_and_means", "surfel_means", "surfel_subsample"]


def surfel_cells(points_box: np.ndarray, radius_m: float) -> np.ndarray:
    """int64 [m]: the cube of side ``radius_m`` each of ``points_box`` float64 [m, 3] lies in (a key)."""
    if points_box.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    cell = np.floor(points_box / radius_m).astype(np.int64)
    cell -= cell.min(axis=0)
    span = cell.max(axis=0) + 1
    return (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]


def first_of_cells(sorted_cells: np.ndarray) -> np.ndarray:
    """int64 [k]: the first index of each run of equal keys in ``sorted_cells`` int64 [m] (sorted)."""
    if sorted_cells.size == 0:
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero(np.concatenate([[True], sorted_cells[1:] != sorted_cells[:-1]]))


def _cube_runs(points_box: np.ndarray, radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """``(order int64 [m], starts int64 [k])``: ``points_box`` float64 [m, 3] (m > 0) sorted by
    the cube of side ``radius_m`` each lies in (stable), and where each cube's run starts."""
    cells = surfel_cells(points_box, radius_m)
    order = np.argsort(cells, kind="stable")
    return order, first_of_cells(cells[order])


def surfel_subsample(points_box: np.ndarray, radius_m: float) -> np.ndarray:
    """int64 [k] sorted indices of ``points_box`` float64 [m, 3] keeping one point per cube of side ``radius_m``.

    An occluder's returns accumulated over a clip are far denser than its splat footprint (a
    return covers ``radius_m`` either side of its own position): one return per cube covers the
    same surface without gaps, and the z-buffer splats (and projects) a fraction of them. The kept
    point of a cube is its first in order, so the choice is deterministic.
    """
    if points_box.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    order, starts = _cube_runs(points_box, radius_m)
    return np.sort(order[starts])


def surfel_means(points_box: np.ndarray, radius_m: float) -> np.ndarray:
    """float64 [k, 3]: the mean of the points of ``points_box`` float64 [m, 3] in each cube of side
    ``radius_m`` (a voxel grid's centroids), in the order of the cubes' keys
    (:func:`surfel_cells`). Range noise moves each return along its ray; the mean of a cube's
    returns (many, where an object was seen over a whole segment) carries less of it."""
    if points_box.shape[0] == 0:
        return np.zeros((0, 3))
    order, starts = _cube_runs(points_box, radius_m)
    return _run_means(points_box, order, starts)


def _run_means(points_box: np.ndarray, order: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """float64 [k, 3]: the mean of ``points_box`` over each run of :func:`_cube_runs`."""
    counts = np.diff(np.append(starts, order.size))
    return np.add.reduceat(points_box[order], starts, axis=0) / counts[:, None]


def surfel_first_and_means(points_box: np.ndarray, radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """``(surfel_subsample(...), surfel_means(...))`` of ``points_box`` float64 [m, 3] from one
    sort of its cubes."""
    if points_box.shape[0] == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    order, starts = _cube_runs(points_box, radius_m)
    return np.sort(order[starts]), _run_means(points_box, order, starts)


def _square_min(image: np.ndarray, r: int) -> np.ndarray:
    """float32 [H, W]: the minimum over the (2r+1)^2 square round each pixel, outside the image
    +inf (``scipy.ndimage.minimum_filter(size=2r+1, mode="constant", cval=inf)``; OpenCV's
    separable erosion, several times faster on a full-size image; min is exact, so the same map)."""
    return cv2.erode(image, np.ones((2 * r + 1, 2 * r + 1), np.uint8), borderType=cv2.BORDER_CONSTANT,
                     borderValue=float("inf"))


def _square_max(image: np.ndarray, r: int) -> np.ndarray:
    """float32 [H, W]: the maximum over the (2r+1)^2 square round each pixel, the edge repeated
    outside (``scipy.ndimage.maximum_filter(size=2r+1, mode="nearest")``; OpenCV's dilation)."""
    return cv2.dilate(image, np.ones((2 * r + 1, 2 * r + 1), np.uint8), borderType=cv2.BORDER_REPLICATE)


def close_holes(buffer: np.ndarray, fill_px: int) -> np.ndarray:
    """float32 [H, W]: the nearest-depth ``buffer`` float32 [H, W] (inf: empty) closed by ``fill_px``.

    A grey-level closing of the near surfaces: each pixel's depth spreads over the
    ``(2 fill_px + 1)^2`` square round it (minimum), then each pixel takes the farthest of that
    over its own square (maximum). An empty or farther pixel with nearer depths on both sides
    within ``2 fill_px`` is filled at about their depth (a hole between an occluder's splats, where a
    capped near footprint or an unsampled part of the object left one); a convex outline and a
    depth step between two surfaces stay where they are, because the second pass takes back what
    the first spread beyond them. Never farther than ``buffer``.
    """
    if fill_px <= 0:
        return buffer
    return np.minimum(buffer, _square_max(_square_min(buffer, fill_px), fill_px))


def nearest_depth(pixels: np.ndarray, depth: np.ndarray, width: int, height: int, focal: float,
                  radius_m, max_px: int, with_radius: bool = False, use_kernel: bool = False):
    """float32 [height, width]: the nearest splatted depth per pixel (inf where nothing lands).

    ``pixels`` float64 [m, 2] (x, y), ``depth`` float64 [m] (> 0; callers drop the rest). A return
    covers the (2r+1)^2 pixels around its own, ``r = min(max_px, round(focal * radius_m / depth))``
    (``radius_m`` metres, one for all or float [m], one per return). With ``with_radius``, returns
    ``(buffer, radius int8 [height, width])``: the footprint ``r`` of the return that holds each
    pixel's depth (the largest among equal depths; 0 where none lands).

    Each footprint size is one pass: the returns of that size are written at their own pixels
    (the nearest per pixel) into a buffer padded by ``max_px``, which a separable minimum filter
    of side 2r+1 (OpenCV's erosion) then spreads (the cost does not grow with the square of the
    footprint). ``use_kernel``: the passes over the returns and the pixels around the erosions
    in numba (:mod:`drivetrack.visibility.kernel`), the same buffer and footprints.
    """
    buffer = np.full((height, width), np.inf, dtype=np.float32)
    footprint = np.zeros((height, width), dtype=np.int8)
    if depth.size == 0:
        return (buffer, footprint) if with_radius else buffer
    if use_kernel:
        _nearest_depth_kernel(pixels, depth, width, height, focal, radius_m, max_px, buffer, footprint)
        return (buffer, footprint) if with_radius else buffer
    pad = int(max_px)
    col = np.floor(pixels[:, 0]).astype(np.int64) + pad
    row = np.floor(pixels[:, 1]).astype(np.int64) + pad
    radius = np.minimum(np.rint(focal * np.asarray(radius_m, dtype=np.float64) / depth), max_px).astype(np.int64)
    radius = np.broadcast_to(radius, depth.shape)
    z = depth.astype(np.float32)
    # a return reaches the image only when its pixel lies within its footprint of it
    ok = (row >= pad - radius) & (row < height + pad + radius) & (col >= pad - radius) & (col < width + pad + radius)
    groups = []
    for r in np.unique(radius[ok]).tolist():
        sel = ok & (radius == r)
        centres = np.full((height + 2 * pad) * (width + 2 * pad), np.inf, dtype=np.float32)
        np.minimum.at(centres, row[sel] * (width + 2 * pad) + col[sel], z[sel])
        centres = centres.reshape(height + 2 * pad, width + 2 * pad)
        if r > 0:
            centres = _square_min(centres, r)
        spread = centres[pad:pad + height, pad:pad + width]
        np.minimum(buffer, spread, out=buffer)
        if with_radius:
            groups.append((r, spread))
    if not with_radius:
        return buffer
    for r, spread in groups:                         # the footprint of the return each pixel kept
        won = (spread == buffer) & np.isfinite(buffer)
        footprint[won] = np.maximum(footprint[won], np.int8(r))
    return buffer, footprint


#: :func:`nearest_depth` with ``use_kernel``: a footprint's returns are written square by square
#: (:func:`drivetrack.visibility.kernel.splat_merge`) when their squares' pixels number at most
#: this many times the padded buffer's, else scattered, eroded by OpenCV and merged (the same
#: buffer either way; on the cost bench's segment most footprints hold a few returns)
SPLAT_DIRECT = 1.0


def _nearest_depth_kernel(pixels, depth, width, height, focal, radius_m, max_px, buffer, footprint) -> None:
    """:func:`nearest_depth` into ``buffer`` (+inf) and ``footprint`` (0): the returns grouped by
    footprint and scattered by numba, each group spread by OpenCV's erosion, merged by numba (or,
    for a group of few returns, each square written directly: :data:`SPLAT_DIRECT`)."""
    from drivetrack.visibility import kernel

    depth = np.ascontiguousarray(depth, dtype=np.float64)
    m = depth.size
    max_px = int(max_px)
    order, flat = np.empty(m, dtype=np.int64), np.empty(m, dtype=np.int64)
    starts = np.empty(max_px + 2, dtype=np.int64)
    kernel.splat_groups(np.ascontiguousarray(pixels, dtype=np.float64), depth,
                        np.ascontiguousarray(np.broadcast_to(np.asarray(radius_m, dtype=np.float64), depth.shape)),
                        int(width), int(height), float(focal), max_px, order, flat, starts)
    pad = max_px
    for r in range(max_px + 1):
        if starts[r] == starts[r + 1]:
            continue
        if (starts[r + 1] - starts[r]) * (2 * r + 1) ** 2 <= (height + 2 * pad) * (width + 2 * pad) * SPLAT_DIRECT:
            kernel.splat_merge(buffer, footprint, flat, order, depth, int(starts[r]), int(starts[r + 1]), r, pad)
            continue
        centres = np.full((height + 2 * pad, width + 2 * pad), np.inf, dtype=np.float32)
        kernel.scatter_min(centres, flat, order, depth, int(starts[r]), int(starts[r + 1]))
        if r > 0:
            centres = _square_min(centres, r)
        kernel.merge_spread(buffer, footprint, centres[pad:pad + height, pad:pad + width], np.int8(r))


def crop_growth_px(max_px: int, fill_px: int) -> int:
    """Buffer pixels the z-buffer's crop reaches beyond its points' pixels: a point's window
    (at most ``max_px``), the closing's reach (``2 fill_px``: :func:`close_holes` spreads, then
    takes back) and the edge band's one pixel more. Within it the crop's buffer equals the
    whole image's at every pixel a point looks at, so a point's decision and margin do not
    depend on the other points tested with it (a chunk, the kept candidates); with the footprint
    alone as before (2026-12-02), a closing cut at the crop's edge moved a few deeply hidden
    point-frames' margins by up to 10 units."""
    return int(max_px) + 2 * int(fill_px) + 1


def occluder_buffer(pixels: np.ndarray, depth: np.ndarray, radius_m, objects: np.ndarray | None, width: int,
                    height: int, focal: float, max_px: int, fill_px: int,
                    use_kernel: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(buffer float32 [height, width], footprint int8 [height, width])``: the other objects'
    nearest splatted depth and the footprint of the return holding it (:func:`nearest_depth`), each
    object's holes closed by ``fill_px`` (:func:`close_holes`) on its own.

    ``objects`` int [m] says which object each return is of (None: all one). Closing each
    object's splats apart fills the gaps between its own returns but not the gap between two
    objects: a pole a few pixels beside a pedestrian, or a sign beside its pole, leaves the
    surface behind them visible between them. Each object is splatted in its own part of the
    image (its returns' pixels grown by its largest footprint, then twice the closing and a pixel:
    beyond that its closed buffer is empty whatever the part's size), then the nearest of all is
    kept. ``use_kernel``: see :func:`nearest_depth`.
    """
    if objects is None or fill_px <= 0:
        buffer, footprint = nearest_depth(pixels, depth, width, height, focal, radius_m, max_px, with_radius=True,
                                          use_kernel=use_kernel)
        return close_holes(buffer, fill_px), footprint
    buffer = np.full((height, width), np.inf, dtype=np.float32)
    footprint = np.zeros((height, width), dtype=np.int8)
    radius_m = np.broadcast_to(np.asarray(radius_m, dtype=np.float64), depth.shape)
    order = np.argsort(objects, kind="stable")
    for part in np.split(order, first_of_cells(objects[order])[1:]):
        # the object's largest footprint (nearest_depth's rule), not max_px: a far object's part
        # is a fraction of the size
        reach = int(np.minimum(np.rint(focal * radius_m[part] / depth[part]), max_px).max())
        pad = reach + 2 * int(fill_px) + 1
        col, row = np.floor(pixels[part, 0]), np.floor(pixels[part, 1])
        c0, c1 = max(0, int(col.min()) - pad), min(width, int(col.max()) + 1 + pad)
        r0, r1 = max(0, int(row.min()) - pad), min(height, int(row.max()) + 1 + pad)
        if c0 >= c1 or r0 >= r1:
            continue
        own, own_footprint = nearest_depth(pixels[part] - (c0, r0), depth[part], c1 - c0, r1 - r0, focal,
                                           radius_m[part], max_px, with_radius=True, use_kernel=use_kernel)
        own = close_holes(own, fill_px)
        if use_kernel:
            from drivetrack.visibility.kernel import merge_nearer

            merge_nearer(buffer[r0:r1, c0:c1], footprint[r0:r1, c0:c1], own, own_footprint)
            continue
        window = buffer[r0:r1, c0:c1]
        nearer = own < window
        window[nearer] = own[nearer]
        footprint[r0:r1, c0:c1][nearer] = own_footprint[nearer]
    return buffer, footprint


def _edge_band(edge: np.ndarray, hidden: np.ndarray, covered: np.ndarray, at: np.ndarray, z: np.ndarray,
               row: np.ndarray, col: np.ndarray, abs_m: float, rel: float) -> None:
    """Sets ``edge`` bool [n] at the points ``at`` int [k] that ``hidden`` bool [n] says are hidden
    while the window one buffer pixel wider than theirs (``covered``: the buffer's square maximum
    over their window) holds a depth beyond their threshold (an uncovered pixel): within a buffer
    pixel of an occluder's outline. ``row`` / ``col`` int [n]: the points' buffer pixels in
    ``covered``'s crop; ``z`` float [n] their depths."""
    at = at[hidden[at]]
    if at.size:
        wider = _square_max(covered, 1)
        z_at = z[at]
        edge[at] = ~(wider[row[at], col[at]] < z_at - (abs_m + rel * z_at))


def hidden_by_others(points_camera: np.ndarray, pixels: np.ndarray, valid: np.ndarray,
                     occluders: list[tuple[np.ndarray, np.ndarray]], width: int, height: int, focal: float,
                     radius_m: float, max_px: int, abs_m: float, rel: float, fill_px: int = 0,
                     subpixels: int = 1, use_kernel: bool = False, rescued: np.ndarray | None = None,
                     edge: np.ndarray | None = None):
    """bool [T, n]: the tracked point lies behind another object's surface at that frame.

    Args:
        points_camera: float64 [T, n, 3], the tracked points in the camera frame (only the first
            column, the z-depth, is read: [T, n, 1] will do).
        pixels: float64 [T, n, 2] their pixels; ``valid`` bool [T, n] where the projection holds.
        occluders: per frame, (pixels float64 [m_t, 2], depth float64 [m_t][, radius_m float64
            [m_t][, object int [m_t]]]) of the other objects' returns projected in that frame's
            image (only valid projections in front of the camera); without the third member every
            return's footprint radius is ``radius_m``; with the fourth, each object's holes are
            closed on their own (:func:`occluder_buffer`).
        width, height, focal: the image and its focal length (pixels).
        radius_m, max_px: the footprint (see :func:`nearest_depth`).
        abs_m, rel: the tolerance; hidden iff ``buffer < z - (abs_m + rel * z)``.
        fill_px: close the buffer by this many pixels first (:func:`close_holes`), each object
            apart when the occluders say which object each return is of.
        subpixels: the buffer's resolution in buffer pixels per image pixel along each axis
            (``max_px``, ``fill_px`` and the footprints are scaled with it, so they keep their size
            in the image). Near an occluder's outline the decision is quantised to one buffer
            pixel: a point a fraction of a pixel outside a pole falls in the same image pixel as
            the pole's outermost returns and was called hidden; 2 halves that band.
        use_kernel: the passes over the points, the returns and the buffer's pixels in numba
            (:mod:`drivetrack.visibility.kernel`; the morphology stays OpenCV's): the same
            decisions and margins.
        rescued: bool [T, n] or None: when given, set where the point's own buffer pixel holds an
            occluder's depth nearer than its threshold while the footprint rule leaves it visible
            (the occluders do not cover its whole footprint): the band along an occluder's outline
            where the buffer cannot say on which side of it the point lies
            (:func:`hull_hidden` decides there).
        edge: bool [T, n] or None: when given, set where the footprint rule hides the point
            while the window one buffer pixel wider reaches a pixel no occluder covers (nearer
            than the point's threshold): the other side of that band, within a buffer pixel of
            an outline (:func:`hull_missed` decides there).

    Returns:
        ``(hidden bool [T, n], margin_m float32 [T, n])``: the margin is how far (metres) the
        farthest buffer value over the point's footprint lies beyond the hiding threshold
        ``z - (abs_m + rel * z)``: negative when hidden, positive when an occluder covers the
        footprint but too far in front to hide it, +inf where no occluder covers it whole.
    """
    if use_kernel:
        return _hidden_by_others_kernel(points_camera, pixels, valid, occluders, width, height, focal, radius_m,
                                        max_px, abs_m, rel, fill_px, subpixels, rescued, edge)
    if subpixels != 1:
        scale = int(subpixels)
        return hidden_by_others(points_camera, pixels * scale, valid,
                                [(o[0] * scale,) + tuple(o[1:]) for o in occluders], width * scale, height * scale,
                                focal * scale, radius_m, max_px * scale, abs_m, rel, fill_px * scale,
                                rescued=rescued, edge=edge)
    t_count, n = valid.shape
    hidden = np.zeros((t_count, n), dtype=bool)
    margin = np.full((t_count, n), np.inf, dtype=np.float32)
    for tau in range(t_count):                       # one image at a time: bounded memory
        occ_pixels, occ_depth = occluders[tau][:2]
        # a footprint radius per return (metres) and its object when the occluder list gives them
        occ_radius = occluders[tau][2] if len(occluders[tau]) > 2 else np.float64(radius_m)
        occ_object = occluders[tau][3] if len(occluders[tau]) > 3 else None
        if occ_depth.size == 0 or n == 0:
            continue
        z = points_camera[tau, :, 0]
        px = np.where(valid[tau, :, None] & np.isfinite(pixels[tau]), pixels[tau], -1.0)
        col, row = np.floor(px[:, 0]).astype(np.int64), np.floor(px[:, 1]).astype(np.int64)
        inside = valid[tau] & (col >= 0) & (col < width) & (row >= 0) & (row < height)
        if not inside.any():
            continue
        # Only the window the tracked points fall in matters: splat into that crop of the image,
        # grown by what reaches a point's footprint (crop_growth_px: the closing included), so
        # each point's buffer is the whole image's; a return's own footprint reaches at most
        # max_px beyond its pixel.
        grow = crop_growth_px(max_px, fill_px)
        c0, c1 = max(0, int(col[inside].min()) - grow), min(width, int(col[inside].max()) + 1 + grow)
        r0, r1 = max(0, int(row[inside].min()) - grow), min(height, int(row[inside].max()) + 1 + grow)
        occ_col, occ_row = np.floor(occ_pixels[:, 0]), np.floor(occ_pixels[:, 1])
        near = ((occ_col >= c0 - max_px) & (occ_col < c1 + max_px) & (occ_row >= r0 - max_px)
                & (occ_row < r1 + max_px))
        if not near.any():
            continue
        buffer, footprint = occluder_buffer(occ_pixels[near] - (c0, r0), occ_depth[near],
                                            occ_radius[near] if np.ndim(occ_radius) else radius_m,
                                            None if occ_object is None else occ_object[near], c1 - c0, r1 - r0,
                                            focal, max_px, fill_px)
        # The same footprint rule on the point's side: it is hidden only when the occluders cover
        # its whole footprint (the farthest buffer value over it is nearer than the point), so the
        # footprints that close the gaps between an occluder's returns do not grow its outline.
        # The window is the larger of the point's footprint and that of the occluder return at its
        # pixel: splatting grows an outline by the occluder's footprint, and looking as far round
        # the point takes that back (a morphological closing), also for a far point whose own
        # footprint is smaller than a near occluder's.
        # Only a point whose own pixel holds an occluder's depth can be covered whole (its window
        # includes that pixel): the others stay visible to this test with an infinite margin.
        on = np.flatnonzero(inside)
        on = on[np.isfinite(buffer[row[on] - r0, col[on] - c0])]
        if on.size == 0:
            continue
        z_on, row_on, col_on = z[on], row[on] - r0, col[on] - c0
        radius = np.minimum(np.rint(focal * radius_m / np.where(z_on > 0, z_on, np.inf)), max_px).astype(np.int64)
        radius = np.maximum(radius, footprint[row_on, col_on])
        farthest = np.full(on.size, np.inf, dtype=np.float64)
        # the windows grow in turn: a square maximum of r + s is that of s over that of r (also at
        # the image's edges), so each size costs only its growth over the last
        sizes, size_of = np.unique(radius, return_inverse=True)
        covered, done = buffer, 0
        threshold = z_on - (abs_m + rel * z_on)
        band = np.zeros(on.size, dtype=bool)
        for k, r in enumerate(sizes.tolist()):
            if r > done:
                covered, done = _square_max(covered, r - done), r
            sel = size_of == k
            farthest[sel] = covered[row_on[sel], col_on[sel]]
            if edge is not None:
                _edge_band(band, farthest < threshold, covered, np.flatnonzero(sel), z_on, row_on, col_on, abs_m, rel)
        hidden[tau, on] = farthest < threshold
        if edge is not None:
            edge[tau, on] = band
        covered = np.isfinite(farthest)
        margin[tau, on[covered]] = (farthest[covered] - threshold[covered]).astype(np.float32)
        if rescued is not None:
            rescued[tau, on] = (buffer[row_on, col_on] < threshold) & ~hidden[tau, on]
    return hidden, margin


#: :func:`own_plane_slack`: the span of a point's own plane that may stand in front of it, in
#: footprint radii (one: a splat's half side; docs/visibility.md "The object's own surface")
OWN_PLANE_FOOTPRINTS = 1.0


#: :func:`pocket_points`: how deep inside the convex hull of its object's surface a point must lie
#: for the object itself to be able to hide it (metres)
OWN_POCKET_DEPTH_M = 0.1


def pocket_points(points_box: np.ndarray, half: np.ndarray, cloud: np.ndarray,
                  min_depth_m: float = OWN_POCKET_DEPTH_M) -> np.ndarray:
    """bool [n]: the points ``points_box`` float [n, 3] (box frame) lying more than ``min_depth_m``
    inside the convex hull of their object's surface ``cloud`` float [m, 3] (box frame): a cabin
    car's bonnet and boot, a pedestrian's far leg; False for a convex object's whole surface.

    Only such a point can be hidden by its own object beyond the back-face test: a point on the
    hull that faces the camera sees it past the hull's supporting plane. The hull lies inside the
    label box (half-size ``half`` float [3]), so a point within ``min_depth_m`` of the box's faces
    is within it of the hull too and is not measured against the hull at all (on a box-shaped car
    under tight labels, none is). A cloud too small or too flat for a hull: none."""
    from scipy.spatial import ConvexHull, QhullError

    from drivetrack.boxes import box_depth

    points_box = np.asarray(points_box, np.float64)
    out = np.zeros(points_box.shape[0], dtype=bool)
    candidate = np.flatnonzero(box_depth(points_box, np.asarray(half, np.float64)) > min_depth_m)
    if candidate.size == 0 or np.shape(cloud)[0] < 4:
        return out
    try:
        facets = ConvexHull(np.asarray(cloud, np.float64)).equations                     # [F, 4], outward
    except QhullError:
        return out
    for start in range(0, candidate.size, 8192):
        rows = candidate[start:start + 8192]
        outside = points_box[rows] @ facets[:, :3].T + facets[:, 3]                        # [k, F], <= 0 inside
        out[rows] = -outside.max(axis=1) > min_depth_m
    return out


#: :func:`roof_fill`: a point of an object's roof is unsampled when no return lies within this
#: (metres) of it
ROOF_FILL_GAP_M = 0.05
#: :func:`roof_fill`: a point of the cloud with no other within this (metres) does not shape the
#: hull: a return of a badly registered frame standing above the roof, a stray return in the box
#: (on the medium hard world with 5 cm labels: 21,777 -> 21,551 wrong calls; with 2 cm range noise
#: too 64,468 -> 64,330; exact labels unchanged)
ROOF_OUTLIER_M = 0.1
#: :func:`roof_fill`: the roof is the part of the hull's top whose facets tilt less than this
#: (degrees) from level: a box car's or van's roof, the flat middle of a rounded one, a head's top;
#: not a windscreen, nor the facet a cabin car's hull spans from its roof to its bonnet's edge
#: (about 26 degrees on the synthetic cabin car, 38 to its boot's; at 25.8 degrees (cos 0.9) parts
#: of it were filled, and the air over the bonnet hid what lay behind: 16,270 -> 16,891 wrong
#: calls on the cabin world)
ROOF_MAX_TILT_DEG = 11.5


#: :func:`roof_fill` / :func:`occluder_hull`'s ``spanned`` when the caller has none: computed there
SPAN_HERE = object()


def returns_hull(cloud: np.ndarray, outlier_m: float = ROOF_OUTLIER_M):
    """``(tree, kept bool [m], returns float64 [k, 3], hull)``: the convex hull
    (``scipy.spatial.ConvexHull``) of an object's returns ``cloud`` float [m, 3] with no other
    within ``outlier_m`` left out (``kept``), and a ``cKDTree`` of all of them; None for a cloud
    too small or too flat (:func:`roof_fill`, :func:`occluder_hull`: both of the same cloud and
    ``outlier_m``, which the track stage computes once per object and hands to both). Read only."""
    from scipy.spatial import ConvexHull, QhullError, cKDTree

    cloud = np.asarray(cloud, np.float64)
    if cloud.shape[0] < 4:
        return None
    tree = cKDTree(cloud)
    second, _ = tree.query(cloud, k=2, distance_upper_bound=outlier_m)                 # itself, then its nearest
    kept = np.isfinite(second[:, 1])
    if kept.sum() < 4:
        return None
    try:
        return tree, kept, cloud[kept], ConvexHull(cloud[kept])
    except QhullError:
        return None


def roof_fill(cloud: np.ndarray, spacing_m: float, max_tilt_deg: float = ROOF_MAX_TILT_DEG,
              min_gap_m: float = ROOF_FILL_GAP_M, outline_step_m: float | None = None,
              outlier_m: float = ROOF_OUTLIER_M, spanned=SPAN_HERE) -> np.ndarray:
    """float64 [h, 3]: the unsampled part of an object's roof (box frame, metres): points of the
    top of the convex hull of its surface ``cloud`` float [m, 3] (box frame, z up), on a grid of
    ``spacing_m`` in x and y, where the hull's top is level to ``max_tilt_deg`` and no point of
    ``cloud`` lies within ``min_gap_m``; and along the roof's outline (the hull edges between a
    level facet and a tilted one) every ``outline_step_m`` (default a third of ``spacing_m``):
    the grid stops up to a spacing short of the outline, and a z-buffer's outline is its
    outermost splats' (measured on the medium hard world: the grid alone at 7.5 cm, 7,623 wrong
    calls; at 2.5 cm, 7,112; at 7.5 cm with the outline at 2.5 cm, 6,970, with far fewer points).

    Why: the lidar sees a car's roof at a grazing angle from a few metres off, and an object's
    returns over a whole segment may hold none of it, while a camera a little higher sees the
    roof as a band of pixels above the car's side: a point of a farther object behind that band
    is hidden by the roof, and a z-buffer of the returns alone has nothing there (on the medium
    hard world, two thirds of the points hidden by another object and called visible lay behind
    an occluder's top, over a third of those more than 5 cm from its every return). The returns on
    the tops of its sides, ends and windows bound the roof, and the hull spans it.

    The upward facets' shadows tile the hull's in ``(x, y)``: a grid point in a level facet's
    shadow is on the roof, at that facet's plane. Points of ``cloud`` with no other within
    ``outlier_m`` are left out first (of the hull and of the gaps). A cloud too small or too flat
    for a hull: none. ``spanned``: :func:`returns_hull` of ``cloud`` and ``outlier_m`` when the
    caller has it (computed here otherwise)."""
    if spanned is SPAN_HERE:
        spanned = returns_hull(cloud, outlier_m)
    if spanned is None:
        return np.zeros((0, 3))
    tree, kept, cloud, hull = spanned
    facets = hull.equations                                                # [F, 4]: n . p + d <= 0 inside
    level = facets[:, 2] >= np.cos(np.radians(max_tilt_deg))
    corners = cloud[hull.simplices[level]][:, :, :2]                                  # [L, 3, 2]
    origin = cloud[:, :2].min(axis=0)                          # the grid's anchor: the cloud's corner
    points = _level_facet_grid(corners, facets[level], origin, spacing_m)
    # the roof's outline: the hull edges between a level facet and a tilted one (edge i of a
    # facet is the one opposite its vertex i, shared with its neighbour i)
    step = spacing_m / 3.0 if outline_step_m is None else float(outline_step_m)
    ends = [np.stack([cloud[hull.simplices[outline, (i + 1) % 3]], cloud[hull.simplices[outline, (i + 2) % 3]]], axis=1)
            for i in range(3) for outline in [level & ~level[hull.neighbors[:, i]]] if outline.any()]
    if ends:
        ends = np.concatenate(ends)                                                     # [E, 2, 3]
        length = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=-1)
        count = np.ceil(length / step).astype(np.int64) + 1                           # samples per edge, ends included
        of = np.repeat(np.arange(ends.shape[0]), count)                                # each sample's edge
        first = np.repeat(np.cumsum(count) - count, count)
        fraction = (np.arange(of.size) - first) / np.maximum(count[of] - 1, 1)
        points = np.concatenate([points, ends[of, 0] + fraction[:, None] * (ends[of, 1] - ends[of, 0])])
    if points.shape[0] == 0:
        return points
    # the gaps, against the kept returns, from the tree of all of them: two left-out returns are
    # more than ``outlier_m`` apart, so of the two nearest returns within ``min_gap_m`` <=
    # ``outlier_m / 2`` at most one is left out
    near, index = tree.query(points, k=2, distance_upper_bound=min_gap_m)
    found = index < tree.n                                                    # [p, 2]: within min_gap_m
    found[found] = kept[index[found]]
    return points[~found.any(axis=1)]


def _level_facet_grid(corners: np.ndarray, plane: np.ndarray, origin: np.ndarray, spacing_m: float) -> np.ndarray:
    """float64 [g, 3]: the points of the grid of ``spacing_m`` anchored at ``origin`` float [2]
    (x, y) that lie in the (x, y) shadow of a level hull facet (``corners`` float [L, 3, 2], its
    corners' x, y; ``plane`` float [L, 4], its outward equation), each at its facet's plane (the
    first facet holding it, facets on a shared edge), in the grid's x-major order.

    The upward facets' shadows tile the hull's in (x, y), so a grid point over a level facet's
    shadow is on the roof there. Each facet's edge tests run over the grid points of its own
    bounding box only: a roof's facets are a few grid cells across."""
    if corners.shape[0] == 0:
        return np.zeros((0, 3))
    lo_all = np.floor((corners.reshape(-1, 2).min(axis=0) - origin) / spacing_m)
    hi_all = np.ceil((corners.reshape(-1, 2).max(axis=0) - origin) / spacing_m)
    ny = int(hi_all[1] - lo_all[1]) + 1
    # each facet's grid bounding box (indices relative to lo_all), then its cells one by one
    lo = np.floor((corners.min(axis=1) - origin) / spacing_m) - lo_all                    # [L, 2]
    hi = np.ceil((corners.max(axis=1) - origin) / spacing_m) - lo_all
    span = (hi - lo + 1).astype(np.int64)                                                 # [L, 2]
    count = span[:, 0] * span[:, 1]
    facet = np.repeat(np.arange(corners.shape[0]), count)
    local = np.arange(facet.size) - np.repeat(np.cumsum(count) - count, count)
    ix = lo[facet, 0].astype(np.int64) + local // span[facet, 1]
    iy = lo[facet, 1].astype(np.int64) + local % span[facet, 1]
    q = origin + spacing_m * np.column_stack([ix + lo_all[0], iy + lo_all[1]])          # [c, 2]
    start = corners[facet]                                                               # [c, 3, 2]
    edge = np.roll(corners, -1, axis=1)[facet] - start                                   # edge i: corner i -> i + 1
    sign = np.sign(edge[:, 0, 0] * -edge[:, 2, 1] - edge[:, 0, 1] * -edge[:, 2, 0])       # orientation, [c]
    side = edge[:, :, 0] * (q[:, None, 1] - start[:, :, 1]) - edge[:, :, 1] * (q[:, None, 0] - start[:, :, 0])
    inside = (side * sign[:, None] >= -1e-9).all(axis=1)
    cell = (ix * ny + iy)[inside]
    facet = facet[inside]
    order = np.lexsort((facet, cell))                      # by grid cell, then the first facet holding it
    cell, facet = cell[order], facet[order]
    first = np.ones(cell.size, dtype=bool)
    first[1:] = cell[1:] != cell[:-1]
    cell, which = cell[first], facet[first]
    xy = origin + spacing_m * np.column_stack([cell // ny + lo_all[0], cell % ny + lo_all[1]])
    top = -(plane[which, 0] * xy[:, 0] + plane[which, 1] * xy[:, 1] + plane[which, 3]) / plane[which, 2]
    return np.column_stack([xy, top])


#: :func:`hull_hidden`: an occluder's hull decides a ray only where the ray enters it within this
#: (metres) of the occluder's surface (its returns and its roof fill): a hull facet spanning a
#: concavity (between a pedestrian's legs, over a cabin car's bonnet) is air
HULL_TRUST_M = 0.05


#: :func:`occluder_hull`: the returns within this (metres) of the hull measure how far its
#: facets stand out of the surface (the median of their depths inside it) ...
HULL_SURFACE_M = 0.1
#: ... and a surface spread more than this (metres) is noisy: its hull is moved in by the spread
HULL_NOISY_M = 0.02


@dataclass
class OccluderHull:
    """An occluder's convex hull for :func:`hull_hidden` (box frame, metres).

    Attributes:
        facets: float64 [F, 4], outward equations ``n . p + d`` (<= 0 inside), moved onto the surface.
        trusted: bool [F], the facets lying on the object's surface (:func:`occluder_hull`).
        tree: ``scipy.spatial.cKDTree`` of the surface the entries are checked against.
        centre, radius: float64 [3] and metres, a sphere holding the hull (a ray that misses it
            misses the hull).
    """
    facets: np.ndarray
    trusted: np.ndarray
    tree: object
    centre: np.ndarray = None
    radius: float = np.inf
    #: metres the facets were moved in from the hull as the returns span it (0: a clean surface)
    shift: float = 0.0


def _dot3(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """float64 [k, F]: ``p @ n.T`` for ``p`` float [k, 3] and ``n`` float [F, 3], by three
    elementwise products (a matrix product starts BLAS threads, whose spinning costs more than
    these small products on a two-core worker)."""
    return p[:, 0, None] * n[None, :, 0] + p[:, 1, None] * n[None, :, 1] + p[:, 2, None] * n[None, :, 2]



def _clip_convex(starts: np.ndarray, ray: np.ndarray, facets: np.ndarray, use_kernel: bool):
    """``(enter, by, leave, never, inside)`` of k rays ``starts + s ray`` (``starts`` float [k, 3],
    or [3]: one start for all; ``ray`` float [k, 3]) against the convex hull of ``facets`` float
    [F, 4] (outward ``n . p + d``): :func:`drivetrack.visibility.kernel.clip_convex`'s figures, by
    it (``use_kernel``) or in numpy from [k, F] products."""
    k = ray.shape[0]
    if use_kernel:
        from drivetrack.visibility.kernel import clip_convex

        one = starts.ndim == 1
        enter, leave = np.empty(k), np.empty(k)
        by = np.empty(k, dtype=np.int64)
        never, inside = np.empty(k, dtype=bool), np.empty(k, dtype=bool)
        clip_convex(np.ascontiguousarray(starts.reshape(-1, 3), dtype=np.float64),
                    np.ascontiguousarray(ray, dtype=np.float64), np.ascontiguousarray(facets, dtype=np.float64),
                    one, enter, leave, by, never, inside)
        return enter, by, leave, never, inside
    if starts.ndim == 1:                      # one start for all: its facet heights once
        a = np.broadcast_to(_dot3(starts[None], facets[:, :3])[0] + facets[:, 3], (k, facets.shape[0]))
    else:
        a = _dot3(starts, facets[:, :3]) + facets[:, 3]                                       # [k, F]
    b = _dot3(ray, facets[:, :3])                                                             # [k, F]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -a / b
    entering = np.where(b < 0, s, -np.inf)
    by = entering.argmax(axis=1)                                                              # the facet entered by
    enter = entering[np.arange(k), by]
    leave = np.where(b > 0, s, np.inf).min(axis=1)
    never = ((b == 0) & (a > 0)).any(axis=1)
    return enter, by, leave, never, (a <= 0).all(axis=1)


def box_points_at(points_world: np.ndarray, world_from_box: np.ndarray, velocity_world: np.ndarray,
                  yaw_rate: float, dt: np.ndarray) -> np.ndarray:
    """float64 [k, 3]: world points ``points_world`` float [k, 3] (metres) in the box frame of an
    object posed ``world_from_box`` float [4, 4] at a reference time and moving with centre
    velocity ``velocity_world`` float [3] (m/s) and ``yaw_rate`` (rad/s, about the world z
    through its centre), each at its own time ``dt`` float [k] (s) after the reference:
    ``R0^T Rz(-w dt) (p - c0 - v dt)``."""
    d = points_world - (world_from_box[:3, 3] + dt[:, None] * np.asarray(velocity_world, np.float64))
    cos, sin = np.cos(-yaw_rate * dt), np.sin(-yaw_rate * dt)
    turned = np.column_stack([cos * d[:, 0] - sin * d[:, 1], sin * d[:, 0] + cos * d[:, 1], d[:, 2]])
    return np.einsum("ji,nj->ni", world_from_box[:3, :3], turned)


def occluder_hull(cloud: np.ndarray, surface: np.ndarray | None = None, outlier_m: float = ROOF_OUTLIER_M,
                  surface_m: float = HULL_SURFACE_M, trust_m: float | None = None,
                  spanned=SPAN_HERE, use_kernel: bool = False) -> OccluderHull | None:
    """The :class:`OccluderHull` of an object's surface ``cloud`` float [m, 3] (box frame): the
    convex hull of its returns (those with no other within ``outlier_m`` left out, as
    :func:`roof_fill`'s), moved in by the spread of a noisy surface; a facet is trusted when its
    centroid and its edges' midpoints all lie within ``trust_m`` (default :data:`HULL_TRUST_M`)
    of ``surface`` float [s, 3] (default ``cloud``; the track stage passes the returns and the
    roof fill). None for a cloud too small or too flat.

    The spread: the median depth inside the hull of the returns within ``surface_m`` of it. A hull
    is spanned by the outermost returns, and where a sweep's registration errors add to the range
    noise they stand out of the surface by several centimetres: on the medium hard world with 5 cm
    labels and 2 cm range noise (spread 2.5-5.8 cm per object) the hulls as spanned hid 6,274 more
    visible point-frames than before; moved in by the spread, 67 fewer. A surface spread less than
    :data:`HULL_NOISY_M` stays as spanned (2 cm range noise alone: 0.5-1.4 cm; moving those in by it
    cost 1,900 of the 2,000 calls the hulls gained there; exact labels: 0). Trusted facets: a
    facet spanning a concavity (from a cabin's roof to the bonnet's edge, between a pedestrian's
    legs) is air over most of its area (cabin cars with 5 cm labels: 24,792 wrong calls with every
    facet, 23,398 with the trusted ones; 24,631 without hulls). ``spanned``: :func:`returns_hull`
    of ``cloud`` and ``outlier_m`` when the caller has it (computed here otherwise). ``use_kernel``:
    the returns' depths inside the hull in numba (:func:`drivetrack.visibility.kernel.hull_depths`),
    the same figures."""
    from scipy.spatial import cKDTree

    trust_m = HULL_TRUST_M if trust_m is None else float(trust_m)
    cloud = np.asarray(cloud, np.float64)
    if spanned is SPAN_HERE:
        spanned = returns_hull(cloud, outlier_m)
    if spanned is None:
        return None
    _, _, kept, hull = spanned
    facets = hull.equations.copy()
    inside = np.empty(kept.shape[0])
    if use_kernel:
        from drivetrack.visibility.kernel import hull_depths

        hull_depths(np.ascontiguousarray(kept, dtype=np.float64), np.ascontiguousarray(facets), inside)
    else:
        for start in range(0, kept.shape[0], 4096):              # bounded memory: [4096, F]
            inside[start:start + 4096] = -(_dot3(kept[start:start + 4096], facets[:, :3]) + facets[:, 3]).max(axis=1)
    # a noisy surface (its returns near the hull a median of more than HULL_NOISY_M inside it)
    # moved in by that median; a clean one left where its returns put it
    near = inside[inside <= surface_m]
    spread = float(np.median(near)) if near.size else 0.0
    shift = spread if spread > HULL_NOISY_M else 0.0
    facets[:, 3] += shift
    corners = kept[hull.simplices]                                                        # [F, 3, 3]
    samples = np.concatenate([corners.mean(axis=1, keepdims=True), 0.5 * (corners + np.roll(corners, -1, axis=1))],
                             axis=1) - shift * facets[:, None, :3]                       # [F, 4, 3]
    tree = cKDTree(cloud if surface is None else np.asarray(surface, np.float64))
    gap, _ = tree.query(samples.reshape(-1, 3), distance_upper_bound=trust_m)
    centre = 0.5 * (kept.min(axis=0) + kept.max(axis=0))
    radius = float(np.sqrt(((kept - centre) ** 2).sum(axis=1).max()))
    return OccluderHull(facets, np.isfinite(gap).reshape(-1, 4).all(axis=1), tree, centre, radius, shift)


def hull_missed(rays: list, depth: np.ndarray, hulls: list, abs_m: float, rel: float,
                use_kernel: bool = False) -> np.ndarray:
    """bool [k]: the ray from the camera centre to each of k tracked points (z-depths ``depth``
    float [k], metres) misses every other object's convex hull as its returns span it (each
    :class:`OccluderHull` grown back by the ``shift`` that moved it onto a noisy surface) before
    the hiding threshold ``z - (abs_m + rel z)``; False for every point when some hull is None
    (an object too small or too flat for one cannot clear the point). ``rays`` and ``hulls`` as
    :func:`hull_hidden`'s; every facet counts, trusted or not (a ray through a concavity's
    facet may still meet the object).

    Why: the z-buffer places an outline to one buffer pixel (half an image pixel), and the
    footprint rule hides a point whose whole footprint its occluders cover: a point a tenth of a
    pixel above a far car's roof line shares the buffer pixel of its topmost returns and is
    hidden. The hull as spanned reaches no farther than the returns, so a ray that misses it passes
    outside them: on the medium hard world with exact labels, the points the footprint rule hides
    within a buffer pixel of an outline and whose rays miss every hull were 2,475 of 10,404;
    freeing them took the wrong calls from 4,966 to 4,097 (with the hulls grown by 5 mm: 4,708;
    by 1 cm: 4,931; shrunk by 5 mm: 6,852; docs/visibility.md "Both sides of the outline band").
    ``use_kernel``: the clipping in numba (:func:`drivetrack.visibility.kernel.clip_convex`), the
    same figures."""
    depth = np.asarray(depth, np.float64).reshape(-1)
    k = depth.size
    missed = np.ones(k, dtype=bool)
    if k == 0:
        return missed
    s_max = (depth - (abs_m + rel * depth)) / depth
    for hull, (centres, points) in zip(hulls, rays):
        if hull is None:
            return np.zeros(k, dtype=bool)
        facets = hull.facets.copy()
        facets[:, 3] -= hull.shift                                 # as spanned: no farther than the returns
        centres = np.asarray(centres, np.float64)
        ray = np.asarray(points, np.float64).reshape(k, 3) - centres
        enter, _, leave, never, _ = _clip_convex(centres, ray, facets, use_kernel)
        enter = np.maximum(enter, 0.0)
        missed &= never | (enter >= leave) | (enter >= s_max)
    return missed


def hull_hidden(rays: list, depth: np.ndarray, hulls: list, abs_m: float, rel: float,
                trust_m: float = HULL_TRUST_M, use_kernel: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(hidden bool [k], margin_m float32 [k])``: which of k tracked points, at z-depths ``depth``
    float [k] (metres), lie behind another object's convex hull: the ray from the camera centre to
    the point enters the hull of object j at a depth nearer than ``z - (abs_m + rel z)``, within
    ``trust_m`` of its surface. ``rays[j] = (centres float [3] or [k, 3], points float [k, 3])``:
    the camera centre(s) and the points in object j's box frame (each point's at its capture
    time); ``hulls[j]``: its :class:`OccluderHull` (or None), whose facet the ray enters by must be
    trusted and whose surface the entry must lie within ``trust_m`` of. Margin: the entry's depth
    minus that threshold (negative: hidden), +inf where no hull hides the point.

    Why: near an occluder's outline the z-buffer is quantised to its buffer pixels and the
    footprint rule leaves a point visible unless the occluders cover its whole footprint
    (:func:`hidden_by_others`); a convex part of an occluder's surface has an exact outline. The
    depth along the ray is linear in the ray parameter s (the camera centre is its origin), so the
    entry's depth is ``s z``. A hull facet spanning a concavity is air: there the entry lies
    farther than ``trust_m`` from every return and the hull does not decide. ``use_kernel``: the
    clipping in numba (:func:`drivetrack.visibility.kernel.clip_convex`), the same figures."""
    depth = np.asarray(depth, np.float64).reshape(-1)
    k = depth.size
    hidden = np.zeros(k, dtype=bool)
    margin = np.full(k, np.inf)
    if k == 0:
        return hidden, margin.astype(np.float32)
    threshold = depth - (abs_m + rel * depth)
    s_max = threshold / depth
    for hull, (centres, points) in zip(hulls, rays):
        if hull is None:
            continue
        facets = hull.facets
        centres = np.asarray(centres, np.float64)
        points = np.asarray(points, np.float64).reshape(k, 3)
        # only the rays that reach the sphere holding the hull before their point
        ray = points - centres
        to_centre = hull.centre - centres
        along = np.clip(np.einsum("...i,...i->...", to_centre, ray) / np.einsum("ni,ni->n", ray, ray), 0.0, 1.0)
        closest = centres + along[:, None] * ray - hull.centre
        near = np.flatnonzero(np.einsum("ni,ni->n", closest, closest) <= (hull.radius * (1 + 1e-9) + 1e-9) ** 2)
        if near.size == 0:
            continue
        one = centres.ndim == 1
        starts = np.broadcast_to(centres, (near.size, 3)) if one else centres[near]
        enter, by, leave, never, inside = _clip_convex(centres if one else starts, ray[near], facets, use_kernel)
        enter = np.maximum(enter, 0.0)
        # a facet the ray runs parallel to and outside of: never inside; the camera inside: no test
        hit = ~(never | inside) & (enter < leave) & (enter < s_max[near]) & hull.trusted[by]
        if not hit.any():
            continue
        rows = near[hit]
        enter = enter[hit]
        entry = starts[hit] + enter[:, None] * ray[rows]
        gap, _ = hull.tree.query(entry, distance_upper_bound=trust_m)
        close = np.isfinite(gap)
        rows, enter = rows[close], enter[close]
        hidden[rows] = True
        margin[rows] = np.minimum(margin[rows], enter * depth[rows] - threshold[rows])
    return hidden, margin.astype(np.float32)


def own_plane_slack(points_box: np.ndarray, normal: np.ndarray, reliable: np.ndarray, centres_box: np.ndarray,
                    radius_m: float) -> np.ndarray:
    """float32 [T, n]: how far (metres) in front of a tracked point its own surface's splats may
    lie without hiding it: the depth its own plane spans over :data:`OWN_PLANE_FOOTPRINTS`
    footprints of ``radius_m`` seen from the camera, ``OWN_PLANE_FOOTPRINTS * radius_m * cot(a)``
    with ``a`` the angle between the line of sight and the plane; +inf where the normal is
    unreliable or the plane is seen edge-on.

    Points ``points_box`` float [n, 3] with normals ``normal`` float [n, 3] (unit, box frame) and
    ``reliable`` bool [n]; camera centres ``centres_box`` float [T, 3] (box frame).

    Why: the splats are squares facing the camera; a surface seen at a grazing angle (a roof from
    just above it, a car's side from behind) has its nearer returns' squares reach over its
    farther ones, metres deeper at a degree's grazing, and the object would hide itself. Its own
    plane can never hide a point; only a part of the object standing in front of it (a cabin
    before the deck behind it, a far leg behind a near one) by more than that depth can."""
    ray = centres_box[:, None, :] - np.asarray(points_box, np.float64)[None]              # [T, n, 3]
    sine = np.abs(np.einsum("tnk,nk->tn", ray, normal)) / np.linalg.norm(ray, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        slack = OWN_PLANE_FOOTPRINTS * radius_m * np.sqrt(np.maximum(1.0 - sine ** 2, 0.0)) / sine
    slack[:, ~np.asarray(reliable, bool)] = np.inf
    return np.where(np.isfinite(slack), slack, np.inf).astype(np.float32)


def _hidden_by_others_kernel(points_camera, pixels, valid, occluders, width, height, focal, radius_m, max_px,
                             abs_m, rel, fill_px, subpixels, rescued=None, edge=None):
    """:func:`hidden_by_others` with ``use_kernel``: its steps in the same order, each pass over
    the points, the returns or the buffer's pixels by :mod:`drivetrack.visibility.kernel`, the
    erosions and dilations by OpenCV."""
    from drivetrack.visibility import kernel

    scale = int(subpixels)
    width, height, focal = int(width) * scale, int(height) * scale, float(focal) * scale
    max_px, fill_px = int(max_px) * scale, int(fill_px) * scale
    t_count, n = valid.shape
    hidden = np.zeros((t_count, n), dtype=bool)
    margin = np.full((t_count, n), np.inf, dtype=np.float32)
    col, row = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
    inside = np.empty(n, dtype=bool)
    on, size = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
    for tau in range(t_count):
        occ_pixels, occ_depth = occluders[tau][:2]
        occ_radius = occluders[tau][2] if len(occluders[tau]) > 2 else None
        occ_object = occluders[tau][3] if len(occluders[tau]) > 3 else None
        if occ_depth.size == 0 or n == 0:
            continue
        z = np.ascontiguousarray(points_camera[tau, :, 0], dtype=np.float64)
        c_lo, c_hi, r_lo, r_hi = kernel.zbuffer_points(np.ascontiguousarray(pixels[tau], dtype=np.float64),
                                                       np.ascontiguousarray(valid[tau], dtype=bool), float(scale),
                                                       width, height, col, row, inside)
        if c_hi < 0:
            continue
        grow = crop_growth_px(max_px, fill_px)
        c0, c1 = max(0, c_lo - grow), min(width, c_hi + 1 + grow)
        r0, r1 = max(0, r_lo - grow), min(height, r_hi + 1 + grow)
        near_pixels = np.empty((occ_depth.size, 2))
        near = kernel.zbuffer_near(np.ascontiguousarray(occ_pixels, dtype=np.float64), float(scale), c0, c1, r0, r1,
                                   max_px, near_pixels)
        if near.size == 0:
            continue
        buffer, footprint = occluder_buffer(near_pixels[:near.size], occ_depth[near],
                                            np.full(near.size, float(radius_m)) if occ_radius is None
                                            else occ_radius[near],
                                            None if occ_object is None else occ_object[near], c1 - c0, r1 - r0,
                                            focal, max_px, fill_px, use_kernel=True)
        count = kernel.zbuffer_on(buffer, footprint, col, row, inside, z, c0, r0, focal, float(radius_m), max_px,
                                  on, size)
        if count == 0:
            continue
        covered, done = buffer, 0
        for r in np.flatnonzero(np.bincount(size[:count], minlength=max_px + 1)).tolist():
            if r > done:
                covered, done = _square_max(covered, r - done), r
            kernel.zbuffer_decide(covered, on[:count], size[:count], r, col, row, c0, r0, z, float(abs_m), float(rel),
                                  hidden[tau], margin[tau])
            if edge is not None:
                _edge_band(edge[tau], hidden[tau], covered, on[:count][size[:count] == r], z, row - r0, col - c0,
                           abs_m, rel)
        if rescued is not None:
            at = on[:count]
            z_at = z[at]
            rescued[tau, at] = (buffer[row[at] - r0, col[at] - c0] < z_at - (abs_m + rel * z_at)) & ~hidden[tau, at]
    return hidden, margin
