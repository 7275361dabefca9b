"""Hostile inputs to `drivetrack evaluate` (issue 13 item 8): prediction files that lie in their
npy headers, hide NaN in tracks or visibility, carry pickled objects or the wrong shapes.

Every prediction here answers a real clip of the shared ``annotated_output`` fixture; the
ground truth is that folder itself (as for a release).
"""
from __future__ import annotations

import io
import math
import re
import time
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest

from drivetrack.evaluation import find_annotation_files, score_predictions
from drivetrack.evaluation.clips import read_clip


def _arrays(url: str) -> dict[str, np.ndarray]:
    with np.load(url) as npz:
        return {k: npz[k] for k in ("tracks", "visibles")}


def _perfect_predictions(src: str, dst: Path) -> dict[str, Path]:
    """One exact prediction per clip of ``src`` under ``dst``: {file name: path}."""
    out = {}
    for file in find_annotation_files(src):
        clip = read_clip(file)
        arrays = {"tracks": clip.tracks, "visibles": clip.visibles}
        target = dst / file.name
        target.parent.mkdir(parents=True, exist_ok=True)
        np.savez(target, tracks=arrays["tracks"], visibles=arrays["visibles"])
        out[target.name] = target
    return out


def _biggest(preds: dict[str, Path]) -> Path:
    """The prediction whose clip has the most truth-visible points (a clip worth corrupting)."""
    return max(preds.values(), key=lambda p: (_arrays(str(p))["visibles"].sum(), p.name))


def _npy_header(shape: tuple, dtype=np.float32) -> bytes:
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)),
                                                  "fortran_order": False, "shape": shape})
    return buffer.getvalue()


def _write_member(archive: zipfile.ZipFile, name: str, header: bytes, data_bytes: int) -> None:
    """A deflated member: ``header`` then ``data_bytes`` zeros, streamed (never held whole)."""
    info = zipfile.ZipInfo(name)
    info.compress_type = zipfile.ZIP_DEFLATED
    with archive.open(info, "w", force_zip64=True) as member:
        member.write(header)
        chunk = bytes(1 << 20)
        left = data_bytes
        while left:
            member.write(chunk[:min(left, len(chunk))])
            left -= min(left, len(chunk))


def _score_with_peak(gt: str, preds: Path):
    """score_predictions's outcome (result or exception) and its peak traced allocation in bytes."""
    tracemalloc.start()
    try:
        start = time.monotonic()
        try:
            outcome = score_predictions(gt, str(preds), query_modes=("first",))
        except Exception as error:              # noqa: BLE001 - the test inspects what was raised
            outcome = error
        elapsed = time.monotonic() - start
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return outcome, peak, elapsed


# ------------------------------------------------------------------------------------------------
# Non-finite predicted positions
# ------------------------------------------------------------------------------------------------

def test_nan_tracks_are_errors_in_the_headline_not_zero_pixels(annotated_output, tmp_path, capsys):
    from drivetrack.cli import main

    preds = _perfect_predictions(annotated_output, tmp_path / "pred")
    victim = _biggest(preds)
    arrays = _arrays(str(victim))
    tracks = arrays["tracks"].astype(np.float32)
    tracks[np.arange(len(tracks)) % 3 != 0] = np.nan      # two tracks in three: NaN everywhere
    tracks[0, :, 0] = np.inf                               # and one track at +inf
    np.savez(victim, tracks=tracks, visibles=arrays["visibles"])
    expected = int((arrays["visibles"] & ~np.isfinite(tracks).all(-1)).sum())
    assert expected > 0

    result = score_predictions(annotated_output, str(tmp_path / "pred"))
    summary = result.summary
    assert summary["num_nonfinite_at_visible"] == expected
    assert summary["num_clips_nonfinite"] == 1
    assert summary["pixel_error_mean"] == math.inf         # never averaged away
    row = result.clips[(result.clips["clip"] == victim.stem) & (result.clips["query_mode"] == "first")]
    assert int(row["num_nonfinite_at_visible"].iloc[0]) == expected
    assert row["pixel_error_median"].iloc[0] == math.inf   # more than half its points are NaN/inf
    for mode in ("first", "strided"):
        m = summary["modes"][mode]
        assert m["average_pts_within_thresh"] < 1.0 and m["average_jaccard"] < 1.0
    clip_first = row.iloc[0]
    assert clip_first["average_pts_within_thresh"] < 0.6   # the NaN/inf tracks are misses

    # every prediction NaN: the median is not "0 px" and not silently missing
    for path in preds.values():
        a = _arrays(str(path))
        np.savez(path, tracks=np.full(a["tracks"].shape, np.nan, np.float32), visibles=a["visibles"])
    all_nan = score_predictions(annotated_output, str(tmp_path / "pred")).summary
    assert all_nan["pixel_error_median"] == math.inf and all_nan["pixel_error_p95"] == math.inf
    assert all_nan["num_nonfinite_at_visible"] == all_nan["num_gt_visible_points"] > 0
    assert all_nan["modes"]["first"]["average_pts_within_thresh"] == 0.0

    assert main(["evaluate", annotated_output, "--predictions", str(tmp_path / "pred")]) == 0
    printed = capsys.readouterr().out
    assert re.search(rf"non-finite\s+predictions:\s+{all_nan['num_nonfinite_at_visible']:,}\s+point-frames\s+in"
                     rf"\s+{all_nan['num_clips']}\s+clips", printed), printed
    assert re.search(r"median\s+inf\s+px", printed), printed


# ------------------------------------------------------------------------------------------------
# Visibility that is not a flag
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("key", ["visibles", "occluded"])
def test_nan_visibility_is_refused_naming_file_and_member(annotated_output, tmp_path, key):
    preds = _perfect_predictions(annotated_output, tmp_path / "pred")
    victim = _biggest(preds)
    arrays = _arrays(str(victim))
    flags = (arrays["visibles"] if key == "visibles" else ~arrays["visibles"]).astype(np.float32)
    flags[0, 0] = np.nan                                   # read as True by a plain astype(bool)
    np.savez(victim, tracks=arrays["tracks"], **{key: flags})
    with pytest.raises(ValueError, match=rf"{re.escape(victim.name)}: {key} must hold only 0/1.*nan.*\(0, 0\)"):
        score_predictions(annotated_output, str(tmp_path / "pred"))
    flags[0, 0] = 0.4                                      # a probability is not a flag either
    np.savez(victim, tracks=arrays["tracks"], **{key: flags})
    with pytest.raises(ValueError, match=rf"{re.escape(victim.name)}: {key} must hold only 0/1"):
        score_predictions(annotated_output, str(tmp_path / "pred"))


def test_visibles_and_occluded_that_disagree_are_refused(annotated_output, tmp_path):
    preds = _perfect_predictions(annotated_output, tmp_path / "pred")
    victim = _biggest(preds)
    arrays = _arrays(str(victim))
    np.savez(victim, tracks=arrays["tracks"], visibles=arrays["visibles"], occluded=arrays["visibles"])
    with pytest.raises(ValueError, match=rf"{re.escape(victim.name)}: has both 'visibles' and 'occluded' and they "
                                         rf"disagree"):
        score_predictions(annotated_output, str(tmp_path / "pred"))


# ------------------------------------------------------------------------------------------------
# dtypes that are not numbers
# ------------------------------------------------------------------------------------------------

def test_object_member_is_refused_naming_the_file(annotated_output, tmp_path):
    preds = _perfect_predictions(annotated_output, tmp_path / "pred")
    victim = _biggest(preds)
    arrays = _arrays(str(victim))
    pickled = np.empty(arrays["tracks"].shape, dtype=object)
    pickled[...] = 0.0
    np.savez(victim, tracks=pickled, visibles=arrays["visibles"])
    with pytest.raises(ValueError, match=rf"{re.escape(victim.name)}: member 'tracks' has dtype object"):
        score_predictions(annotated_output, str(tmp_path / "pred"))


def test_string_tracks_are_refused_not_parsed(annotated_output, tmp_path):
    preds = _perfect_predictions(annotated_output, tmp_path / "pred")
    victim = _biggest(preds)
    arrays = _arrays(str(victim))
    np.savez(victim, tracks=arrays["tracks"].astype(str), visibles=arrays["visibles"])  # astype(float) would work
    with pytest.raises(ValueError, match=rf"{re.escape(victim.name)}: tracks has dtype <U\d+; expected a real"):
        score_predictions(annotated_output, str(tmp_path / "pred"))


def test_member_present_twice_is_refused(annotated_output, tmp_path):
    preds = _perfect_predictions(annotated_output, tmp_path / "pred")
    victim = _biggest(preds)
    arrays = _arrays(str(victim))
    with zipfile.ZipFile(victim, "a") as archive, pytest.warns(UserWarning, match="Duplicate name"):
        buffer = io.BytesIO()
        np.lib.format.write_array(buffer, arrays["tracks"] + 50)
        archive.writestr("tracks.npy", buffer.getvalue())      # a second, different 'tracks'
    with pytest.raises(ValueError, match=rf"{re.escape(victim.name)}: member 'tracks' appears twice"):
        score_predictions(annotated_output, str(tmp_path / "pred"))


# ------------------------------------------------------------------------------------------------
# Headers that declare more than the file holds, shapes that are not the clip's
# ------------------------------------------------------------------------------------------------

def test_header_declaring_a_huge_array_is_refused_before_allocating(annotated_output, tmp_path):
    preds = _perfect_predictions(annotated_output, tmp_path / "pred")
    victim = _biggest(preds)
    arrays = _arrays(str(victim))
    with zipfile.ZipFile(victim, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("tracks.npy", _npy_header((10**6, 10**4, 2)) + bytes(16))   # declares 80 GB
        buffer = io.BytesIO()
        np.lib.format.write_array(buffer, arrays["visibles"])
        archive.writestr("visibles.npy", buffer.getvalue())
    assert victim.stat().st_size < 50_000                   # the clip's visibles, deflated
    outcome, peak, elapsed = _score_with_peak(annotated_output, tmp_path / "pred")
    assert peak < 100 * 2**20, f"peak traced allocation {peak / 2**20:.0f} MiB ({outcome!r})"
    assert isinstance(outcome, ValueError), outcome
    message = str(outcome)
    assert victim.name in message and "'tracks'" in message and "80,000,000,000 bytes" in message, message
    assert elapsed < 30


def test_consistent_but_oversized_member_is_refused_from_its_header(annotated_output, tmp_path):
    """A genuine zip of zeros (a few hundred kB on disk, 150 MiB inflated) whose shape is not the
    clip's: refused from the header, nothing of it allocated."""
    preds = _perfect_predictions(annotated_output, tmp_path / "pred")
    victim = _biggest(preds)
    arrays = _arrays(str(victim))
    n, t = arrays["visibles"].shape
    rows = (150 * 2**20) // (t * 2 * 4)
    with zipfile.ZipFile(victim, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        _write_member(archive, "tracks.npy", _npy_header((rows, t, 2)), rows * t * 2 * 4)
        buffer = io.BytesIO()
        np.lib.format.write_array(buffer, arrays["visibles"])
        archive.writestr("visibles.npy", buffer.getvalue())
    assert victim.stat().st_size < 5 * 2**20
    outcome, peak, _ = _score_with_peak(annotated_output, tmp_path / "pred")
    assert peak < 100 * 2**20, f"peak traced allocation {peak / 2**20:.0f} MiB ({outcome!r})"
    assert isinstance(outcome, ValueError), outcome
    assert re.search(rf"{re.escape(victim.name)}: tracks has shape \({rows}, {t}, 2\), expected \(N, T, 2\) = "
                     rf"\({n}, {t}, 2\)", str(outcome)), outcome


def test_wrong_shapes_name_file_member_expected_and_found(annotated_output, tmp_path):
    preds = _perfect_predictions(annotated_output, tmp_path / "pred")
    victim = _biggest(preds)
    arrays = _arrays(str(victim))
    n, t = arrays["visibles"].shape
    np.savez(victim, tracks=arrays["tracks"], occluded=~arrays["visibles"][:, :-1])
    with pytest.raises(ValueError, match=rf"{re.escape(victim.name)}: occluded has shape \({n}, {t - 1}\), "
                                         rf"expected \(N, T\) = \({n}, {t}\) \(N tracks, T frames of the "
                                         rf"ground-truth clip .*{re.escape(victim.stem)}\)"):
        score_predictions(annotated_output, str(tmp_path / "pred"))
    np.savez(victim, tracks=arrays["tracks"][..., 0], visibles=arrays["visibles"])
    with pytest.raises(ValueError, match=rf"{re.escape(victim.name)}: tracks has shape \({n}, {t}\), expected "
                                         rf"\(N, T, 2\) = \({n}, {t}, 2\)"):
        score_predictions(annotated_output, str(tmp_path / "pred"))


def test_nan_annotation_tracks_count_against_exact_truth(annotated_output, synth_source):
    """The same rule in the other mode: an annotation's NaN position at a truth-visible frame is
    an error in the summary, not a point left out of the pixel statistics."""
    from drivetrack.evaluation import evaluate_clips, read_clip

    files = [f for f in find_annotation_files(annotated_output)]
    segment = files[0].segment
    clips = [read_clip(f) for f in files if f.segment == segment][:3]
    clips[0].tracks = clips[0].tracks.astype(np.float32)
    clips[0].tracks[:, :, 1] = np.nan
    result = evaluate_clips(clips, synth_source, query_modes=("first",))
    bad = int(result.clips["num_nonfinite_at_visible"].iloc[0])
    assert bad > 0
    assert result.summary["num_nonfinite_at_visible"] == bad and result.summary["num_clips_nonfinite"] == 1
    assert result.summary["pixel_error_mean"] == math.inf
    assert result.clips["pixel_error_median"].iloc[0] == math.inf


def test_read_npz_headers_reads_declarations_only(tmp_path):
    from drivetrack.storage import read_npz_headers, write_npz

    url = str(tmp_path / "a.npz")
    write_npz(url, {"tracks": np.zeros((3, 5, 2), np.float32), "visibles": np.ones((3, 5), bool)})
    headers = read_npz_headers(url)
    assert {k: (h.dtype, h.shape) for k, h in headers.items()} == {
        "tracks": (np.dtype(np.float32), (3, 5, 2)), "visibles": (np.dtype(bool), (3, 5))}
    bad = tmp_path / "bad.npz"
    with zipfile.ZipFile(bad, "w") as archive:
        archive.writestr("x.npy", _npy_header((10**9,), np.float64) + bytes(8))
    with pytest.raises(ValueError, match=r"bad\.npz: member 'x' declares float64 \(1000000000,\)"):
        read_npz_headers(str(bad))
