"""Look at point tracks: overlays, contact sheets, clips, error views and release previews.

What is drawn (docs/looking-at-a-release.md shows the pictures):

- K sampled tracks of one clip over its frames, one colour per track: a filled dot where the
  track is visible, a tilted cross where it is occluded (as the DriveTrack paper's figures), a
  polyline trail of its last ``trail`` frames through the positions in or near the image (a
  point that left the view holds its last valid position, which is not drawn as a trail).
- Optionally a depth panel beside each frame: the completed depth map of that frame, recomputed
  from the source segment (releases do not store depth), inverse depth in the TURBO colour map,
  black = unknown.
- Optionally, on synthetic data, an error view: each point coloured by its pixel distance to the
  exact ground truth (TAP-Vid thresholds 1, 2, 4, 8 px), and a ring around points whose
  occlusion flag disagrees with the truth.

Conventions are those of docs/architecture.md: images uint8 RGB ``[H, W, 3]``, pixels ``(x, y)``
= (column, row) with pixel ``i`` covering ``[i, i+1)`` (so a point at ``x`` is drawn at the
integer pixel ``floor(x)``). All storage goes through fsspec.

    from drivetrack.show import find_clips, load_clip, render_sheet, render_video, write_previews
    clip = load_clip(find_clips("OUT")[0])
    sheet = render_sheet(clip, sample_tracks(clip, 24))     # uint8 [H', W', 3]
"""
from __future__ import annotations

import io
import posixpath
import re
import zipfile
from dataclasses import dataclass

import fsspec
import numpy as np

__all__ = ["Clip", "ErrorView", "CLIP_NAME", "find_clips", "parse_clip_name", "clip_num_tracks",
           "select_clip", "load_clip", "parse_frames", "sample_tracks", "track_colors",
           "draw_tracks", "depth_panel", "clip_depth", "error_view", "render_frames",
           "contact_sheet", "render_sheet", "render_video", "write_image", "write_video",
           "write_previews", "fit_width", "SPLITS", "ERROR_BINS_PX"]

#: ``waymo_{segment}_{CAMERA}_{object_id}.npz``; camera names tried longest first.
CLIP_NAME = re.compile(r"^waymo_(?P<segment>.+?)_(?P<camera>FRONT_LEFT|FRONT_RIGHT|SIDE_LEFT|SIDE_RIGHT|FRONT)"
                       r"_(?P<object_id>[A-Za-z0-9_.\-]+)\.npz$")
SPLITS = ("training", "validation", "testing")
#: Folders whose ``waymo_*.npz`` are not DriveTrack clips (TAPVid-3D copies, release internals).
_NOT_CLIP_DIRS = {"tapvid3d", "_staging", "_txn", "previews"}
#: Upper bounds (px) of the error colour bins; the last bin is everything above.
ERROR_BINS_PX = (1.0, 2.0, 4.0, 8.0)
#: RGB colour per error bin: < 1, < 2, < 4, < 8, >= 8 px.
ERROR_COLORS = ((40, 200, 60), (160, 220, 40), (250, 220, 30), (250, 140, 20), (230, 30, 30))
WRONG_FLAG_COLOR = (255, 0, 255)


# ---- finding and reading clips -------------------------------------------------------------

def parse_clip_name(url: str) -> tuple[str, str, str]:
    """``(segment, CAMERA, object_id)`` from a clip file name; ValueError naming the file if not one."""
    name = posixpath.basename(str(url))
    m = CLIP_NAME.match(name)
    if not m:
        raise ValueError(f"{url}: not a DriveTrack clip file name (expected "
                         f"waymo_{{segment}}_{{CAMERA}}_{{object_id}}.npz)")
    return m["segment"], m["camera"], m["object_id"]


def _fs(url: str):
    return fsspec.core.url_to_fs(str(url))


def _join(fs, path: str) -> str:
    """The URL of ``path`` on ``fs`` (plain path for the local file system)."""
    protocol = fs.protocol if isinstance(fs.protocol, str) else fs.protocol[0]
    return path if protocol in ("file", "local") else f"{protocol}://{path}"


def find_clips(root: str) -> list[str]:
    """Sorted URLs of every DriveTrack clip (``**/waymo_*.npz``) under ``root``.

    Works on an annotation output folder and on a release version folder, whatever the split
    folder layout (``{split}/`` or ``tracks/{split}/``); TAPVid-3D copies (a ``tapvid3d`` folder)
    and release internals (``_staging``, ``_txn``) are left out.
    """
    fs, path = _fs(root)
    if not fs.isdir(path):
        raise FileNotFoundError(f"{root}: not a folder (pass a clip .npz file or a folder holding clips)")
    found = fs.glob(posixpath.join(path.rstrip("/"), "**", "waymo_*.npz"))
    base = path.rstrip("/")
    out = []
    for p in found:
        rel = p[len(base):].lstrip("/") if p.startswith(base) else p
        if set(rel.split("/")[:-1]) & _NOT_CLIP_DIRS or not CLIP_NAME.match(posixpath.basename(p)):
            continue
        out.append(_join(fs, p))
    return sorted(out)


def _npy_header(fs, path: str, key: str) -> tuple[tuple[int, ...], np.dtype]:
    with fs.open(path, "rb") as f, zipfile.ZipFile(f) as zf:
        try:
            member = zf.open(f"{key}.npy")
        except KeyError:
            raise KeyError(f"{path}: no array {key!r} in the file (has {sorted(n[:-4] for n in zf.namelist())})") from None
        with member:
            version = np.lib.format.read_magic(member)
            shape, _, dtype = (np.lib.format.read_array_header_1_0(member) if version == (1, 0)
                               else np.lib.format.read_array_header_2_0(member))
    return tuple(int(s) for s in shape), dtype


def clip_num_tracks(url: str) -> int:
    """N of a clip, read from the ``tracks`` array header only (no data is decompressed)."""
    fs, path = _fs(url)
    return _npy_header(fs, path, "tracks")[0][0]


def select_clip(source: str, object_id: str | None = None, camera: str | None = None) -> str:
    """The clip to show: ``source`` itself if it is a file, else the clip under the folder
    ``source`` matching ``object_id`` / ``camera`` with the most tracks (ties: first by name)."""
    fs, path = _fs(source)
    if fs.isfile(path):
        return str(source)
    clips = find_clips(source)
    if not clips:
        raise FileNotFoundError(f"{source}: no DriveTrack clip (waymo_*.npz) under this folder")
    keep = []
    for url in clips:
        _, cam, obj = parse_clip_name(url)
        if (object_id is None or obj == object_id) and (camera is None or cam == camera.upper()):
            keep.append(url)
    if not keep:
        have = sorted({f"{parse_clip_name(u)[2]} ({parse_clip_name(u)[1]})" for u in clips})
        raise LookupError(f"{source}: no clip for object {object_id!r} camera {camera!r}; "
                          f"objects here: {', '.join(have[:20])}{' ...' if len(have) > 20 else ''}")
    counts = [clip_num_tracks(u) for u in keep]
    return keep[int(np.argmax(counts))]


@dataclass
class Clip:
    """One DriveTrack clip as read from its file.

    Attributes:
        url: where it was read from.
        split, segment, camera, object_id: identity (split = the clip file's folder name).
        video: uint8 [T, H, W, 3] RGB.
        tracks: float32 [N, T, 2] pixels (x, y); NaN only where not visible.
        visibles: bool [N, T].
        timestamps_micros: int64 [T] (None if the file has none).
        query_frames: int32 [N] clip frame of each track's LiDAR return (None if absent).
        lidar_sources: int32 [N, 4] (laser, return, row, column) of that return (None if absent).
    """
    url: str
    split: str
    segment: str
    camera: str
    object_id: str
    video: np.ndarray
    tracks: np.ndarray
    visibles: np.ndarray
    timestamps_micros: np.ndarray | None = None
    query_frames: np.ndarray | None = None
    lidar_sources: np.ndarray | None = None

    @property
    def num_frames(self) -> int:
        return int(self.video.shape[0])

    @property
    def num_tracks(self) -> int:
        return int(self.tracks.shape[0])

    @property
    def title(self) -> str:
        return f"{self.segment} {self.camera} {self.object_id}"


def load_clip(url: str) -> Clip:
    """Read a DriveTrack clip; errors name the file and the offending key, shape or dtype."""
    segment, camera, object_id = parse_clip_name(url)
    fs, path = _fs(url)
    try:
        with fs.open(path, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        raise FileNotFoundError(f"{url}: no such clip file") from None
    try:
        z = np.load(io.BytesIO(data), allow_pickle=False)
    except (ValueError, zipfile.BadZipFile, OSError) as error:
        raise ValueError(f"{url}: not a readable .npz file ({error})") from error
    with z:
        missing = [k for k in ("video", "tracks", "visibles") if k not in z.files]
        if missing:
            raise KeyError(f"{url}: missing array(s) {missing}; a DriveTrack clip has video, tracks, visibles")
        arrays = {k: z[k] for k in z.files}
    video, tracks, visibles = arrays["video"], arrays["tracks"], arrays["visibles"]
    if video.dtype != np.uint8 or video.ndim != 4 or video.shape[-1] != 3:
        raise ValueError(f"{url}: video must be uint8 [T, H, W, 3], found {video.dtype} {video.shape}")
    t = video.shape[0]
    if tracks.ndim != 3 or tracks.shape[1:] != (t, 2):
        raise ValueError(f"{url}: tracks must be [N, {t}, 2] (T from video), found {tracks.shape}")
    if visibles.dtype != bool or visibles.shape != tracks.shape[:2]:
        raise ValueError(f"{url}: visibles must be bool {tracks.shape[:2]}, found {visibles.dtype} {visibles.shape}")
    split = posixpath.basename(posixpath.dirname(path))
    return Clip(url=str(url), split=split, segment=segment, camera=camera, object_id=object_id,
                video=video, tracks=tracks.astype(np.float32, copy=False), visibles=visibles,
                timestamps_micros=arrays.get("timestamps_micros"), query_frames=arrays.get("query_frames"),
                lidar_sources=arrays.get("lidar_sources"))


def parse_frames(spec: str | None, num_frames: int) -> np.ndarray:
    """int64 [F] clip frames of a Python-style slice ``"A:B"`` (or ``"A:B:S"``, or one index ``"A"``)."""
    if spec is None or spec.strip() in ("", ":"):
        return np.arange(num_frames)
    parts = spec.split(":")
    try:
        if len(parts) == 1:
            index = int(parts[0])
            frames = np.arange(num_frames)[[index]]
        elif len(parts) <= 3:
            bounds = [int(p) if p.strip() else None for p in parts]
            frames = np.arange(num_frames)[slice(*bounds)]
        else:
            raise ValueError("too many ':'")
    except (ValueError, IndexError) as error:
        raise ValueError(f"--frames {spec!r}: expected A:B (clip frames 0..{num_frames - 1}); {error}") from None
    if frames.size == 0:
        raise ValueError(f"--frames {spec!r} selects no frame of a {num_frames}-frame clip")
    return frames


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


# ---- depth panel -----------------------------------------------------------------------------

def _scene_frames(timestamps_all: np.ndarray, timestamps_clip: np.ndarray | None, where: str) -> np.ndarray:
    """int64 [T] segment frame index of each clip frame, matched on timestamps."""
    if timestamps_clip is None:
        raise ValueError(f"{where}: the clip has no timestamps_micros; cannot match its frames to the source")
    idx = np.clip(np.searchsorted(timestamps_all, timestamps_clip), 0, max(len(timestamps_all) - 1, 0))
    bad = timestamps_all[idx] != timestamps_clip if len(timestamps_all) else np.ones(len(timestamps_clip), bool)
    if np.any(bad):
        raise ValueError(f"{where}: clip timestamp(s) {timestamps_clip[bad][:3].tolist()} not found among the "
                         f"source's {len(timestamps_all)} frame timestamps (wrong --source or segment?)")
    return idx.astype(np.int64)


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
    seg_frames = _scene_frames(scene.timestamps_micros, clip.timestamps_micros,
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


# ---- error view (synthetic ground truth) -----------------------------------------------------

@dataclass
class ErrorView:
    """A clip's tracks compared with the exact synthetic ground truth.

    Attributes:
        matched: bool [N], the track's LiDAR return was found in the ground truth.
        gt_tracks: float32 [N, T, 2] true pixels (NaN where unmatched or not projectable).
        gt_visibles: bool [N, T] true visibility (False where unmatched).
        error_px: float32 [N, T] |tracks - gt_tracks| (NaN where either is not finite).
        wrong_flag: bool [N, T] matched and ``visibles != gt_visibles``.
    """
    matched: np.ndarray
    gt_tracks: np.ndarray
    gt_visibles: np.ndarray
    error_px: np.ndarray
    wrong_flag: np.ndarray

    def summary(self, frames: np.ndarray | None = None) -> dict[str, float]:
        """Median / p90 pixel error where both say visible, and the wrong-flag rate (matched tracks)."""
        sel = slice(None) if frames is None else np.asarray(frames)
        m = self.matched
        err = self.error_px[m][:, sel]
        both = (self.gt_visibles[m] & ~self.wrong_flag[m])[:, sel] & np.isfinite(err)
        vals = err[both]
        return {"matched_fraction": float(m.mean()) if m.size else float("nan"),
                "median_error_px": float(np.median(vals)) if vals.size else float("nan"),
                "p90_error_px": float(np.percentile(vals, 90)) if vals.size else float("nan"),
                "wrong_flag_fraction": float(self.wrong_flag[m][:, sel].mean()) if m.any() else float("nan")}


def error_view(clip: Clip, truth_root: str, split: str | None = None) -> ErrorView:
    """Match the clip's tracks to the synthetic ground truth under ``truth_root``.

    A track is matched by its LiDAR return: (segment frame of ``query_frames``, laser, return,
    range-image row, column) = ``lidar_sources`` against ``lidar_hits.npz``; clip frames are
    matched to segment frames on ``timestamps_micros``.
    """
    from drivetrack.synth.ground_truth import load_ground_truth

    split = split or (clip.split if clip.split in SPLITS else None)
    if split is None:
        raise ValueError(f"{clip.url}: cannot tell the split from the folder {clip.split!r}; pass --split")
    if clip.lidar_sources is None or clip.query_frames is None:
        raise ValueError(f"{clip.url}: the error view needs lidar_sources and query_frames in the clip")
    truth = load_ground_truth(truth_root, split, clip.segment)
    seg_frames = _scene_frames(truth.objects["timestamps_micros"], clip.timestamps_micros,
                               f"{clip.url} vs ground truth {truth.url}")
    h = truth.hits
    num_frames_gt = int(truth.objects["timestamps_micros"].shape[0])

    def key(frame, laser, ret, row, col):
        # one int64 per return: frame, laser, return, row, column packed in disjoint bit fields
        return ((np.asarray(frame, np.int64) << 44) | (np.asarray(laser, np.int64) << 40)
                | (np.asarray(ret, np.int64) << 36) | (np.asarray(row, np.int64) << 18) | np.asarray(col, np.int64))

    gt_keys = key(h["frame"], h["laser"], h["return_index"], h["row"], h["col"])
    order = np.argsort(gt_keys, kind="stable")
    src = clip.lidar_sources.astype(np.int64)
    ours = key(seg_frames[clip.query_frames.astype(np.int64)], src[:, 0], src[:, 1], src[:, 2], src[:, 3])
    pos = np.clip(np.searchsorted(gt_keys[order], ours), 0, max(gt_keys.size - 1, 0))
    matched = (gt_keys[order][pos] == ours) if gt_keys.size else np.zeros(ours.shape, bool)
    hit = order[pos]
    axis = truth.camera_axis(clip.camera)
    n, t = clip.visibles.shape
    gt_tracks = np.full((n, t, 2), np.nan, np.float32)
    gt_vis = np.zeros((n, t), bool)
    if np.any(seg_frames >= num_frames_gt):
        raise ValueError(f"{clip.url}: clip frames beyond the ground truth's {num_frames_gt} frames")
    gt_tracks[matched] = h["pixels"][hit[matched]][:, axis][:, seg_frames]
    gt_vis[matched] = h["visible"][hit[matched]][:, axis][:, seg_frames]
    with np.errstate(invalid="ignore"):
        err = np.linalg.norm(clip.tracks.astype(np.float64) - gt_tracks, axis=-1).astype(np.float32)
    wrong = matched[:, None] & (clip.visibles != gt_vis)
    return ErrorView(matched=matched, gt_tracks=gt_tracks, gt_visibles=gt_vis, error_px=err, wrong_flag=wrong)


def error_colors(error_px: np.ndarray) -> np.ndarray:
    """uint8 [..., 3] RGB bin colour of each pixel error (grey where NaN)."""
    err = np.asarray(error_px, np.float64)
    bins = np.digitize(np.nan_to_num(err, nan=0.0), ERROR_BINS_PX)
    out = np.asarray(ERROR_COLORS, np.uint8)[bins]
    out[~np.isfinite(err)] = (150, 150, 150)
    return out


def _error_legend(width: int) -> np.ndarray:
    """uint8 [h, width, 3] legend strip of the error colours."""
    import cv2

    scale = float(np.clip(width / 1400, 0.4, 0.6))
    h = int(round(70 * scale))
    strip = np.full((h, width, 3), 30, np.uint8)
    labels = ["<1 px", "<2 px", "<4 px", "<8 px", ">=8 px", "no truth", "wrong occlusion flag"]
    colors = list(ERROR_COLORS) + [(150, 150, 150), WRONG_FLAG_COLOR]
    x = 6
    for text, color in zip(labels, colors):
        cv2.circle(strip, (x + 6, h // 2), 6, tuple(int(c) for c in color), -1 if text != labels[-1] else 2)
        cv2.putText(strip, text, (x + 16, h // 2 + 5), cv2.FONT_HERSHEY_SIMPLEX, scale, (235, 235, 235), 1, cv2.LINE_AA)
        x += 16 + cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] + 14
    return strip


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
        strip = _error_legend(out[0].shape[1])
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
        sheet = np.concatenate([sheet, _error_legend(sheet.shape[1])], axis=0)
    return sheet


def render_video(clip: Clip, track_index: np.ndarray, frames: np.ndarray | None = None, trail: int = 8,
                 depth: np.ndarray | None = None, errors: ErrorView | None = None) -> list[np.ndarray]:
    """Every frame of ``frames`` rendered, for :func:`write_video`."""
    frames = np.arange(clip.num_frames) if frames is None else np.asarray(frames)
    return render_frames(clip, track_index, frames, trail=trail, depth=depth, errors=errors)


# ---- writing ---------------------------------------------------------------------------------

def write_image(url: str, image: np.ndarray) -> str:
    """Write uint8 [H, W, 3] RGB as PNG (or JPEG by extension) at ``url``; returns ``url``."""
    import cv2

    ext = posixpath.splitext(str(url))[1].lower()
    if ext not in (".png", ".jpg", ".jpeg"):
        raise ValueError(f"{url}: image output must end with .png, .jpg or .jpeg")
    ok, data = cv2.imencode(ext, np.ascontiguousarray(image[..., ::-1]))
    if not ok:
        raise OSError(f"{url}: OpenCV could not encode the image ({image.shape})")
    fs, path = _fs(url)
    parent = posixpath.dirname(path)
    if parent:
        fs.makedirs(parent, exist_ok=True)
    with fs.open(path, "wb") as f:
        f.write(data.tobytes())
    return url


def write_video(url: str, images: list[np.ndarray], fps: float = 10.0) -> str:
    """Write RGB frames as an H.264 MP4 (``.mp4``, yuv420p, plays in browsers) or a ``.gif``.

    MP4 goes through imageio's ffmpeg plugin (imageio-ffmpeg ships its own ffmpeg binary);
    frames are padded to even sizes, which yuv420p needs. Returns ``url``.
    """
    import imageio.v2 as imageio

    ext = posixpath.splitext(str(url))[1].lower()
    if ext not in (".mp4", ".gif"):
        raise ValueError(f"{url}: clip output must end with .mp4 or .gif")
    if not images:
        raise ValueError(f"{url}: no frames to write")
    h, w = images[0].shape[:2]
    ph, pw = h + h % 2, w + w % 2
    frames = [np.pad(im, ((0, ph - h), (0, pw - w), (0, 0))) if (ph, pw) != (h, w) else im for im in images]
    from drivetrack.storage import atomic_local_path

    with atomic_local_path(url, ext) as tmp:
        if ext == ".mp4":
            with imageio.get_writer(tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264",
                                    pixelformat="yuv420p", macro_block_size=2, quality=8,
                                    ffmpeg_log_level="error",
                                    output_params=["-movflags", "+faststart", "-fflags", "+bitexact"]) as writer:
                for frame in frames:
                    writer.append_data(frame)
        else:
            imageio.mimsave(tmp, frames, format="GIF", duration=1.0 / fps, loop=0)
    return url


# ---- release previews ------------------------------------------------------------------------

def _split_of(url: str) -> str:
    return posixpath.basename(posixpath.dirname(_fs(url)[1]))


def fit_width(image: np.ndarray, max_width: int) -> np.ndarray:
    """``image`` shrunk (area interpolation) to at most ``max_width`` pixels wide; never enlarged."""
    import cv2

    h, w = image.shape[:2]
    if w <= max_width:
        return image
    size = (int(max_width), max(1, int(round(h * max_width / w))))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def write_previews(out_dir: str, per_split: int = 3, points: int = 24, sheet_count: int = 4,
                   trail: int = 8, fps: float = 10.0, seed: int = 0, sheet_width: int = 1280,
                   video_width: int = 960) -> list[str]:
    """Write previews of an annotation output folder (before publish); returns the written URLs.

    Per split (the folder holding the clips): contact sheets ``previews/{split}/{stem}.png`` of the
    ``per_split`` clips with the most tracks (cameras taken in turn, so the sheets show several
    cameras), and one short clip ``previews/{split}/{stem}.mp4`` of the split's largest clip.
    The URLs come back in split order, sheets before the clip. A folder with no clip writes
    nothing and returns ``[]``. Full-size Waymo frames (1920 x 1280) are shrunk to
    ``sheet_width`` / ``video_width`` pixels so previews stay small (about 1 MB each).
    """
    if per_split < 1:
        raise ValueError(f"per_split must be >= 1, got {per_split}")
    root = str(out_dir).rstrip("/")
    by_split: dict[str, list[str]] = {}
    for url in find_clips(root):
        by_split.setdefault(_split_of(url), []).append(url)
    written: list[str] = []
    for split in sorted(by_split):
        ranked = sorted(by_split[split], key=lambda u: (-clip_num_tracks(u), u))
        per_camera: dict[str, list[str]] = {}
        for url in ranked:
            per_camera.setdefault(parse_clip_name(url)[1], []).append(url)
        picked: list[str] = []
        queues = sorted(per_camera.values(), key=lambda q: (-clip_num_tracks(q[0]), q[0]))
        while len(picked) < per_split and any(queues):
            for q in queues:
                if q and len(picked) < per_split:
                    picked.append(q.pop(0))
        for i, url in enumerate(picked):
            clip = load_clip(url)
            stem = posixpath.splitext(posixpath.basename(url))[0]
            index = sample_tracks(clip, points, seed=seed)
            base = f"{root}/previews/{split}/{stem}"
            sheet = render_sheet(clip, index, count=sheet_count, columns=2, trail=trail)
            written.append(write_image(f"{base}.png", fit_width(sheet, sheet_width)))
            if i == 0:
                video_url = f"{base}.mp4"
                video = [fit_width(im, video_width) for im in render_video(clip, index, trail=trail)]
        written.append(write_video(video_url, video, fps=fps))
    return written
