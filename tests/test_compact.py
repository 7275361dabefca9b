"""Release layout v2 (issue 18): clips and frames tables that load with Hugging Face ``datasets``
(normal and streaming) and ``mlcroissant``, ``drivetrack.load_clip``, and ``drivetrack export``
byte for byte equal to the npz the writers produced before the layout changed.

Also the refusals: a clip referring to a frame its frames table lacks, and a truncated table,
are named (file, clip, frame) by the loader, export and publish.
"""
from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from drivetrack.cli import main

GOLDEN_NPZ = Path(__file__).parent / "golden" / "npz_sha256.json"


@pytest.fixture(scope="module")
def release(annotated_output, tmp_path_factory) -> str:
    """A small published release (v2 layout) of the shared annotation output."""
    out = tmp_path_factory.mktemp("compact_out")
    shutil.copytree(annotated_output, out, dirs_exist_ok=True)
    store = tmp_path_factory.mktemp("compact_store")
    assert main(["publish", str(out), "--store", str(store), "--version", "0.1.0"]) == 0
    return str(store / "drivetrack-waymo" / "0.1.0")


def _npz(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


@pytest.fixture(scope="module")
def exported_before_zbuffer(synth_source, synth_segments, tmp_path_factory) -> str:
    """The shared source annotated as the golden npz were (before the z-buffer of other objects,
    issue 15: the same defaults with ``occluder_tolerance_m`` no occluder exceeds, the labelled
    returns of the depth maps left at their capture time, back-face normals from the clip's
    returns, yaw-only labels' tilt a straight line in time, the object's own returns in the
    depth maps hiding its points like any other surface and unreliable normals never taken from
    the label box's faces), exported."""
    from drivetrack.annotate import AnnotateConfig, annotate
    from drivetrack.compact.export import FORMATS, export_clips
    from drivetrack.tracks import TrackConfig

    out = tmp_path_factory.mktemp("annotated_before_zbuffer")
    results = annotate(synth_source, "training", synth_segments, str(out),
                       AnnotateConfig(track=TrackConfig(occluder_tolerance_m=1e9,
                                                                    depth_object_motion=False,
                                                                    normals_from="clip",
                                                                    label_tilt="linear",
                                                                    own_surface_margin_m=None,
                                                                    box_face_normals_m=None, normal_neighbours=12,
                                                                    normal_neighbourhood="centred")), threads=2)
    assert all(r.status == "done" for r in results), [(r.segment, r.error) for r in results]
    exported = tmp_path_factory.mktemp("exported_before_zbuffer")
    export_clips(str(out), list(FORMATS), str(exported))
    return str(exported)


def test_export_is_byte_identical_to_the_writers_npz(exported_before_zbuffer, exported_output):
    """Every golden clip (sha256 of the npz the writers write straight from the tracks, as they did
    before layout v2; tests/golden/make_npz_sha256.py) exports to the same bytes, annotated with the
    visibility of that time; the default (z-buffer) exports the same files."""
    golden = json.loads(GOLDEN_NPZ.read_text())
    assert len(golden) >= 10
    root = Path(exported_before_zbuffer)
    got = {rel: hashlib.sha256((root / rel).read_bytes()).hexdigest() for rel in golden if (root / rel).exists()}
    assert got == golden
    for folder in (exported_before_zbuffer, exported_output):
        exported = sorted(p.relative_to(folder).as_posix() for p in Path(folder).rglob("*.npz"))
        assert exported == sorted(golden)
    changed = [rel for rel in golden
               if hashlib.sha256((Path(exported_output) / rel).read_bytes()).hexdigest() != golden[rel]]
    assert changed, "the z-buffer changed no clip of the shared scene"


def test_release_holds_tables_and_no_npz(release):
    files = [p.relative_to(release).as_posix() for p in Path(release).rglob("*") if p.is_file()]
    assert any(f.startswith("clips/training/") and f.endswith(".parquet") for f in files)
    assert any(f.startswith("frames/training/") and f.endswith(".parquet") for f in files)
    assert not [f for f in files if f.endswith(".npz")]
    # one row group per clip, floats BYTE_STREAM_SPLIT + zstd
    table = pq.ParquetFile(next(Path(release).glob("clips/training/*.parquet")))
    assert table.metadata.num_row_groups == table.metadata.num_rows
    names = [table.metadata.row_group(0).column(i).path_in_schema for i in range(table.metadata.num_columns)]
    column = table.metadata.row_group(0).column(names.index("tracks.list.element"))
    assert "BYTE_STREAM_SPLIT" in column.encodings and column.compression == "ZSTD"


def test_frames_are_stored_once_as_the_source_jpeg(release, synth_source):
    """Frames tables hold each frame once, the JPEG bytes exactly as in the source camera_image."""
    tables = sorted(Path(release).glob("frames/training/*.parquet"))
    assert tables
    for path in tables:
        t = pq.read_table(path)
        frames = t.column("frame").to_pylist()
        assert frames == sorted(set(frames))
        for image in t.column("image").to_pylist()[:3]:
            assert image["bytes"][:2] == b"\xff\xd8" and image["bytes"][-2:] == b"\xff\xd9"
    # the bytes are the source's: the source camera_image parquet holds each of them
    from drivetrack.outputs import parse_table_path

    _, _, segment, _ = parse_table_path(f"frames/training/{tables[0].name}")
    source = pq.read_table(Path(synth_source) / "training" / "camera_image" / f"{segment}.parquet")
    image_column = next(c for c in source.column_names if c.endswith(".image"))
    source_bytes = set(source.column(image_column).to_pylist())
    stored = pq.read_table(tables[0]).column("image").to_pylist()
    assert stored and all(s["bytes"] in source_bytes for s in stored)


def test_datasets_loads_the_release_normal_and_streaming(release, exported_output, tmp_path):
    """`datasets.load_dataset` reads the card's configs; one clip's tracks and visibility equal the
    exported DriveTrack npz of the same clip."""
    datasets = pytest.importorskip("datasets")
    clips = datasets.load_dataset(release, "clips", split="training", cache_dir=str(tmp_path))
    assert clips.num_rows >= 10
    row = clips[3]
    n, t = row["num_tracks"], row["num_frames"]
    npz = _npz(Path(exported_output) / "tracks" / "training" / f"{row['clip']}.npz")
    np.testing.assert_array_equal(np.asarray(row["tracks"], np.float32).reshape(n, t, 2), npz["tracks"])
    np.testing.assert_array_equal(np.asarray(row["visibles"], bool).reshape(n, t), npz["visibles"])
    np.testing.assert_array_equal(np.asarray(row["query_frames"]), npz["query_frames"])

    streamed = datasets.load_dataset(release, "clips", split="training", streaming=True, cache_dir=str(tmp_path))
    first = next(iter(streamed))
    assert first["clip"] == clips[0]["clip"]
    np.testing.assert_array_equal(np.asarray(first["tracks"], np.float32), np.asarray(clips[0]["tracks"], np.float32))

    frames = datasets.load_dataset(release, "frames", split="training", cache_dir=str(tmp_path))
    image = frames[0]["image"]
    assert image.size == (row["width"], row["height"])
    streamed_frames = next(iter(datasets.load_dataset(release, "frames", split="training", streaming=True,
                                                           cache_dir=str(tmp_path))))
    assert streamed_frames["image"].size == image.size


def test_mlcroissant_iterates_both_record_sets(release):
    mlc = pytest.importorskip("mlcroissant")
    dataset = mlc.Dataset(str(Path(release) / "croissant.json"))
    clip = next(iter(dataset.records("clips")))
    assert clip["clips/clip"].decode().startswith("waymo_")
    n, t = clip["clips/num_tracks"], clip["clips/num_frames"]
    assert len(clip["clips/tracks"]) == n * t * 2 and len(clip["clips/visibles"]) == n * t
    frame = next(iter(dataset.records("frames")))
    assert frame["frames/image"].size[0] > 0


def test_load_clip_matches_the_export(release, exported_output):
    import drivetrack

    stem = sorted(p.stem for p in (Path(exported_output) / "tracks" / "training").glob("*.npz"))[1]
    clip = drivetrack.load_clip(release, stem)
    npz = _npz(Path(exported_output) / "tracks" / "training" / f"{stem}.npz")
    np.testing.assert_array_equal(clip.tracks, npz["tracks"])
    np.testing.assert_array_equal(clip.visibles, npz["visibles"])
    assert clip.video.shape == npz["video"].shape
    np.testing.assert_array_equal(clip.video[2], npz["video"][2])
    with pytest.raises(FileNotFoundError, match="no clip waymo_nosuch_FRONT_x"):
        drivetrack.load_clip(release, "waymo_nosuch_FRONT_x")


def test_export_cli_writes_one_format(release, tmp_path, capsys):
    assert main(["export", release, "--format", "tapvid3d", "--out", str(tmp_path)]) == 0
    assert sorted(p.parts[-3] for p in tmp_path.rglob("*.npz")) == ["tapvid3d"] * len(list(tmp_path.rglob("*.npz")))
    assert "exported" in capsys.readouterr().err


def _copy_release_out(annotated_output, tmp_path) -> Path:
    out = tmp_path / "out"
    shutil.copytree(annotated_output, out)
    return out


def test_missing_frame_reference_is_named(annotated_output, tmp_path, capsys):
    """A frames table without a frame a clip uses: export, load_clip and publish name file, clip, frame."""
    import drivetrack
    from drivetrack.compact.read import CompactFormatError

    out = _copy_release_out(annotated_output, tmp_path)
    frames_path = sorted((out / "frames" / "training").glob("*_FRONT.parquet"))[0]
    table = pq.read_table(frames_path)
    dropped = table.column("frame")[5].as_py()
    pq.write_table(table.filter(pa.compute.not_equal(table.column("frame"), dropped)), frames_path)
    clips = pq.read_table(sorted((out / "clips" / "training").glob("*.parquet"))[0], columns=["clip", "camera", "frames"])
    stem = next(c for c, cam, f in zip(*(clips.column(k).to_pylist() for k in ("clip", "camera", "frames")))
                if cam == "FRONT" and dropped in f)
    with pytest.raises(CompactFormatError, match=rf"{frames_path.name}.*{stem}.*frame {dropped}"):
        drivetrack.load_clip(str(out), stem)
    assert main(["export", str(out), "--format", "drivetrack-npz", "--out", str(tmp_path / "exp")]) == 1
    assert f"frame {dropped}" in capsys.readouterr().err
    assert main(["publish", str(out), "--store", str(tmp_path / "store"), "--version", "0.1.0"]) != 0
    err = capsys.readouterr().err
    assert stem in err and f"refers to frame {dropped}" in err and frames_path.name in err
    assert not (tmp_path / "store" / "drivetrack-waymo" / "0.1.0" / "manifest.json").exists()


def test_truncated_clips_table_is_named(annotated_output, tmp_path, capsys):
    import drivetrack
    from drivetrack.compact.read import CompactFormatError

    out = _copy_release_out(annotated_output, tmp_path)
    path = sorted((out / "clips" / "training").glob("*.parquet"))[0]
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    rel = f"clips/training/{path.name}"
    with pytest.raises(CompactFormatError, match=rf"{rel}: not a readable Parquet table"):
        drivetrack.load_clip(str(out), f"waymo_{path.stem}_FRONT_x")
    assert main(["export", str(out), "--format", "tapvid3d", "--out", str(tmp_path / "exp")]) == 1
    assert rel in capsys.readouterr().err
    assert main(["gates", str(out)]) != 0
    assert rel in capsys.readouterr().err


def test_occlusion_margins_travel_from_the_track_stage_to_tables_loaders_and_npz(synth_source, synth_segments,
                                                                                 annotated_output, tmp_path):
    """``TrackConfig.occlusion_margins`` (issue 15 step 4): the clips table holds each clip's margins
    as the track stage computed them, ``read_clip`` / ``load_clip`` return them, the DriveTrack npz
    export carries them (float16) and the release contents check accepts that member; runs without
    the option store an empty list (None when read, no npz member), and a table written before the
    column existed still reads."""
    import drivetrack
    from drivetrack.annotate import AnnotateConfig, annotate_segment
    from drivetrack.compact.export import export_clips
    from drivetrack.compact.read import iter_clips, read_clip
    from drivetrack.outputs import DRIVETRACK, clip_stem
    from drivetrack.release.contents import check_clip_npz
    from drivetrack.tracks import TrackConfig

    out = tmp_path / "out"
    result = annotate_segment(synth_source, "training", synth_segments[0], str(out),
                              AnnotateConfig(track=TrackConfig(occlusion_margins=True)), keep_tracks=True)
    assert result.status == "done", result.error
    kept = [t for t in result.tracks if t.rejection is None and t.num_tracks > 0]
    assert kept
    export_clips(str(out), ["drivetrack-npz"], str(tmp_path / "npz"))
    for t in kept:
        stem = clip_stem(t.segment, t.camera_name, t.object_id)
        assert t.occlusion_margin.dtype == np.float16 and t.occlusion_margin.shape == t.visibles.shape
        stored = read_clip(str(out), stem)
        np.testing.assert_array_equal(stored.occlusion_margin, t.occlusion_margin.astype(np.float32))
        np.testing.assert_array_equal(drivetrack.load_clip(str(out), stem).occlusion_margin, stored.occlusion_margin)
        path = tmp_path / "npz" / "tracks" / "training" / f"{stem}.npz"
        np.testing.assert_array_equal(_npz(path)["occlusion_margin"], t.occlusion_margin)
        with open(path, "rb") as f:
            assert "occlusion_margin" in [name for name, _, _ in check_clip_npz(f, str(path), DRIVETRACK)]
    # the sign is the decision, as written
    stored = read_clip(str(out), clip_stem(kept[0].segment, kept[0].camera_name, kept[0].object_id))
    inside = ~np.isnan(stored.occlusion_margin)
    np.testing.assert_array_equal(stored.visibles[inside], ~np.signbit(stored.occlusion_margin[inside]))

    # the default run: no margins anywhere
    assert all(clip.occlusion_margin is None for clip in iter_clips(annotated_output))
    # a clips table written before the column existed reads as no margins
    old = tmp_path / "old"
    shutil.copytree(annotated_output, old)
    table_path = sorted((old / "clips" / "training").glob("*.parquet"))[0]
    table = pq.read_table(table_path)
    pq.write_table(table.drop(["occlusion_margin"]), table_path, row_group_size=1)
    first = next(iter(iter_clips(str(old))))
    assert first.occlusion_margin is None and first.num_tracks > 0
