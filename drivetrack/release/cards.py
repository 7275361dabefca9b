"""Dataset cards: a Hugging Face ``README.md`` (YAML front matter + body) and a Croissant 1.1
``croissant.json`` (JSON-LD; one FileObject with sha256 per data file, record sets describing the
arrays of the ``.npz`` clips and the columns of ``stats/*.parquet``).

Both are built from plain dicts (the manifest body, the statistics, the gate report); nothing
here touches storage except :func:`describe_npz`, which reads array headers from an open file.
"""
from __future__ import annotations

import json
import re
import zipfile
from dataclasses import dataclass

import numpy as np
import yaml

from drivetrack.release.manifest import FileEntry

CROISSANT_CONFORMS_TO = "http://mlcommons.org/croissant/1.1"

CROISSANT_CONTEXT = {
    "@language": "en",
    "@vocab": "https://schema.org/",
    "arrayShape": "cr:arrayShape",
    "citeAs": "cr:citeAs",
    "column": "cr:column",
    "conformsTo": "dct:conformsTo",
    "containedIn": "cr:containedIn",
    "cr": "http://mlcommons.org/croissant/",
    "rai": "http://mlcommons.org/croissant/RAI/",
    "data": {"@id": "cr:data", "@type": "@json"},
    "dataType": {"@id": "cr:dataType", "@type": "@vocab"},
    "dct": "http://purl.org/dc/terms/",
    "equivalentProperty": "cr:equivalentProperty",
    "examples": {"@id": "cr:examples", "@type": "@json"},
    "extract": "cr:extract",
    "field": "cr:field",
    "fileProperty": "cr:fileProperty",
    "fileObject": "cr:fileObject",
    "fileSet": "cr:fileSet",
    "format": "cr:format",
    "includes": "cr:includes",
    "isArray": "cr:isArray",
    "isLiveDataset": "cr:isLiveDataset",
    "jsonPath": "cr:jsonPath",
    "key": "cr:key",
    "md5": "cr:md5",
    "parentField": "cr:parentField",
    "path": "cr:path",
    "recordSet": "cr:recordSet",
    "references": "cr:references",
    "regex": "cr:regex",
    "repeated": "cr:repeated",
    "replace": "cr:replace",
    "samplingRate": "cr:samplingRate",
    "sc": "https://schema.org/",
    "separator": "cr:separator",
    "source": "cr:source",
    "subField": "cr:subField",
    "transform": "cr:transform",
}

DEFAULT_CARD = {
    "pretty_name": "DriveTrack Waymo point tracks",
    "description": ("Long-range point-track annotations generated automatically from Waymo Open "
                    "Dataset v2 driving logs with the DriveTrack method (LiDAR points on labelled "
                    "objects, projected into camera frames, occlusion from completed depth)."),
    "license": "other",
    "license_name": "waymo-open-dataset-terms",
    "license_link": "https://waymo.com/open/terms/",
    "task_categories": ["keypoint-detection"],
    "tags": ["point-tracking", "tap-vid", "tapvid-3d", "autonomous-driving", "waymo", "lidar"],
    "citation": (
        "@inproceedings{balasingam2024drivetrack,\n"
        "  title     = {DriveTrack: A Benchmark for Long-Range Point Tracking in Real-World Videos},\n"
        "  author    = {Balasingam, Arjun and Chandler, Joseph and Li, Chenning and Zhang, Zhoutong "
        "and Balakrishnan, Hari},\n"
        "  booktitle = {Proceedings of the IEEE/CVF Conference on Computer Vision and Pattern "
        "Recognition (CVPR)},\n"
        "  year      = {2024}\n"
        "}"),
}
"""Card defaults; every key can be overridden with ``card=`` (or ``config["card"]``) at publish."""


# ---- npz introspection -----------------------------------------------------------------

@dataclass(frozen=True)
class ArraySpec:
    """One array of an ``.npz`` file: name, numpy dtype string, shape (``-1`` = varies)."""

    name: str
    dtype: str
    shape: tuple[int, ...]


def describe_npz(f, where: str) -> list[ArraySpec]:
    """Names, dtypes and shapes of the arrays in an ``.npz`` (reads headers only, not the data).

    Refuses object arrays. Publish checks clips with the stricter
    :func:`drivetrack.release.contents.check_clip_npz` (declared members, dtypes and shapes)."""
    from drivetrack.release.contents import _read_header

    out: list[ArraySpec] = []
    try:
        with zipfile.ZipFile(f) as zf:
            for info in zf.infolist():
                if not info.filename.endswith(".npy"):
                    continue
                with zf.open(info) as member:
                    shape, _fortran, dtype, _offset = _read_header(member)
                if dtype.hasobject:  # never declared in a card: loading it means unpickling
                    raise ValueError(f"member {info.filename[:-4]!r} has dtype {dtype.str} (Python objects)")
                out.append(ArraySpec(info.filename[:-4], dtype.str, shape))
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as e:
        from drivetrack.release.errors import InvalidSourceError

        raise InvalidSourceError(f"{where}: not a readable .npz file ({e})") from e
    return out


def merge_specs(per_file: list[list[ArraySpec]]) -> list[ArraySpec]:
    """Union of array specs over files; a dimension that differs between files becomes ``-1``."""
    merged: dict[str, ArraySpec] = {}
    for specs in per_file:
        for s in specs:
            prev = merged.get(s.name)
            if prev is None:
                merged[s.name] = s
            elif len(prev.shape) != len(s.shape):
                merged[s.name] = ArraySpec(s.name, prev.dtype, tuple(-1 for _ in s.shape))
            else:
                shape = tuple(a if a == b else -1 for a, b in zip(prev.shape, s.shape))
                merged[s.name] = ArraySpec(s.name, prev.dtype, shape)
    return [merged[k] for k in sorted(merged)]


# ---- Croissant --------------------------------------------------------------------------

_ENCODING = {".npz": "application/x-npz", ".parquet": "application/x-parquet", ".json": "application/json",
             ".html": "text/html", ".md": "text/markdown", ".png": "image/png", ".jpg": "image/jpeg",
             ".mp4": "video/mp4", ".csv": "text/csv", ".txt": "text/plain"}


def encoding_format(path: str) -> str:
    for ext, fmt in _ENCODING.items():
        if path.endswith(ext):
            return fmt
    return "application/octet-stream"


def _id(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", text)


def _croissant_type(dtype: str) -> str:
    kind = np.dtype(dtype).kind
    if np.dtype(dtype).hasobject:
        raise ValueError(f"dtype {dtype} (Python objects) cannot be declared in croissant.json")
    return {"f": "sc:Float", "i": "sc:Integer", "u": "sc:Integer", "b": "sc:Boolean"}.get(kind, "sc:Text")


_ARROW_TYPES = {"double": "sc:Float", "float": "sc:Float", "halffloat": "sc:Float", "bool": "sc:Boolean",
                "string": "sc:Text", "large_string": "sc:Text"}


def _arrow_croissant_type(arrow_type: str) -> str:
    if arrow_type.startswith(("int", "uint")):
        return "sc:Integer"
    if arrow_type.startswith("timestamp"):
        return "sc:Date"
    return _ARROW_TYPES.get(arrow_type, "sc:Text")


ARRAY_DOCS = {
    "video": "uint8 RGB frames [T, H, W, 3]",
    "depths": "depth maps [T, H, W], metres (camera-frame x), 0 = unknown",
    "tracks": "pixel positions [N, T, 2] as (x, y) = (column, row)",
    "visibles": "visibility [N, T]",
    "occlusion_margin": "signed distance of each visibility decision from flipping [N, T], in ambiguity thresholds",
    "points3d": "3D points of the tracks",
    "images_jpeg_bytes": "JPEG-encoded frames [T]",
    "tracks_XYZ": "3D positions [T, N, 3], metres, OpenCV camera frame (X right, Y down, Z forward)",
    "visibility": "visibility [T, N]",
    "queries_xyt": "queries [N, 3] as (pixel x, pixel y, frame)",
    "fx_fy_cx_cy": "pinhole intrinsics [4], pixels",
    "extrinsics_w2c": "camera_from_world transforms [T, 4, 4]",
}


def _table_record_set(kind: str, schema, pattern: str) -> tuple[dict, dict]:
    """The FileSet and RecordSet of the v2 ``kind`` tables (``clips`` / ``frames``): one field per
    column, read from the Parquet files by mlcroissant (``records()``)."""
    import pyarrow as pa

    from drivetrack.compact.layout import COLUMN_DESCRIPTIONS

    set_id = f"{kind}-files"
    file_set = {"@type": "cr:FileSet", "@id": set_id, "name": set_id, "encodingFormat": "application/x-parquet",
                "includes": pattern,
                "description": f"The {kind} tables of release layout v2 (docs/formats.md)."}
    fields = []
    for f in schema:
        t = f.type.value_type if pa.types.is_list(f.type) else f.type
        field = {"@type": "cr:Field", "@id": f"{kind}/{f.name}", "name": f.name,
                 "description": COLUMN_DESCRIPTIONS.get(f.name, f.name),
                 "source": {"fileSet": {"@id": set_id}, "extract": {"column": f.name}}}
        if pa.types.is_struct(t):  # the image: its JPEG bytes
            field["dataType"] = "sc:ImageObject"
            field["source"]["transform"] = {"jsonPath": "bytes"}
        else:
            field["dataType"] = _arrow_croissant_type(str(t))
        if pa.types.is_list(f.type):
            field["isArray"] = True
            field["arrayShape"] = "-1"
        fields.append(field)
    record_set = {"@type": "cr:RecordSet", "@id": kind, "name": kind,
                  "description": f"One record per row of the {kind} tables.", "field": fields}
    return file_set, record_set


def build_croissant(*, dataset: str, version: str, created: str, card: dict, data_files: list[FileEntry],
                    npz_configs: dict[str, tuple[str, list[ArraySpec]]],
                    parquet_columns: dict[str, list[tuple[str, str]]], url: str | None = None) -> dict:
    """Croissant 1.1 JSON-LD for a release.

    Record sets ``clips`` and ``frames`` over the v2 tables (when the release has them; every
    column a field), one per statistics table, and one per npz layout when npz clips are
    published (``npz_configs``: ``{config name: (glob of its files, merged array specs)}``; those
    mlcroissant can describe but not read). ``parquet_columns``: ``{path of a stats parquet:
    [(column, arrow type string), ...]}``. Content URLs are relative to the version folder (where
    ``croissant.json`` lives).
    """
    from drivetrack.compact.layout import CLIPS_SCHEMA, FRAMES_SCHEMA
    from drivetrack.outputs import CLIPS, FRAMES, TABLE_FOLDERS, parse_table_path
    distribution: list[dict] = []
    for e in sorted(data_files, key=lambda e: e.path):
        distribution.append({
            "@type": "cr:FileObject", "@id": _id(e.path), "name": e.path, "contentUrl": e.path,
            "contentSize": f"{e.size} B", "encodingFormat": encoding_format(e.path), "sha256": e.sha256})
    record_sets: list[dict] = []
    kinds = {parse_table_path(e.path)[0] for e in data_files if parse_table_path(e.path)}
    for kind, schema in ((CLIPS, CLIPS_SCHEMA), (FRAMES, FRAMES_SCHEMA)):
        if kind in kinds:
            file_set, record_set = _table_record_set(kind, schema, f"{TABLE_FOLDERS[kind]}/*/*.parquet")
            distribution.append(file_set)
            record_sets.append(record_set)
    for config, (pattern, specs) in sorted(npz_configs.items()):
        set_id = f"{_id(config)}-files"
        distribution.append({
            "@type": "cr:FileSet", "@id": set_id, "name": set_id, "encodingFormat": "application/x-npz",
            "includes": pattern,
            "description": f"The {config} clips: one .npz per (segment, camera, object)."})
        fields = [{
            "@type": "cr:Field", "@id": f"{_id(config)}/file", "name": "file", "dataType": "sc:Text",
            "description": "Path of the clip file.",
            "source": {"fileSet": {"@id": set_id}, "extract": {"fileProperty": "fullpath"}}}]
        for s in specs:
            fields.append({
                "@type": "cr:Field", "@id": f"{_id(config)}/{_id(s.name)}", "name": s.name,
                "description": (f"{ARRAY_DOCS.get(s.name, 'array')}; numpy dtype {s.dtype}, shape "
                                f"({', '.join(str(d) for d in s.shape)}) with -1 where it varies "
                                f"between clips. Stored as the .npz member '{s.name}'."),
                "dataType": _croissant_type(s.dtype), "isArray": True,
                "arrayShape": ",".join(str(d) for d in s.shape) if s.shape else "1",
                "source": {"fileSet": {"@id": set_id}, "extract": {"column": s.name}}})
        record_sets.append({
            "@type": "cr:RecordSet", "@id": _id(config), "name": config,
            "description": f"One record per {config} clip; fields are the arrays of the clip's .npz.",
            "field": fields})
    for path, columns in sorted(parquet_columns.items()):
        rs = _id(path.rsplit("/", 1)[-1].rsplit(".", 1)[0])
        record_sets.append({
            "@type": "cr:RecordSet", "@id": f"stats-{rs}", "name": f"stats-{rs}",
            "description": f"Rows of {path}.",
            "field": [{
                "@type": "cr:Field", "@id": f"stats-{rs}/{_id(col)}", "name": col,
                "dataType": _arrow_croissant_type(arrow_type),
                "source": {"fileObject": {"@id": _id(path)}, "extract": {"column": col}}}
                for col, arrow_type in columns]})
    doc = {
        "@context": CROISSANT_CONTEXT,
        "@type": "sc:Dataset",
        "name": dataset,
        "description": card["description"],
        "conformsTo": CROISSANT_CONFORMS_TO,
        "citeAs": card["citation"],
        "license": card.get("license_link") or card["license"],
        "url": url or f"https://example.invalid/{dataset}/{version}",
        "version": version,
        "datePublished": created,
        "keywords": list(card.get("tags", [])),
        "distribution": distribution,
        "recordSet": record_sets,
    }
    return doc


# ---- Hugging Face card -----------------------------------------------------------------------

def size_category(n: int) -> str:
    """Hugging Face ``size_categories`` bucket for ``n`` examples."""
    bounds = [(1_000, "n<1K"), (10_000, "1K<n<10K"), (100_000, "10K<n<100K"), (1_000_000, "100K<n<1M"),
              (10_000_000, "1M<n<10M"), (100_000_000, "10M<n<100M"), (1_000_000_000, "100M<n<1B")]
    for bound, name in bounds:
        if n < bound:
            return name
    return "n>1T" if n >= 10**12 else "1B<n<10B"


def hf_configs(splits: list[str], paths: list[str]) -> list[dict]:
    """``configs`` of the card: ``clips`` (the default) and ``frames`` over the v2 tables,
    ``data_files`` per split, and ``stats``. Exported npz files get no config (``datasets``
    cannot read npz); the card body says how to load them."""
    from drivetrack.outputs import CLIPS, FRAMES, parse_table_path, table_glob

    configs = []
    for kind, extra in ((CLIPS, {"default": True}), (FRAMES, {})):
        have = sorted({p[1] for p in map(parse_table_path, paths) if p and p[0] == kind and p[1] in splits})
        if have:
            configs.append({"config_name": kind, **extra,
                            "data_files": [{"split": s, "path": table_glob(kind, s)} for s in have]})
    if any(p.startswith("stats/") and p.endswith(".parquet") for p in paths):
        configs.append({"config_name": "stats", "data_files": [
            {"split": "train", "path": "stats/objects.parquet"}]} if "stats/objects.parquet" in paths else
            {"config_name": "stats", "data_files": [{"split": "train", "path": "stats/*.parquet"}]})
    if not configs:  # an arbitrary folder: one config over every file
        configs.append({"config_name": "default", "data_files": [{"split": "train", "path": "**"}]})
    return configs


def dataset_infos(configs: list[dict]) -> list[dict]:
    """``dataset_info`` of the card: the features of the ``clips`` and ``frames`` configs (so
    ``datasets.load_dataset`` reads the JPEG column as an ``Image`` and knows every type, also
    when streaming)."""
    from drivetrack.compact.layout import CLIPS_FEATURES, FRAMES_FEATURES

    features = {"clips": CLIPS_FEATURES, "frames": FRAMES_FEATURES}
    return [{"config_name": c["config_name"], "features": features[c["config_name"]]}
            for c in configs if c["config_name"] in features]


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, dict):
        return ", ".join(f"{k}: {_fmt(x)}" for k, x in v.items())
    return str(v)


def summarize_gates(gate_report: dict | None, accepted_reason: str | None) -> dict | None:
    """A compact, JSON-able summary of a gate report for the manifest and the card."""
    if gate_report is None:
        return None
    results = gate_report.get("results") or []
    rows = []
    for r in results:
        if not isinstance(r, dict):
            rows.append({"name": str(r), "success": None})
            continue
        cfg = r.get("expectation_config") if isinstance(r.get("expectation_config"), dict) else {}
        name = r.get("name") or r.get("gate") or r.get("expectation") or r.get("expectation_type") \
            or cfg.get("type") or cfg.get("expectation_type") or "gate"
        row = {"name": str(name), "success": None if r.get("success") is None else bool(r.get("success"))}
        for k in ("table", "column", "observed", "threshold", "message"):
            if k in r and isinstance(r[k], (str, int, float, bool)):
                row[k] = r[k]
        rows.append(row)
    return {"success": bool(gate_report.get("success")),
            "accepted_failure_reason": accepted_reason,
            "passed": sum(1 for r in rows if r["success"] is True),
            "failed": sum(1 for r in rows if r["success"] is False),
            "results": rows}


def build_hf_card(*, dataset: str, version: str, created: str, card: dict, paths: list[str], splits: list[str],
                  counts: dict, statistics: dict, gates: dict | None, run: dict | None,
                  code: dict, store_url: str) -> str:
    """The Hugging Face dataset card (``README.md``): YAML front matter and a Markdown body."""
    n_examples = sum(s.get("clips", 0) for s in counts.get("splits", {}).values()) or counts["files"]
    front = {
        "license": card["license"],
        "pretty_name": card["pretty_name"],
        "size_categories": [size_category(n_examples)],
        "task_categories": list(card["task_categories"]),
        "tags": list(card.get("tags", [])),
        "configs": hf_configs(splits, paths),
    }
    infos = dataset_infos(front["configs"])
    if infos:
        front["dataset_info"] = infos
    if card["license"] == "other":
        front["license_name"] = card["license_name"]
        front["license_link"] = card["license_link"]
    lines = ["---", yaml.safe_dump(front, sort_keys=False, allow_unicode=False).rstrip(), "---", "",
             f"# {card['pretty_name']} ({dataset} {version})", "", card["description"], "",
             "## Release", "",
             f"- version: `{version}` (created {created})",
             f"- files: {counts['files']} ({counts['bytes'] / 1e6:.1f} MB); every file's size and sha256 "
             f"are in `manifest.json` and `SHA256SUMS`",
             f"- code: drivetrack {code.get('drivetrack')}, git {code.get('git_commit') or 'unknown'}"]
    if run:
        if run.get("code_version"):
            lines.append(f"- annotated with: {_fmt(run['code_version'])}")
        if "seed" in run:
            lines.append(f"- seed: {run['seed']}")
        if isinstance(run.get("segments"), list):
            lines.append(f"- input segments: {len(run['segments'])} (ids and source checksums in `manifest.json`)")
    lines += ["", "## Contents", "",
              "Release layout v2: `clips/{split}/{segment}.parquet` (one row per clip: tracks, visibility, "
              "query frames, LiDAR sources, 3D points, camera) and `frames/{split}/{segment}_{CAMERA}.parquet` "
              "(one row per frame: the source JPEG, stored once). Columns: docs/formats.md of the "
              "drivetrack package.", "",
              "| split | clips | npz clips (DriveTrack / TAPVid-3D) | MB |", "|---|---|---|---|"]
    for split, c in counts.get("splits", {}).items():
        lines.append(f"| {split} | {c['clips']} | {c.get('npz_clips', 0)} / {c['tapvid3d_clips']} | "
                     f"{c['bytes'] / 1e6:.1f} |")
    if statistics:
        lines += ["", "## Statistics", "", "| table | statistic | value |", "|---|---|---|"]
        for table, entry in statistics.items():
            for k, v in entry.items():
                if k != "columns":
                    lines.append(f"| {table} | {k} | {_fmt(v)} |")
    previews = sorted(p for p in paths if p.startswith("previews/") and p.endswith((".png", ".mp4", ".gif")))
    if previews:
        lines += ["", "## Previews", "",
                  "Made by `drivetrack show`: visible points are filled dots, occluded ones crosses, "
                  "with trails of the last frames.", ""]
        lines += [f"![{p}]({p})" if p.endswith(".png") else f"- clip: [{p}]({p})" for p in previews]
    lines += ["", "## Quality gates", ""]
    if gates is None:
        lines.append("No gate report was supplied for this release.")
    else:
        verdict = "passed" if gates["success"] else "FAILED"
        lines.append(f"Gates {verdict}: {gates['passed']} passed, {gates['failed']} failed "
                     f"(full reports under `validation/` when present).")
        if gates.get("binding_sha256"):
            lines += ["", f"The gate report is bound to this release's content (binding "
                      f"`{gates['binding_sha256'][:16]}`: sha256 of the statistics tables and of every "
                      f"clip file, checked at publish; gates run by: {gates.get('ran_by', 'report')})."]
        if gates.get("accepted_failure_reason"):
            lines += ["", f"**Published despite failed gates.** Reason given: {gates['accepted_failure_reason']}"]
        if gates["results"]:
            lines += ["", "| gate | result |", "|---|---|"]
            for r in gates["results"]:
                mark = {True: "pass", False: "FAIL", None: "?"}[r["success"]]
                lines.append(f"| {r['name']} | {mark} |")
    split = splits[0] if splits else "training"
    lines += ["", "## How to load", "", "With `datasets` (normal or `streaming=True`):", "", "```python",
              "import numpy as np, datasets",
              "clips = datasets.load_dataset('<this folder or Hub repo>', 'clips', split='" + split + "')",
              "c = clips[0]",
              "tracks = np.asarray(c['tracks'], np.float32).reshape(c['num_tracks'], c['num_frames'], 2)  # [N,T,2] (x, y)",
              "visibles = np.asarray(c['visibles']).reshape(c['num_tracks'], c['num_frames'])        # [N,T]",
              "frames = datasets.load_dataset('<this folder or Hub repo>', 'frames', split='" + split + "')  # JPEGs",
              "```", "",
              "With the drivetrack package (video decoded lazily):", "", "```python",
              "import drivetrack",
              "clip = drivetrack.load_clip('<this folder>', 'waymo_<segment>_<CAMERA>_<object_id>')",
              "clip.video[0], clip.tracks, clip.visibles   # [H,W,3] RGB, [N,T,2], [N,T]",
              "```", "",
              "As the DriveTrack or TAPVid-3D npz files: `drivetrack export <this folder> --format drivetrack-npz "
              "--format tapvid3d --out DIR`.", "",
              "Check the download: `sha256sum -c SHA256SUMS` in this folder, or "
              f"`drivetrack verify {store_url} --version {version} --dataset {dataset}`.",
              "The Croissant description (`croissant.json`) loads with `mlcroissant`.",
              "", "## Citation", "", "```bibtex", card["citation"], "```", ""]
    return "\n".join(lines)


def croissant_bytes(doc: dict) -> bytes:
    return (json.dumps(doc, indent=1, ensure_ascii=False) + "\n").encode("utf-8")
