"""drivetrack show: finding and reading clips, what is drawn where, sheets, MP4s, the error view,
the depth panel and release previews, on the session's small synthetic annotation."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from drivetrack import show
from drivetrack.cli import main


@pytest.fixture(scope="module")
def clips(annotated_output) -> list[str]:
    return show.find_clips(annotated_output)


@pytest.fixture(scope="module")
def clip(annotated_output) -> show.Clip:
    return show.load_clip(show.select_clip(annotated_output))


# ---- finding and reading ---------------------------------------------------------------------

def test_find_clips_skips_tapvid3d_copies_and_matches_the_stats(annotated_output, clips):
    import pandas as pd

    assert clips and all("tapvid3d" not in c.split("/")[:-1] for c in clips)
    objects = pd.read_parquet(f"{annotated_output}/stats/objects.parquet")
    assert len(clips) == len(objects)
    stems = {show.clips.clip_stem_of(c) for c in clips}
    assert stems == {f"waymo_{s}_{c}_{o}" for s, c, o in zip(objects["segment"], objects["camera"], objects["object_id"])}
    assert {c.split("#")[0].split(f"{annotated_output}/", 1)[1] for c in clips} == set(objects["file"])


def test_parse_clip_name_handles_underscores_and_two_word_cameras():
    assert show.parse_clip_name("x/waymo_123_4_FRONT_RIGHT_C_Pt-x.npz") == ("123_4", "FRONT_RIGHT", "C_Pt-x")
    assert show.parse_clip_name("waymo_drivetrack_synth_s7_0000_FRONT_-LjG_.npz") == (
        "drivetrack_synth_s7_0000", "FRONT", "-LjG_")
    with pytest.raises(ValueError, match="notaclip.npz"):
        show.parse_clip_name("/a/notaclip.npz")


def test_select_clip_takes_the_largest_and_filters_by_object(annotated_output, clips):
    counts = {c: show.clip_num_tracks(c) for c in clips}
    assert show.select_clip(annotated_output) == max(clips, key=lambda c: (counts[c], -clips.index(c)))
    some = clips[-1]
    _, camera, object_id = show.parse_clip_name(show.clips.clip_stem_of(some))
    assert show.select_clip(annotated_output, object_id, camera) == some
    with pytest.raises(LookupError, match="no clip for object 'nope'"):
        show.select_clip(annotated_output, "nope")


def test_load_clip_reads_the_arrays_and_names_bad_files(clip, tmp_path):
    assert clip.video.dtype == np.uint8 and clip.tracks.shape[1:] == (clip.num_frames, 2)
    assert clip.visibles.shape == clip.tracks.shape[:2] and clip.split == "training"
    bad = tmp_path / "waymo_seg_FRONT_obj.npz"
    np.savez(bad, video=clip.video[:2], tracks=clip.tracks[:3, :2])
    with pytest.raises(KeyError, match=r"waymo_seg_FRONT_obj\.npz.*visibles"):
        show.load_clip(str(bad))
    np.savez(bad, video=clip.video[:2], tracks=clip.tracks[:3, :3], visibles=clip.visibles[:3, :3])
    with pytest.raises(ValueError, match=r"waymo_seg_FRONT_obj\.npz: tracks must be \[N, 2, 2\]"):
        show.load_clip(str(bad))


def test_parse_frames():
    assert show.parse_frames("2:5", 10).tolist() == [2, 3, 4]
    assert show.parse_frames("-2:", 10).tolist() == [8, 9]
    assert show.parse_frames(None, 3).tolist() == [0, 1, 2]
    assert show.parse_frames("0:10:4", 10).tolist() == [0, 4, 8]
    with pytest.raises(ValueError, match="selects no frame"):
        show.parse_frames("5:5", 10)
    with pytest.raises(ValueError, match="'a:b'"):
        show.parse_frames("a:b", 10)


def test_sample_tracks_is_seeded_visible_and_spread(clip):
    frames = np.arange(3, 9)
    a = show.sample_tracks(clip, 16, frames, seed=1)
    assert a.size == 16 and np.unique(a).size == 16
    assert np.all(clip.visibles[a][:, frames].any(axis=1))
    assert np.array_equal(a, show.sample_tracks(clip, 16, frames, seed=1))
    # farthest-point sampling spreads: the closest pair is farther apart than for random picks
    vis = clip.visibles[:, frames]
    cand = np.flatnonzero(vis.any(axis=1))

    def min_gap(idx):
        xy = clip.tracks[idx, frames[np.argmax(vis[idx], axis=1)]]
        d = np.linalg.norm(xy[:, None] - xy[None], axis=-1) + np.eye(len(idx)) * 1e9
        return d.min()

    rng = np.random.default_rng(0)
    random_gaps = [min_gap(rng.choice(cand, 16, replace=False)) for _ in range(20)]
    assert min_gap(a) > np.median(random_gaps)
    with pytest.raises(ValueError, match="--points"):
        show.sample_tracks(clip, 0)


# ---- drawing ---------------------------------------------------------------------------------

def test_draw_tracks_dots_crosses_trails_and_nothing_for_nan():
    image = np.zeros((60, 80, 3), np.uint8)
    xy = np.array([[[10.0, 10.0], [20.7, 30.2]],        # visible at t=1 -> dot at (20, 30)
                   [[50.0, 40.0], [50.5, 40.5]],        # occluded at t=1 -> cross at (50, 40)
                   [[np.nan, np.nan], [np.nan, np.nan]]], np.float32)
    visible = np.array([[True, True], [False, False], [False, False]])
    colors = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], np.uint8)
    out = show.draw_tracks(image, xy, visible, 1, colors, trail=1)
    assert tuple(out[30, 20]) == (255, 0, 0)                              # dot centre, track colour
    assert out[30, 20 + 2, 0] == 255 and out[30 + 2, 20, 0] == 255        # filled disc (radius 3)
    assert out[20, 15, 0] > 100                                           # trail from (10,10) to (20,30)
    g = out[..., 1]
    assert g[40, 50] == 255 and g[42, 52] > 100 and g[38, 48] > 100       # cross: centre and diagonals
    assert g[40, 53] < 60 and g[43, 50] < 60                              # ... but not the axes
    without_nan = show.draw_tracks(image, xy[:2], visible[:2], 1, colors[:2], trail=1)
    assert np.array_equal(out, without_nan)                               # NaN track: nothing drawn
    assert image.max() == 0                                               # input untouched
    rings = show.draw_tracks(image, xy, visible, 1, colors, trail=0, rings=np.array([True, False, False]))
    r, g, b = (int(v) for v in rings[30, 20 + 7])                          # ring around the dot
    assert r > 150 and b > 150 and g < 80 and out[30, 20 + 7].max() == 0


def test_render_sheet_grid_shape(clip):
    index = show.sample_tracks(clip, 8)
    h, w = clip.video.shape[1:3]
    sheet = show.render_sheet(clip, index, count=5, columns=3)
    assert sheet.shape == (2 * h + 4, 3 * w + 8, 3)
    assert show.sheet_frames(np.arange(10, 30), 5).tolist() == [10, 15, 20, 24, 29]


# ---- command line: PNG and MP4 ---------------------------------------------------------------

def test_cli_writes_a_png_sheet_and_an_mp4_of_the_rendered_frames(annotated_output, clip, tmp_path, capsys):
    import cv2
    import imageio.v2 as imageio

    png, mp4 = tmp_path / "s.png", tmp_path / "c.mp4"
    assert main(["show", annotated_output, "--frames", "2:12", "--points", "12", "--sheet-frames", "4",
                 "--out", str(png), "--out", str(mp4)]) == 0
    assert capsys.readouterr().out.split() == [str(png), str(mp4)]
    h, w = clip.video.shape[1:3]
    sheet = cv2.imread(str(png))
    assert sheet.shape == (2 * h + 4, 3 * w + 8, 3)                   # 4 frames on 3 columns
    with imageio.get_reader(str(mp4)) as reader:
        assert reader.get_meta_data()["codec"] == "h264"
        decoded = np.stack([frame for frame in reader])      # list() asks len(): infinite
    assert decoded.shape == (10, h, w, 3)
    expected = show.render_frames(clip, show.sample_tracks(clip, 12, np.arange(2, 12)), np.arange(2, 12))
    err = np.abs(decoded.astype(np.int16) - np.stack(expected).astype(np.int16)).mean()
    assert err < 6, f"decoded MP4 differs from the rendered frames by {err:.1f} grey levels on average"


def test_cli_gif_and_errors(annotated_output, tmp_path, capsys):
    gif = tmp_path / "c.gif"
    assert main(["show", annotated_output, "--frames", "0:3", "--out", str(gif)]) == 0
    assert gif.read_bytes()[:6] in (b"GIF89a", b"GIF87a")
    assert main(["show", annotated_output, "--errors", "--out", str(tmp_path / "e.png")]) == 2
    assert "--source" in capsys.readouterr().err
    assert main(["show", annotated_output, "--out", str(tmp_path / "x.bmp")]) == 2
    assert main(["show", annotated_output, "--object=nope", "--out", str(tmp_path / "x.png")]) == 2
    assert "objects here" in capsys.readouterr().err.replace("\n", "")


# ---- error view and depth panel (synthetic truth) ---------------------------------------------

def test_error_view_matches_truth_and_sees_injected_errors(clip, synth_source):
    view = show.error_view(clip, synth_source)
    s = view.summary()
    assert s["matched_fraction"] == 1.0
    assert s["median_error_px"] < 1.0 and s["wrong_flag_fraction"] < 0.1
    shifted = show.Clip(**{**clip.__dict__, "tracks": clip.tracks + np.float32([3.0, 4.0])})
    s2 = show.error_view(shifted, synth_source).summary()
    assert 4.0 < s2["median_error_px"] < 6.0                              # |(3, 4)| = 5 px on top
    flipped = show.Clip(**{**clip.__dict__, "visibles": ~clip.visibles})
    assert show.error_view(flipped, synth_source).summary()["wrong_flag_fraction"] > 0.9
    colors = show.error_colors(np.array([0.5, 1.5, 3.0, 5.0, 9.0, np.nan]))
    assert [tuple(c) for c in colors] == list(show.ERROR_COLORS) + [(150, 150, 150)]


def test_error_view_refuses_the_wrong_source(clip, tmp_path):
    with pytest.raises(FileNotFoundError, match="ground truth"):
        show.error_view(clip, str(tmp_path))


def test_depth_panel_recomputes_depth_close_to_the_truth(clip, synth_source, tmp_path):
    from drivetrack.synth import load_ground_truth

    frames = np.array([0, clip.num_frames - 1])
    depth = show.clip_depth(clip, synth_source, frames)
    h, w = clip.video.shape[1:3]
    assert depth.shape == (2, h, w) and depth.dtype == np.float32
    truth = load_ground_truth(synth_source, "training", clip.segment).depth(clip.camera)
    seg = np.searchsorted(load_ground_truth(synth_source, "training", clip.segment).objects["timestamps_micros"],
                          clip.timestamps_micros[frames])
    both = (depth > 0) & (truth[seg] > 0)
    assert both.mean() > 0.3
    rel = np.abs(depth[both] - truth[seg][both]) / truth[seg][both]
    assert np.median(rel) < 0.05
    out = tmp_path / "d.png"
    assert main(["show", show.select_clip(clip.url), "--source", synth_source, "--depth-panel", "--errors",
                 "--frames", "0:2", "--sheet-frames", "2", "--out", str(out)]) == 0
    import cv2
    picture = cv2.imread(str(out))
    assert picture.shape[1] == 2 * 2 * w + 4 and picture.shape[0] > h      # two tiles of image+depth, legend


# ---- previews ---------------------------------------------------------------------------------

def test_write_previews(annotated_output, tmp_path):
    import cv2
    import imageio.v2 as imageio

    out = tmp_path / "out"
    shutil.copytree(annotated_output, out)
    written = show.write_previews(str(out), per_split=2)
    assert [w.rsplit(".", 1)[1] for w in written] == ["png", "png", "mp4"]
    assert all(w.startswith(f"{out}/previews/training/waymo_") for w in written)
    for png in written[:2]:
        assert cv2.imread(png) is not None
    with imageio.get_reader(written[2]) as reader:
        assert sum(1 for _ in reader) == show.load_clip(show.select_clip(str(out))).num_frames
    assert show.find_clips(str(out)) == show.find_clips(annotated_output).__class__(
        c.replace(annotated_output, str(out)) for c in show.find_clips(annotated_output))
    empty = tmp_path / "empty"
    empty.mkdir()
    assert show.write_previews(str(empty)) == []
    with pytest.raises(ValueError, match="per_split"):
        show.write_previews(str(out), per_split=0)
