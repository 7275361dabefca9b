"""Writing pictures and clips, and the release previews of an annotation output folder."""
from __future__ import annotations

import posixpath

import numpy as np

from drivetrack.show.clips import clip_num_tracks, clip_stem_of, find_clips, fs_of, load_clip, parse_clip_name
from drivetrack.show.draw import render_sheet, render_video, sample_tracks

__all__ = ["write_image", "write_video", "fit_width", "write_previews"]


def write_image(url: str, image: np.ndarray) -> str:
    """Write uint8 [H, W, 3] RGB as PNG (or JPEG by extension) at ``url``; returns ``url``."""
    import cv2

    ext = posixpath.splitext(str(url))[1].lower()
    if ext not in (".png", ".jpg", ".jpeg"):
        raise ValueError(f"{url}: image output must end with .png, .jpg or .jpeg")
    ok, data = cv2.imencode(ext, np.ascontiguousarray(image[..., ::-1]))
    if not ok:
        raise OSError(f"{url}: OpenCV could not encode the image ({image.shape})")
    from drivetrack.storage import write_bytes

    return write_bytes(url, data.tobytes())


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



def _split_of(url: str) -> str:
    return posixpath.basename(posixpath.dirname(fs_of(url)[1]))


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
            per_camera.setdefault(parse_clip_name(clip_stem_of(url))[1], []).append(url)
        picked: list[str] = []
        queues = sorted(per_camera.values(), key=lambda q: (-clip_num_tracks(q[0]), q[0]))
        while len(picked) < per_split and any(queues):
            for q in queues:
                if q and len(picked) < per_split:
                    picked.append(q.pop(0))
        for i, url in enumerate(picked):
            clip = load_clip(url)
            stem = clip_stem_of(url)
            index = sample_tracks(clip, points, seed=seed)
            base = f"{root}/previews/{split}/{stem}"
            sheet = render_sheet(clip, index, count=sheet_count, columns=2, trail=trail)
            written.append(write_image(f"{base}.png", fit_width(sheet, sheet_width)))
            if i == 0:
                video_url = f"{base}.mp4"
                video = [fit_width(im, video_width) for im in render_video(clip, index, trail=trail)]
        written.append(write_video(video_url, video, fps=fps))
    return written
