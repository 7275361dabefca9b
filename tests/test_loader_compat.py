"""Our files, read the way the field's loaders read them (docs/formats.md, "Loader compatibility").

The files are those ``drivetrack export`` writes from the release tables (the ``exported_output``
fixture: DriveTrack and TAPVid-3D npz), as a user of those loaders gets them.

Each reader below is written from the public loader it names (our code, their reading steps):

- ``aharley/alltracker`` ``datasets/drivetrackdataset.py``: glob ``*.npz`` in one folder,
  ``np.load(allow_pickle=True)``, ``video`` / ``tracks`` / ``visibles``, transpose to time-major,
  drop tracks with any non-finite value, skip clips with fewer than ``traj_per_sample`` (512)
  tracks, out-of-image -> invisible, keep tracks visible twice, drop tracks that go far out of
  bounds, keep tracks visible in frame 0, and skip the clip unless 512 remain.
- ``chandlj/pips2`` ``datasets/drivetrackdataset.py`` (the DriveTrack authors' PIPs++ fork):
  split each clip into 24-frame chunks, keep full chunks of the camera's size, keep tracks
  visible in the chunk, keep chunks with >= 256 tracks; the dataset then needs the points
  visible in frames 0 and 1 and scales pixels to the crop.
- ``google-deepmind/tapnet`` ``tapnet/tapvid3d/evaluation/evaluate_model.py`` (+ ``metrics.py``):
  ``images_jpeg_bytes``, ``queries_xyt``, ``tracks_XYZ``, ``visibility``, ``fx_fy_cx_cy``; the
  first JPEG gives H, W; intrinsics scaled so the short side is 256; queries reversed to
  (t, y, x); arrays passed with ``order='t n'``; depth-adaptive thresholds use Z / sqrt(fx fy).
- ``google-deepmind/tapnet`` ``tapnet/tapvid/evaluation_datasets.py``: ``sample_queries_first``
  and ``sample_queries_strided`` on TAP-Vid ``points`` in [0, 1] scaled to a 256 x 256 raster.
"""
from __future__ import annotations

import glob
import io
import os

import numpy as np
import pytest

from drivetrack.evaluation import metrics


@pytest.fixture(scope="module")
def split_dir(exported_output) -> str:
    """The folder of DriveTrack clips of one split (what a loader's ``data_root`` points at)."""
    folders = sorted({os.path.dirname(p) for p in glob.glob(f"{exported_output}/**/waymo_*.npz", recursive=True)
                      if "tapvid3d" not in p.split(os.sep)})
    assert len(folders) == 1, folders
    return folders[0]


@pytest.fixture(scope="module")
def tapvid3d_files(exported_output) -> list[str]:
    files = sorted(p for p in glob.glob(f"{exported_output}/**/waymo_*.npz", recursive=True)
                   if "tapvid3d" in p.split(os.sep))
    assert files
    return files


def drivetrack_file_of(tapvid3d_file: str, split_dir: str) -> str:
    path = os.path.join(split_dir, os.path.basename(tapvid3d_file))
    assert os.path.exists(path), f"no DriveTrack clip for {tapvid3d_file}"
    return path


# ---- aharley/alltracker: datasets/drivetrackdataset.py ------------------------------------------

def alltracker_style_read(path: str, traj_per_sample: int = 512, crop_size=(384, 512)):
    """(rgbs [S,H,W,3], trajs [S,N',2], visibs [S,N'], kept track indices, accepted, reason) as that
    loader builds them when it indexes the folder: drop tracks with a non-finite value; a clip with
    fewer than ``traj_per_sample`` tracks is skipped; out-of-image -> invisible; keep tracks
    visible twice (``utils.data.standardize_test_data``); drop tracks that ever go farther than
    2 max(H, W) from the crop centre; keep tracks visible in frame 0; a clip keeps its place only
    with ``traj_per_sample`` such tracks (its random trim to 10,000 tracks is left out: it only
    subsamples)."""
    ds = np.load(path, allow_pickle=True)
    rgbs, trajs, visibs = ds["video"], ds["tracks"], ds["visibles"]
    trajs = np.transpose(trajs, (1, 0, 2)).astype(np.float32)                # S, N, 2
    visibs = np.transpose(visibs, (1, 0)).astype(np.float32)                 # S, N
    valids = visibs.copy()
    kept = np.flatnonzero(np.isfinite(trajs.sum(0).sum(1)))                  # any NaN/inf -> dropped
    trajs, visibs, valids = trajs[:, kept], visibs[:, kept].copy(), valids[:, kept]
    if trajs.shape[1] < traj_per_sample:
        return rgbs, trajs, visibs, kept, False, "fewer finite tracks than traj_per_sample"
    s, h, w, _ = rgbs.shape
    outside = (trajs[..., 0] > w - 1) | (trajs[..., 0] < 0) | (trajs[..., 1] > h - 1) | (trajs[..., 1] < 0)
    visibs[outside] = 0
    twice = (valids * visibs).sum(0) > 1                                     # "tracks that make sense"
    trajs, visibs, valids, kept = trajs[:, twice], visibs[:, twice], valids[:, twice], kept[twice]
    if trajs.shape[1] < traj_per_sample:
        return rgbs, trajs, visibs, kept, False, "fewer tracks visible twice than traj_per_sample"
    centre = np.array(crop_size[::-1], np.float32) / 2.0
    close = np.all(np.linalg.norm(trajs - centre, axis=-1) < max(h, w) * 2, axis=0)
    trajs, visibs, valids, kept = trajs[:, close], visibs[:, close], valids[:, close], kept[close]
    if trajs.shape[1] < traj_per_sample:
        return rgbs, trajs, visibs, kept, False, "fewer tracks near the crop than traj_per_sample"
    first = (valids[0] * visibs[0]) > 0
    trajs, visibs, kept = trajs[:, first], visibs[:, first], kept[first]
    if trajs.shape[1] < traj_per_sample:
        return rgbs, trajs, visibs, kept, False, "fewer tracks visible in frame 0 than traj_per_sample"
    return rgbs, trajs, visibs, kept, True, ""


def test_alltracker_style_loader_reads_every_clip(split_dir):
    paths = sorted(glob.glob(os.path.join(split_dir, "*.npz")))             # flat glob, as theirs
    assert paths
    kept_fraction, accepted_at_512 = [], []
    for path in paths:
        # its per-track rules, without its clip-size threshold: every clip has tracks it can use
        rgbs, trajs, visibs, kept, accepted, reason = alltracker_style_read(path, traj_per_sample=1)
        assert accepted, f"{path}: {reason}"
        with np.load(path, allow_pickle=False) as z:                         # and no pickle needed
            tracks, visibles = z["tracks"], z["visibles"]
        s, h, w, c = rgbs.shape
        assert rgbs.dtype == np.uint8 and c == 3 and tracks.shape[1] == s
        assert trajs.shape[0] == s and trajs.shape[2] == 2 and visibs.shape == trajs.shape[:2]
        assert np.all(np.isfinite(trajs))
        # our tracks are finite at every frame (hidden frames hold the nearest valid position),
        # so their NaN rule drops none, and they stay near the image (no far out-of-bounds drop)
        assert np.all(np.isfinite(tracks))
        twice_first = np.flatnonzero((visibles.sum(axis=1) >= 2) & visibles[:, 0])
        assert set(kept.tolist()) <= set(twice_first.tolist())
        # only their stricter last-pixel-column rule differs: a track it drops is visible (ours) in
        # the last pixel column or row at a frame
        dropped = np.setdiff1d(twice_first, kept)
        edge = (tracks[dropped, :, 0] > w - 1) | (tracks[dropped, :, 1] > h - 1)
        assert np.all((edge & visibles[dropped]).any(axis=1)), dropped
        # their out-of-image rule (x > W-1) only removes points of the last pixel column/row
        ours = visibles[kept].T
        theirs = visibs.astype(bool)
        lost = ours & ~theirs
        assert np.all((trajs[..., 0][lost] > w - 1) | (trajs[..., 1][lost] > h - 1))
        kept_fraction.append(kept.size / tracks.shape[0])
        # at its default of 512 tracks per sample, a clip is indexed iff 512 of them pass
        at_512 = alltracker_style_read(path)
        assert at_512[4] == (len(kept) >= 512), (path, at_512[5])
        accepted_at_512.append(at_512[4])
    print(f"alltracker-style: kept fraction of tracks per clip {np.round(kept_fraction, 3).tolist()}; "
          f"clips indexed at traj_per_sample=512: {sum(accepted_at_512)} of {len(paths)}")
    assert any(accepted_at_512), "no clip has the 512 frame-0-visible tracks alltracker samples"


# ---- chandlj/pips2: datasets/drivetrackdataset.py (24-frame chunks) ---------------------------------

CHUNK = 24


def pips2_style_chunks(path: str, min_tracks: int = 256):
    """The 24-frame chunks that fork's preprocessing keeps (its size check uses the file's own H, W;
    the original hard-codes 1280 x 1920, the size of Waymo's front cameras)."""
    with np.load(path) as z:
        video, points, visibles = z["video"], z["tracks"].astype(np.float32), z["visibles"]
    _, h, w, _ = video.shape
    cuts = list(range(0, video.shape[0], CHUNK))[1:]
    out = []
    for v, t, vi in zip(np.array_split(video, cuts, axis=0), np.array_split(points, cuts, axis=1),
                        np.array_split(visibles, cuts, axis=1)):
        if v.shape != (CHUNK, h, w, 3) or t.shape[1] != CHUNK or vi.shape[1] != CHUNK:
            continue
        seen = np.any(vi, axis=-1)
        t, vi = t[seen], vi[seen]
        if t.shape[0] < min_tracks or t.shape[0] != vi.shape[0]:
            continue
        out.append({"video": v, "target_points": t, "visibles": vi})
    return out


def pips2_style_sample(chunk: dict, crop=(512, 896), n: int = 64, seed: int = 0):
    """What that dataset's ``__getitem__`` hands the trainer: trajs [S,N,2] in crop pixels, valids [S,N]."""
    rgbs = chunk["video"]
    trajs = chunk["target_points"].copy()
    valids = chunk["visibles"].astype(np.float32)
    h, w = rgbs.shape[1:3]
    trajs[..., 0] *= crop[1] / w
    trajs[..., 1] *= crop[0] / h
    trajs, valids = trajs.transpose(1, 0, 2), valids.transpose(1, 0)
    ok = valids[0] > 0
    trajs, valids = trajs[:, ok], valids[:, ok]
    ok = valids[1] > 0
    trajs, valids = trajs[:, ok], valids[:, ok]
    pick = np.random.default_rng(seed).choice(trajs.shape[1], min(n, trajs.shape[1]), replace=False)
    return trajs[:, pick], valids[:, pick]


def test_pips2_style_24_frame_chunks(split_dir):
    paths = sorted(glob.glob(os.path.join(split_dir, "*.npz")))
    chunks = [c for p in paths for c in pips2_style_chunks(p)]
    assert chunks, "no clip gives a full 24-frame chunk with >= 256 tracks"
    for chunk in chunks:
        assert chunk["video"].shape[0] == CHUNK and chunk["target_points"].shape[1:] == (CHUNK, 2)
        trajs, valids = pips2_style_sample(chunk)
        assert trajs.shape[:2] == valids.shape and trajs.shape[1] > 0
        # every point the trainer supervises (valids = 1) is a finite pixel inside the crop
        sup = valids > 0
        assert np.all(np.isfinite(trajs[sup]))
        assert np.all((trajs[sup] >= 0) & (trajs[sup] < np.array([896, 512])))
        # frames 0 and 1 are valid for every sampled track, as that loader requires
        assert np.all(valids[:2] > 0)


def test_full_preset_frames_have_the_size_that_fork_hard_codes():
    from drivetrack.synth.sensors import camera_models
    from drivetrack.synth import PRESETS

    models = camera_models(PRESETS["full"], ("FRONT", "FRONT_LEFT", "FRONT_RIGHT"))
    sizes = {(m.height, m.width) for m in (models.values() if isinstance(models, dict) else models)}
    assert sizes == {(1280, 1920)}


# ---- google-deepmind/tapnet: tapnet/tapvid3d/evaluation/evaluate_model.py ---------------------------

def tapvid3d_style_read(path: str) -> dict:
    """The five arrays that evaluation script reads, plus what it derives from them."""
    from PIL import Image

    with open(path, "rb") as f:
        z = np.load(f, allow_pickle=True)
        out = {k: z[k] for k in ("images_jpeg_bytes", "queries_xyt", "tracks_XYZ", "visibility", "fx_fy_cx_cy")}
    with io.BytesIO(out["images_jpeg_bytes"][0]) as buf:
        out["hw"] = np.array(Image.open(buf).convert("RGB")).shape[:2]
    out["scale_to_256"] = 256 / min(out["hw"])                               # short side -> 256
    out["query_points_tyx"] = out["queries_xyt"][..., ::-1]                 # what it passes on
    return out


def pinhole(xyz: np.ndarray, fx_fy_cx_cy: np.ndarray) -> np.ndarray:
    """(x, y) = (fx X / Z + cx, fy Y / Z + cy): the projection tapnet's TAPVid-3D tools use."""
    fx, fy, cx, cy = (float(v) for v in fx_fy_cx_cy)
    z = xyz[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.stack([fx * xyz[..., 0] / z + cx, fy * xyz[..., 1] / z + cy], axis=-1)


def test_tapvid3d_files_read_like_tapnet_evaluation(tapvid3d_files, split_dir):
    for path in tapvid3d_files:
        d = tapvid3d_style_read(path)
        with np.load(path, allow_pickle=False) as z:                         # no pickle needed either
            assert z["images_jpeg_bytes"].dtype.kind == "S"
        with np.load(drivetrack_file_of(path, split_dir)) as z:
            video, tracks, visibles = z["video"], z["tracks"], z["visibles"]
        t, n = visibles.shape[1], visibles.shape[0]
        # time-major layout and shapes
        assert len(d["images_jpeg_bytes"]) == t
        assert d["tracks_XYZ"].shape == (t, n, 3) and d["visibility"].shape == (t, n)
        assert d["visibility"].dtype == bool and np.array_equal(d["visibility"], visibles.T)
        assert d["queries_xyt"].shape == (n, 3) and d["fx_fy_cx_cy"].shape == (4,)
        assert tuple(d["hw"]) == video.shape[1:3]
        # intrinsics: positive focal lengths, principal point inside the image
        fx, fy, cx, cy = d["fx_fy_cx_cy"]
        h, w = d["hw"]
        assert fx > 0 and fy > 0 and 0 < cx < w and 0 < cy < h
        assert np.isclose(d["scale_to_256"] * min(h, w), 256)
        # query order: (x, y, t); reversed -> (t, y, x) with an integer frame where the point is visible
        q = d["query_points_tyx"]
        frame = q[:, 0]
        assert np.all(frame == np.round(frame)) and np.all((frame >= 0) & (frame < t))
        frame = frame.astype(np.int64)
        assert np.all(d["visibility"][frame, np.arange(n)])
        assert np.allclose(q[:, 2:0:-1], tracks[np.arange(n), frame], atol=1e-3)   # (x, y) of the 2D track
        # visible points are in front of the camera (the 3D thresholds scale with Z)
        xyz = d["tracks_XYZ"]
        assert np.all(np.isfinite(xyz)) and np.all(xyz[..., 2][d["visibility"]] > 0)
        # the pinhole projection of tracks_XYZ lands on the 2D tracks, up to the lens distortion
        # the pinhole intrinsics leave out (a few pixels at most on these lenses)
        proj = pinhole(xyz, d["fx_fy_cx_cy"]).transpose(1, 0, 2)            # [N, T, 2]
        gap = np.linalg.norm(proj - tracks, axis=-1)[visibles]
        assert np.median(gap) < 1.0 and gap.max() < 8.0, (path, np.median(gap), gap.max())


def test_tapvid3d_perfect_prediction_scores_one(tapvid3d_files):
    """Ground truth fed back as the prediction, through the evaluation's own arrangement
    ('t n' order, median depth scaling, thresholds Z * d / sqrt(fx fy) at 256 px)."""
    d = tapvid3d_style_read(tapvid3d_files[0])
    gt, vis = d["tracks_XYZ"].astype(np.float64), d["visibility"]
    pred = gt * 1.7                                                          # a scale median scaling removes
    gt_n, pred_n = np.linalg.norm(gt, axis=-1), np.linalg.norm(pred, axis=-1)
    scale = np.median(gt_n[vis]) / np.median(pred_n[vis])
    intr = d["fx_fy_cx_cy"] * d["scale_to_256"]
    per_point = gt[..., 2] / np.sqrt(intr[0] * intr[1])
    err = np.linalg.norm(pred * scale - gt, axis=-1)
    for thresh in (1, 2, 4, 8, 16):
        assert np.all(err[vis] < thresh * per_point[vis])
    shifted = pred * scale + np.array([0.0, 0.0, 0.5])                     # 0.5 m in depth
    assert np.mean(np.linalg.norm(shifted - gt, axis=-1)[vis] < per_point[vis]) < 0.5


# ---- google-deepmind/tapnet: tapnet/tapvid/evaluation_datasets.py (queries) ---------------------------

def tapnet_style_queries_first(occluded: np.ndarray, points: np.ndarray):
    """sample_queries_first: drop never-visible tracks; each query is (t, y, x) at the first visible frame."""
    valid = np.sum(~occluded, axis=1) > 0
    points, occluded = points[valid], occluded[valid]
    queries = []
    for i in range(points.shape[0]):
        t = np.flatnonzero(~occluded[i])[0]
        queries.append([t, points[i, t, 1], points[i, t, 0]])
    return np.array(queries, dtype=np.float64), points, occluded


def tapnet_style_queries_strided(occluded: np.ndarray, points: np.ndarray, stride: int = 5):
    """sample_queries_strided: at frames 0, stride, ..., one query per track visible there (frame-major)."""
    queries, tracks, occs, groups = [], [], [], []
    for t in range(0, occluded.shape[1], stride):
        mask = ~occluded[:, t]
        queries.append(np.stack([np.full(mask.sum(), t, np.float64), points[mask, t, 1], points[mask, t, 0]], -1))
        tracks.append(points[mask])
        occs.append(occluded[mask])
        groups.append(np.flatnonzero(mask))
    return np.concatenate(queries), np.concatenate(tracks), np.concatenate(occs), np.concatenate(groups)


@pytest.mark.parametrize("mode", ["first", "strided"])
def test_tapvid_queries_from_our_tracks(split_dir, mode):
    path = sorted(glob.glob(os.path.join(split_dir, "*.npz")))[0]
    with np.load(path) as z:
        video, tracks, visibles = z["video"], z["tracks"], z["visibles"]
    h, w = video.shape[1:3]
    tapvid = metrics.to_tapvid(tracks, visibles, w, h)                      # points in [0, 1], occluded
    assert tapvid["points"].dtype == np.float32 and tapvid["occluded"].dtype == bool
    raster = tapvid["points"].astype(np.float64) * np.array([256, 256])     # 256 x 256, as tapnet resizes
    occluded = tapvid["occluded"]
    if mode == "first":
        q, target, occ = tapnet_style_queries_first(occluded, raster)
        ours, index = metrics.queries_first(visibles, tracks)
    else:
        q, target, occ, groups = tapnet_style_queries_strided(occluded, raster)
        ours, index = metrics.queries_strided(visibles, tracks, stride=5)
        assert np.array_equal(index, groups)
    # same queries, same order: ours are in image pixels, theirs in the 256 x 256 raster
    assert q.shape == ours.shape and q.shape[0] > 0
    assert np.array_equal(q[:, 0], ours[:, 0])
    assert np.allclose(q[:, 1:], metrics.rescale_points(ours[:, :0:-1], (w, h), (256, 256))[:, ::-1], atol=1e-3)
    assert np.all(np.isfinite(q))                                           # queries are visible points
    # the ground truth as prediction scores 1 in that mode; flipping occlusion scores 0 accuracy
    b = lambda a: a[None]                                                   # noqa: E731 (batch axis)
    perfect = metrics.compute_tapvid_metrics(b(q), b(occ), b(target), b(occ), b(target), mode)
    assert perfect["average_jaccard"][0] == pytest.approx(1.0)
    assert perfect["occlusion_accuracy"][0] == pytest.approx(1.0)
    flipped = metrics.compute_tapvid_metrics(b(q), b(occ), b(target), b(~occ), b(target), mode)
    assert flipped["occlusion_accuracy"][0] == pytest.approx(0.0)
