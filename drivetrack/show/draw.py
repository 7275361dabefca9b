"""Drawing point tracks: sampling, colours, markers and trails, depth panels, composed pictures.

Images uint8 RGB ``[H, W, 3]``, pixels ``(x, y)`` = (column, row) with pixel ``i`` covering
``[i, i+1)`` (a point at ``x`` is drawn at the integer pixel ``floor(x)``).
"""
from __future__ import annotations

import numpy as np

from drivetrack.evaluation.clips import Clip
from drivetrack.show.clips import SPLITS, scene_frames
from drivetrack.show.errors import WRONG_FLAG_COLOR, ErrorView, error_colors, error_legend

__all__ = ["sample_tracks", "track_colors", "draw_tracks", "clip_depth", "depth_panel", "render_frames",
           "contact_sheet", "sheet_frames", "render_sheet", "render_video"]


# ---- what to draw ---------------------------------------------------------------------------

def sample_tracks(clip: Clip, k: int, frames: np.ndarray | None = None, seed: int = 0) -> np.ndarray:
    """int64 [<=K] indices of tracks to draw, spread over the object.

    Candidates are the tracks visible in at least one of ``frames``; among them, farthest-point
    sampling on each track's position at its first visible frame (from a seeded random start)
    spreads the dots over the whole object instead of clustering where the LiDAR is densest.
    """
    if k < 1:
        raise ValueError(f"--points must be >= 1, got {k}")
    frames = np.arange(clip.num_frames) if frames is None else np.asarray(frames)
    vis = clip.visibles[:, frames]
    candidates = np.flatnonzero(vis.any(axis=1))
    if candidates.size <= k:
        return candidates
    first = np.argmax(vis[candidates], axis=1)
    xy = clip.tracks[candidates, frames[first]].astype(np.float64)           # [C, 2], finite (visible)
    rng = np.random.default_rng(seed)
    chosen = [int(rng.integers(candidates.size))]
    dist = np.sum((xy - xy[chosen[0]]) ** 2, axis=1)
    for _ in range(k - 1):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.sum((xy - xy[nxt]) ** 2, axis=1))
    return candidates[np.array(chosen)]


def track_colors(k: int) -> np.ndarray:
    """uint8 [K, 3] RGB, saturated hues spaced by the golden angle (neighbours differ)."""
    import cv2

    hue = (np.arange(k) * 0.618033988749895 % 1.0 * 180).astype(np.uint8)
    hsv = np.stack([hue, np.full(k, 230, np.uint8), np.full(k, 255, np.uint8)], axis=-1)[None]
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0]


def _sizes(width: int) -> tuple[int, int, int]:
    """(dot radius, cross size, line thickness) for an image ``width`` pixels wide."""
    radius = max(3, int(round(width / 240)))
    return radius, 2 * radius + 3, max(1, radius // 3)


def draw_tracks(image: np.ndarray, xy: np.ndarray, visible: np.ndarray, t: int,
                colors: np.ndarray, trail: int = 8, rings: np.ndarray | None = None) -> np.ndarray:
    """Draw tracks at frame ``t`` onto a copy of ``image``.

    Args:
        image: uint8 [H, W, 3] RGB.
        xy: float [K, T, 2] pixels (x, y), NaN = nothing to draw.
        visible: bool [K, T].
        t: index on the T axis of the frame shown.
        colors: uint8 [K, 3] RGB per track, or uint8 [K, T, 3] per track and frame.
        trail: how many previous frames the trail covers (0 = none).
        rings: optional bool [K] (at frame t): draw a ring around these points.
    Returns:
        uint8 [H, W, 3]: visible = filled dot with a dark outline, occluded = tilted cross, trail
        = polyline through the positions of frames ``t - trail .. t`` that lie in or near the image.

    One OpenCV call per drawn primitive (K of them, K ~ tens): drawing has no vectorised form.
    """
    import cv2

    out = np.ascontiguousarray(image).copy()
    h, w = out.shape[:2]
    radius, cross, thick = _sizes(w)
    colors = np.asarray(colors)
    per_frame = colors.ndim == 3
    lo = max(0, t - trail)
    margin = 0.05 * max(w, h)
    shift = 4                                                    # sub-pixel precision of polylines
    for i in range(xy.shape[0]):
        color = tuple(int(c) for c in (colors[i, t] if per_frame else colors[i]))
        seg = xy[i, lo:t + 1]
        # Trails join positions near the image only: off-image positions (a point that left the
        # view, or behind the camera holding its last valid position) would draw long streaks.
        with np.errstate(invalid="ignore"):
            ok = (np.all(np.isfinite(seg), axis=1) & (seg[:, 0] >= -margin) & (seg[:, 0] < w + margin)
                  & (seg[:, 1] >= -margin) & (seg[:, 1] < h + margin))
        if trail > 0 and ok.sum() >= 2:
            # split the trail where positions are missing, draw each finite run
            runs = np.split(np.arange(seg.shape[0]), np.flatnonzero(np.diff(ok.astype(np.int8)) != 0) + 1)
            for run in runs:
                if run.size >= 2 and ok[run[0]]:
                    pts = np.round((seg[run] + 0.0) * (1 << shift)).astype(np.int32)
                    cv2.polylines(out, [pts.reshape(-1, 1, 2)], False, color, thick, cv2.LINE_AA, shift)
        p = xy[i, t]
        if not np.all(np.isfinite(p)):
            continue
        c = (int(np.floor(p[0])), int(np.floor(p[1])))
        if not (-cross <= c[0] < w + cross and -cross <= c[1] < h + cross):
            continue
        if visible[i, t]:
            cv2.circle(out, c, radius + 1, (20, 20, 20), -1, cv2.LINE_AA)
            cv2.circle(out, c, radius, color, -1, cv2.LINE_AA)
        else:
            cv2.drawMarker(out, c, (20, 20, 20), cv2.MARKER_TILTED_CROSS, cross, thick + 2, cv2.LINE_AA)
            cv2.drawMarker(out, c, color, cv2.MARKER_TILTED_CROSS, cross, thick + 1, cv2.LINE_AA)
        if rings is not None and rings[i]:
            cv2.circle(out, c, radius + 4, WRONG_FLAG_COLOR, max(1, thick), cv2.LINE_AA)
    return out


def _label(image: np.ndarray, text: str) -> np.ndarray:
    """Write ``text`` in a dark band at the top-left of ``image`` (in place) and return it."""
    import cv2

    scale = max(0.4, image.shape[1] / 1200)
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    cv2.rectangle(image, (0, 0), (min(image.shape[1], tw + 8), th + base + 6), (0, 0, 0), -1)
    cv2.putText(image, text, (4, th + 3), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return image



def clip_depth(clip: Clip, source: str, frames: np.ndarray, completer: str = "nearest",
               storage_options: dict | None = None) -> np.ndarray:
    """float32 [F, H, W] completed depth (metres, z-depth, 0 = unknown) of clip ``frames``.

    Recomputed from the source segment the way the track stage computes its occlusion maps
    (the default TrackConfig: every lidar, first returns, moved to the image pose, then the
    ``completer``); releases do not store depth stacks.
    """
    from drivetrack.tracks.config import TrackConfig
    from drivetrack.depth.stage import DepthJob, complete_depth, sparse_depth
    from drivetrack.waymo.reader import load_scene
    from drivetrack.waymo.schema import CameraName

    split = clip.split if clip.split in SPLITS else "training"
    camera = int(CameraName[clip.camera])
    scene = load_scene(source, split, clip.segment, cameras=(camera,), lasers=None, returns=(1, 2),
                       with_images=False, storage_options=storage_options)
    seg_frames = scene_frames(scene.timestamps_micros, clip.timestamps_micros,
                               f"{clip.url} vs source {source} segment {clip.segment}")[frames]
    config = TrackConfig(depth_completer=completer)
    sparse = sparse_depth(scene, config, DepthJob(camera, seg_frames))
    return complete_depth(sparse, config)


def depth_panel(depth: np.ndarray, near_m: float = 2.0) -> np.ndarray:
    """uint8 [H, W, 3] RGB picture of a depth map: ``near_m / depth`` in TURBO (red = ``near_m`` or
    nearer, blue = far), black = unknown."""
    import cv2

    depth = np.asarray(depth, dtype=np.float32)
    known = depth > 0
    inv = np.where(known, near_m / np.maximum(depth, near_m), 0.0)        # 1 at <= near_m, -> 0 far
    scaled = np.clip(inv * 255, 0, 255).astype(np.uint8)
    rgb = cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO)[..., ::-1].copy()
    rgb[~known] = 0
    return rgb



# ---- composing pictures ----------------------------------------------------------------------

def render_frames(clip: Clip, track_index: np.ndarray, frames: np.ndarray, *, trail: int = 8,
                  depth: np.ndarray | None = None, errors: ErrorView | None = None,
                  label: bool = True, legend: bool = True) -> list[np.ndarray]:
    """One uint8 [H, W or 2W, 3] RGB picture per clip frame in ``frames``.

    ``depth`` (float32 [F, H, W], aligned with ``frames``) adds a depth panel on the right, with
    the same markers. ``errors`` colours each point by its error bin instead of its track colour
    and rings points whose occlusion flag is wrong (with a legend strip below each picture when
    ``legend``). The depth colour scale is fixed over the whole stack (nearest 2% of known
    depths = red), so colours compare between frames.
    """
    frames = np.asarray(frames, dtype=np.int64)
    if depth is not None and depth.shape[0] != frames.size:
        raise ValueError(f"depth has {depth.shape[0]} maps for {frames.size} frames")
    track_index = np.asarray(track_index, dtype=np.int64)
    xy = clip.tracks[track_index]
    vis = clip.visibles[track_index]
    colors = track_colors(track_index.size) if errors is None else error_colors(errors.error_px[track_index])
    near_m = 2.0
    if depth is not None and np.any(depth > 0):
        near_m = float(max(np.percentile(depth[depth > 0], 2), 0.5))
    out = []
    for i, t in enumerate(frames.tolist()):
        rings = None if errors is None else errors.wrong_flag[track_index, t]
        image = draw_tracks(clip.video[t], xy, vis, t, colors, trail=trail, rings=rings)
        if label:
            _label(image, f"{clip.camera} {clip.object_id}  frame {t}/{clip.num_frames - 1}")
        if depth is not None:
            panel = draw_tracks(depth_panel(depth[i], near_m), xy, vis, t, colors, trail=trail, rings=rings)
            if label:
                _label(panel, "completed depth (red = near, black = unknown)")
            image = np.concatenate([image, panel], axis=1)
        out.append(image)
    if errors is not None and legend:
        strip = error_legend(out[0].shape[1])
        out = [np.concatenate([im, strip], axis=0) for im in out]
    return out


def contact_sheet(images: list[np.ndarray], columns: int = 3, gap: int = 4) -> np.ndarray:
    """uint8 [rows*h + gaps, cols*w + gaps, 3]: ``images`` (same shape) on a grid, dark gaps."""
    if not images:
        raise ValueError("contact_sheet needs at least one image")
    h, w = images[0].shape[:2]
    columns = max(1, min(columns, len(images)))
    rows = -(-len(images) // columns)
    sheet = np.full((rows * h + (rows - 1) * gap, columns * w + (columns - 1) * gap, 3), 16, np.uint8)
    for i, im in enumerate(images):
        r, c = divmod(i, columns)
        sheet[r * (h + gap):r * (h + gap) + h, c * (w + gap):c * (w + gap) + w] = im
    return sheet


def sheet_frames(frames: np.ndarray, count: int) -> np.ndarray:
    """``count`` frames evenly spread over ``frames`` (first and last included)."""
    frames = np.asarray(frames)
    if count >= frames.size:
        return frames
    return frames[np.unique(np.round(np.linspace(0, frames.size - 1, count)).astype(np.int64))]


def render_sheet(clip: Clip, track_index: np.ndarray, frames: np.ndarray | None = None, count: int = 6,
                 columns: int | None = None, trail: int = 8, depth: np.ndarray | None = None,
                 errors: ErrorView | None = None) -> np.ndarray:
    """Contact sheet of ``count`` frames spread over ``frames`` (default the whole clip).

    ``depth``, if given, holds one map per frame of ``frames`` (not only the chosen ones)."""
    frames = np.arange(clip.num_frames) if frames is None else np.asarray(frames)
    chosen = sheet_frames(frames, count)
    sub = None if depth is None else depth[np.searchsorted(frames, chosen)]
    images = render_frames(clip, track_index, chosen, trail=trail, depth=sub, errors=errors, legend=False)
    sheet = contact_sheet(images, columns or (2 if depth is not None else 3))
    if errors is not None:
        sheet = np.concatenate([sheet, error_legend(sheet.shape[1])], axis=0)
    return sheet


def render_video(clip: Clip, track_index: np.ndarray, frames: np.ndarray | None = None, trail: int = 8,
                 depth: np.ndarray | None = None, errors: ErrorView | None = None) -> list[np.ndarray]:
    """Every frame of ``frames`` rendered, for :func:`write_video`."""
    frames = np.arange(clip.num_frames) if frames is None else np.asarray(frames)
    return render_frames(clip, track_index, frames, trail=trail, depth=depth, errors=errors)

