"""A tracker vs a release: score a folder of predictions against the release's clips as ground truth.

The release's (or an annotation folder's) tracks and visibility are the ground truth, a tracker's
npz per clip (same file names; ``tracks`` [N, T, 2] and ``visibles`` or ``occluded`` [N, T]) the
prediction. Every file is checked from its npy headers before its data is read (docs/evaluation.md).
"""
from __future__ import annotations

import posixpath

import numpy as np
import pandas as pd

from drivetrack.evaluation.clips import (FLAGS, PIXELS, AnnotationFile, find_annotation_files, flags, fs_of,
                                         load_npz, read_stored, url_of)
from drivetrack.evaluation.metrics import QUERY_MODES, rescale_points
from drivetrack.evaluation.scoring import (DEFAULT_MAX_QUERIES, Evaluation, aggregate_objects, errors_at_visible,
                                           summarise, pixel_error_stats, tapvid_scores)

__all__ = ["score_predictions"]


def _prediction_index(predictions_url: str, storage_options: dict | None) -> dict[str, str]:
    fs, base = fs_of(predictions_url, storage_options)
    if not fs.isdir(base):
        raise FileNotFoundError(f"predictions folder {predictions_url} does not exist")
    by_name: dict[str, str] = {}
    for path in sorted(fs.glob(f"{base}/**/*.npz")):
        rel = path[len(base):].lstrip("/")
        name = posixpath.basename(rel)
        if "tapvid3d" in rel.split("/")[:-1]:
            continue
        if name in by_name:
            raise ValueError(f"predictions folder {predictions_url}: {name} appears twice "
                             f"({by_name[name]} and {url_of(fs, path)})")
        by_name[name] = url_of(fs, path)
    return by_name


_TRUTH_SPEC = {"visibles": (FLAGS, ("N", "T")), "tracks": (PIXELS, ("N", "T", 2))}
_PREDICTION_SPEC = {"tracks": (PIXELS, ("N", "T", 2)), "visibles": (FLAGS, ("N", "T")),
                    "occluded": (FLAGS, ("N", "T"))}


def _read_truth(file: AnnotationFile, storage_options: dict | None) -> tuple[np.ndarray, np.ndarray]:
    """(tracks float64 [N, T, 2], visibles bool [N, T]) of a release clip used as ground truth."""
    if file.clip:
        stored = read_stored(file, storage_options)
        tracks, visibles = stored.tracks.astype(np.float64), stored.visibles
    else:
        arrays = load_npz(file.url, _TRUTH_SPEC, storage_options=storage_options)
        tracks = arrays["tracks"].astype(np.float64)
        visibles = flags(arrays["visibles"], file.url, "visibles")
    bad = visibles & ~np.isfinite(tracks).all(axis=-1)
    if bad.any():
        n, t = (int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"{file.where}: ground-truth tracks are not finite at {int(bad.sum()):,} visible points "
                         f"(first: track {n}, frame {t}: {tracks[n, t].tolist()}); the clip cannot be a reference")
    return tracks, visibles


def _read_prediction(url: str, shape: tuple[int, int], truth_file: str,
                     storage_options: dict | None) -> tuple[np.ndarray, np.ndarray]:
    """(tracks [N, T, 2], visibles bool [N, T]) of one prediction file, shapes checked against the
    ground-truth clip's (N, T) from the npy headers before any data is read."""
    n, t = shape
    arrays = load_npz(url, _PREDICTION_SPEC, optional=("visibles", "occluded"), storage_options=storage_options,
                       dims={"N": n, "T": t}, dims_from=f"the ground-truth clip {truth_file}")
    if "visibles" not in arrays and "occluded" not in arrays:
        raise ValueError(f"{url}: needs 'visibles' or 'occluded' [N, T] = {(n, t)}; has {sorted(arrays)}")
    visibles = flags(arrays["visibles"], url, "visibles") if "visibles" in arrays else None
    if "occluded" in arrays:
        occluded = flags(arrays["occluded"], url, "occluded")
        if visibles is not None and (visibles == occluded).any():
            n_bad, t_bad = (int(i) for i in np.argwhere(visibles == occluded)[0])
            raise ValueError(f"{url}: has both 'visibles' and 'occluded' and they disagree (track {n_bad}, frame "
                             f"{t_bad}: visible {bool(visibles[n_bad, t_bad])}, occluded "
                             f"{bool(occluded[n_bad, t_bad])}); keep one")
        visibles = ~occluded if visibles is None else visibles
    return arrays["tracks"], visibles


def _video_size(file: AnnotationFile, storage_options: dict | None) -> tuple[int, int]:
    """(width, height) of a clip's images: the clips table's ``width``/``height``, or an npz clip
    file's ``video`` [T, H, W, 3] from the npy header only."""
    from drivetrack.storage import NpzReader

    if file.clip:
        model = read_stored(file, storage_options).camera_model
        return int(model.width), int(model.height)
    url = file.url
    with NpzReader(url, url, storage_options) as npz:
        if "video" not in npz:
            raise ValueError(f"{url}: has no 'video' array to take the image size from; pass image_size")
        shape = npz.header("video").shape
    if len(shape) != 4 or shape[1] < 1 or shape[2] < 1:
        raise ValueError(f"{url}: video has shape {shape}, expected (T, H, W, 3) to take the image size from")
    return int(shape[2]), int(shape[1])


def score_predictions(release_or_out_url: str, predictions_url: str, split: str | None = None,
                      query_modes: tuple[str, ...] = QUERY_MODES, stride: int = 5,
                      max_queries: int | None = DEFAULT_MAX_QUERIES, resize_to: tuple[int, int] | None = None,
                      allow_missing: bool = False, storage_options: dict | None = None) -> Evaluation:
    """Score a tracker's predictions against a release (or annotation folder) as ground truth.

    Args:
        release_or_out_url: release or annotation folder: its clips tables (``clips/*/*.parquet``),
            or, without them, its ``waymo_*.npz`` clips (any depth; TAPVid-3D copies skipped).
        predictions_url: folder of npz files with the *same file names* (any depth), each with
            ``tracks`` float [N, T, 2] pixels (x, y) at the clip's resolution and ``visibles``
            (or ``occluded``) bool (or 0/1) [N, T], track n answering the query of ground-truth
            track n. Each file's npy headers are checked (dtype, shape = the ground-truth clip's
            N and T, declared size) before its data is read; NaN or any value other than 0/1
            in a flag array is an error; a non-finite predicted position where the truth is
            visible is a miss and an infinite pixel error, counted per clip and in the summary
            (``num_nonfinite_at_visible``, ``num_clips_nonfinite``).
        resize_to: (width, height) to rescale both to before scoring (TAP-Vid uses 256 x 256);
            None scores at the clip's own resolution.
        allow_missing: skip clips without a prediction (counted in the summary) instead of raising.
    """
    files = find_annotation_files(release_or_out_url, split, storage_options)
    if not files:
        raise FileNotFoundError(f"no clips (clips/*/*.parquet tables or waymo_*.npz files) under {release_or_out_url}"
                                + (f" for split {split!r}" if split else ""))
    predictions = _prediction_index(predictions_url, storage_options)
    names = [f.name for f in files]
    missing = [n for n in names if n not in predictions]
    if missing and not allow_missing:
        raise FileNotFoundError(f"predictions folder {predictions_url} has no file for {len(missing)} of "
                                f"{len(files)} clips, e.g. {missing[:3]}")
    rows: list[dict] = []
    errors: list[np.ndarray] = []
    for file, name in zip(files, names):
        if name not in predictions:
            continue
        gt_tracks, gt_visibles = _read_truth(file, storage_options)
        pred_tracks, pred_visibles = _read_prediction(predictions[name], gt_visibles.shape, file.where_relative,
                                                      storage_options)
        pred_tracks = pred_tracks.astype(np.float64)
        if resize_to is not None:
            size = _video_size(file, storage_options)
            gt_tracks = rescale_points(gt_tracks, size, resize_to)
            with np.errstate(over="ignore", invalid="ignore"):
                pred_tracks = rescale_points(pred_tracks, size, resize_to)
        clip_errors, nonfinite = errors_at_visible(pred_tracks, gt_tracks, gt_visibles)
        errors.append(clip_errors.astype(np.float32))
        base = {"split": file.split, "segment": file.segment, "camera": file.camera, "object_id": file.object_id,
                "file": file.relpath, "clip": file.name[:-len(".npz")], "num_frames": int(gt_visibles.shape[1]), "num_tracks": int(gt_visibles.shape[0]),
                "num_gt_visible_points": int(gt_visibles.sum()), "num_pred_visible_points": int(pred_visibles.sum()),
                **pixel_error_stats(clip_errors), "num_nonfinite_at_visible": nonfinite}
        for mode in query_modes:
            rows.append({**base, "query_mode": mode,
                         **tapvid_scores(gt_tracks, gt_visibles, pred_tracks, pred_visibles, mode, stride,
                                         max_queries)})
    frame = pd.DataFrame(rows)
    summary = summarise("predictions_vs_release", frame, errors,
                       {"ground_truth": str(release_or_out_url), "predictions": str(predictions_url),
                        "query_modes": list(query_modes), "stride": stride,
                        "resolution": "native" if resize_to is None else f"{resize_to[0]}x{resize_to[1]}",
                        "num_clips_missing": len(missing)})
    return Evaluation(frame, aggregate_objects(frame), summary)

