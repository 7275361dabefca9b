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
from drivetrack.evaluation.clips import Clip
from drivetrack.outputs import parse_clip_name
from drivetrack.show.clips import SPLITS, clip_num_tracks, find_clips, load_clip, parse_frames, select_clip
from drivetrack.show.draw import (clip_depth, contact_sheet, depth_panel, draw_tracks, render_frames, render_sheet,
                                  render_video, sample_tracks, sheet_frames, track_colors)
from drivetrack.show.errors import ERROR_BINS_PX, ERROR_COLORS, ErrorView, error_colors, error_view
from drivetrack.show.previews import fit_width, write_image, write_previews, write_video

__all__ = ["Clip", "ErrorView", "find_clips", "parse_clip_name", "clip_num_tracks", "select_clip", "load_clip",
           "parse_frames", "sample_tracks", "track_colors", "draw_tracks", "depth_panel", "clip_depth", "error_view",
           "error_colors", "render_frames", "contact_sheet", "sheet_frames", "render_sheet", "render_video",
           "write_image", "write_video", "write_previews", "fit_width", "SPLITS", "ERROR_BINS_PX", "ERROR_COLORS"]
