"""The output contract: which files a release may hold, and the checks publish makes on them.

An annotation output folder (docs/architecture.md, "Annotation output folder") holds exactly:

    run.json                                         provenance (annotate, flows)
    status.json, status.html                         build status page (flows)
    stats/{objects,segments,rejections}.parquet      statistics tables
    clips/{split}/{segment}.parquet                  clips tables (release layout v2, drivetrack.compact)
    frames/{split}/{segment}_{CAMERA}.parquet        frames tables (release layout v2)
    tracks/{split}/waymo_{stem}.npz                  DriveTrack clips      (CLIP_FORMATS[DRIVETRACK])
    tapvid3d/{split}/waymo_{stem}.npz                TAPVid-3D clips       (CLIP_FORMATS[TAPVID3D])
    previews/{split}/waymo_{stem}.{png,mp4}          previews (drivetrack show / flows)
    validation/gates.json, validation/report.html, validation/gx_results/{suite}.json,
    validation/data_docs/**.{html,css,png,ico,json}  gate reports (drivetrack gates)

:data:`MEMBERS` is that list as code. Every other file is refused by publish, and so are
symbolic links (to files or folders), hidden names (a path component starting with ``.``, which
covers ``.env`` and the writers' ``.partial-*`` temporary files), sockets, fifos and devices.
Clip files are checked member by member against :data:`CLIP_FORMATS` from their ``.npy`` headers
alone (nothing of the data is decompressed beyond the header): names, dtypes, shapes and the
relations between them (one N, one T per clip); object arrays are refused everywhere. The v2
tables are checked by :func:`drivetrack.release.publish` (columns, readability, frame references:
:func:`drivetrack.compact.read.check_frame_references`).
"""
from __future__ import annotations

import io
import math
import os
import re
import stat
import zipfile
from dataclasses import dataclass

import numpy as np

from drivetrack.outputs import (CLIPS, DRIVETRACK, FRAMES, LAYOUTS, TABLE_FOLDERS, TAPVID3D, parse_clip_path,
                                parse_table_path)
from drivetrack.names import is_valid_name
from drivetrack.release.errors import InvalidSourceError

__all__ = ["MEMBERS", "CLIP_FORMATS", "OPTIONAL_MEMBERS", "ArrayFormat", "member_kind", "list_local_folder", "open_local_nofollow",
           "check_clip_npz", "check_stats_table", "clips_of_unfinished_segments", "refuse"]

_SEG = r"[A-Za-z0-9][A-Za-z0-9_.\-]*"          # one path component, never hidden
_SPLIT = r"[A-Za-z0-9][A-Za-z0-9._\-]{0,127}"     # drivetrack.names "split"
_STEM = r"waymo_[A-Za-z0-9][A-Za-z0-9_.\-]*"      # waymo_{segment}_{CAMERA}_{object_id}
STATS_TABLES = ("objects", "segments", "rejections")


@dataclass(frozen=True)
class Member:
    """One kind of file a release may hold: ``pattern`` is matched in full against the relative path."""

    name: str
    pattern: re.Pattern
    kind: str  # "json", "parquet", "table:<kind>", "npz:<layout>", "file"


MEMBERS: tuple[Member, ...] = (
    Member("provenance", re.compile(r"run\.json"), "json"),
    Member("build status page", re.compile(r"status\.(json|html)"), "file"),
    Member("statistics table", re.compile(rf"stats/({'|'.join(STATS_TABLES)})\.parquet"), "parquet"),
    Member("clips table", re.compile(rf"{TABLE_FOLDERS[CLIPS]}/{_SPLIT}/{_SEG}\.parquet"), f"table:{CLIPS}"),
    Member("frames table", re.compile(rf"{TABLE_FOLDERS[FRAMES]}/{_SPLIT}/{_SEG}\.parquet"), f"table:{FRAMES}"),
    Member("DriveTrack clip", re.compile(rf"{LAYOUTS[DRIVETRACK]}/{_SPLIT}/{_STEM}\.npz"), f"npz:{DRIVETRACK}"),
    Member("TAPVid-3D clip", re.compile(rf"{LAYOUTS[TAPVID3D]}/{_SPLIT}/{_STEM}\.npz"), f"npz:{TAPVID3D}"),
    Member("preview", re.compile(rf"previews/{_SPLIT}/{_STEM}\.(png|mp4)"), "file"),
    Member("gate report", re.compile(rf"validation/(gates\.json|report\.html|gx_results/{_SEG}\.json)"), "file"),
    Member("gate Data Docs", re.compile(rf"validation/data_docs/({_SEG}/)*{_SEG}\.(html|css|png|ico|json)"), "file"),
)


def member_kind(rel: str) -> str | None:
    """The kind of the release member at relative path ``rel``, or None when it is not one."""
    if any(part.startswith(".") for part in rel.split("/")):
        return None
    for m in MEMBERS:
        if m.pattern.fullmatch(rel):
            if m.kind.startswith(("npz:", "table:")) and not is_valid_name("split", rel.split("/")[1]):
                return None
            if m.kind.startswith("table:") and not parse_table_path(rel):
                return None
            return m.kind
    return None


def refuse(where: str, problems: list[str], what: str, limit: int = 20) -> None:
    """Raise one :class:`InvalidSourceError` listing ``problems`` (nothing when there are none)."""
    if not problems:
        return
    shown = problems[:limit] + ([f"... and {len(problems) - limit} more"] if len(problems) > limit else [])
    raise InvalidSourceError(f"{where}: {len(problems)} file(s) cannot be published ({what}):\n  "
                             + "\n  ".join(shown))


_KNOWN = ("run.json, status.json/html, stats/{objects,segments,rejections}.parquet, "
          "clips/{split}/{segment}.parquet, frames/{split}/{segment}_{CAMERA}.parquet, "
          "tracks/{split}/waymo_*.npz, tapvid3d/{split}/waymo_*.npz, previews/{split}/waymo_*.png|mp4, "
          "validation/ gate reports")


def _file_type(mode: int) -> str:
    for test, name in ((stat.S_ISSOCK, "a socket"), (stat.S_ISFIFO, "a fifo"), (stat.S_ISCHR, "a device"),
                       (stat.S_ISBLK, "a device")):
        if test(mode):
            return name
    return "not a regular file"


def list_local_folder(root: str) -> dict[str, int]:
    """``{relative path: size}`` of a local output folder, walked without following links.

    Raises :class:`InvalidSourceError` listing every symbolic link, hidden name, special file and
    file that is not a release member (:data:`MEMBERS`).
    """
    out: dict[str, int] = {}
    problems: list[str] = []

    def fail(err: OSError):
        raise InvalidSourceError(f"cannot list {err.filename}: {err.strerror}") from err

    for dirpath, dirs, files in os.walk(root, followlinks=False, onerror=fail):
        keep = []
        for name in sorted(dirs + files):
            full = os.path.join(dirpath, name)
            rel = os.path.relpath(full, root).replace(os.sep, "/")
            st = os.lstat(full)
            if stat.S_ISLNK(st.st_mode):
                problems.append(f"{rel}: symbolic link (to {os.readlink(full)}); links are never followed")
            elif name.startswith("."):
                problems.append(f"{rel}: hidden {'folder' if stat.S_ISDIR(st.st_mode) else 'file'} "
                                f"(temporary or private files such as .env or .partial-* are not release members)")
            elif stat.S_ISDIR(st.st_mode):
                keep.append(name)
            elif not stat.S_ISREG(st.st_mode):
                problems.append(f"{rel}: {_file_type(st.st_mode)}, not a regular file")
            elif member_kind(rel) is None:
                problems.append(f"{rel}: not a release member (known: {_KNOWN})")
            else:
                out[rel] = st.st_size
        dirs[:] = sorted(d for d in dirs if d in keep)
    refuse(root, problems, "only regular files of the output contract are published, see docs/release.md "
                           "'What publish refuses'")
    return dict(sorted(out.items()))


def check_listed(where: str, entries: dict[str, str]) -> None:
    """Refuse entries of a remote listing (``{relative path: fsspec type}``) that are not regular
    files of the output contract."""
    problems = []
    for rel, kind in sorted(entries.items()):
        if kind == "directory":
            if any(p.startswith(".") for p in rel.split("/")):
                problems.append(f"{rel}: hidden folder")
        elif kind != "file":
            problems.append(f"{rel}: {kind}, not a regular file")
        elif any(p.startswith(".") for p in rel.split("/")):
            problems.append(f"{rel}: hidden file (temporary or private files are not release members)")
        elif member_kind(rel) is None:
            problems.append(f"{rel}: not a release member (known: {_KNOWN})")
    refuse(where, problems, "only regular files of the output contract are published, see docs/release.md "
                            "'What publish refuses'")


def open_local_nofollow(root: str, rel: str):
    """Open ``root/rel`` for reading without following a symbolic link at any component below
    ``root``, and only if it is a regular file (a link swapped in after the listing is refused)."""
    parts = rel.split("/")
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0)
    dfd = os.open(root, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        for part in parts[:-1]:
            nfd = os.open(part, flags | getattr(os, "O_DIRECTORY", 0), dir_fd=dfd)
            os.close(dfd)
            dfd = nfd
        fd = os.open(parts[-1], flags | getattr(os, "O_NONBLOCK", 0), dir_fd=dfd)
    except OSError as e:
        raise InvalidSourceError(f"{os.path.join(root, rel)}: cannot be opened as a regular file without "
                                 f"following links ({e.strerror})") from e
    finally:
        os.close(dfd)
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise InvalidSourceError(f"{os.path.join(root, rel)}: not a regular file")
    return os.fdopen(fd, "rb", buffering=0)


# ---- clip formats ------------------------------------------------------------------------------

@dataclass(frozen=True)
class ArrayFormat:
    """Declared format of one ``.npy`` member: dtype (``"S"``: fixed-width bytes of any width) and
    shape, each dimension an int or a symbol bound once per clip (``N`` tracks, ``T`` frames,
    ``H`` x ``W`` pixels)."""

    dtype: str
    shape: tuple

    def dtype_ok(self, dtype: np.dtype) -> bool:
        if self.dtype == "S":
            return dtype.kind == "S" and dtype.itemsize >= 1
        return dtype == np.dtype(self.dtype)


#: The members of each clip layout, as written by drivetrack/tracks/writers.py (docs/formats.md);
#: those of :data:`OPTIONAL_MEMBERS` may be absent.
CLIP_FORMATS: dict[str, dict[str, ArrayFormat]] = {
    DRIVETRACK: {
        "video": ArrayFormat("uint8", ("T", "H", "W", 3)),
        "tracks": ArrayFormat("float32", ("N", "T", 2)),
        "visibles": ArrayFormat("bool", ("N", "T")),
        "timestamps_micros": ArrayFormat("int64", ("T",)),
        "query_frames": ArrayFormat("int32", ("N",)),
        "lidar_sources": ArrayFormat("int32", ("N", 4)),
        "points3d": ArrayFormat("float32", ("N", "T", 3)),
        # optional: written when the run kept the occlusion margins (docs/visibility.md)
        "occlusion_margin": ArrayFormat("float16", ("N", "T")),
    },
    TAPVID3D: {
        "images_jpeg_bytes": ArrayFormat("S", ("T",)),
        "tracks_XYZ": ArrayFormat("float32", ("T", "N", 3)),
        "visibility": ArrayFormat("bool", ("T", "N")),
        "queries_xyt": ArrayFormat("float32", ("N", 3)),
        "fx_fy_cx_cy": ArrayFormat("float32", (4,)),
        "extrinsics_w2c": ArrayFormat("float32", ("T", 4, 4)),
        "distortion_k1_k2_p1_p2_k3": ArrayFormat("float32", (5,)),
        "timestamps_micros": ArrayFormat("int64", ("T",)),
    },
}


#: Members of :data:`CLIP_FORMATS` a clip may leave out.
OPTIONAL_MEMBERS = frozenset({"occlusion_margin"})


def _read_header(member) -> tuple[tuple[int, ...], bool, np.dtype, int]:
    version = np.lib.format.read_magic(member)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(member)
    elif version in ((2, 0), (3, 0)):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(member)
    else:
        raise ValueError(f"unsupported .npy format version {version}")
    return tuple(int(s) for s in shape), bool(fortran), dtype, member.tell()


def check_clip_npz(f, where: str, layout: str) -> list[tuple[str, np.dtype, tuple[int, ...]]]:
    """Check an open clip ``.npz`` against :data:`CLIP_FORMATS` ``[layout]`` from headers only.

    Returns ``[(member, dtype, shape)]`` sorted by name. Raises :class:`InvalidSourceError` naming
    the file and the member: not a zip, a member that is not ``<name>.npy`` or is listed twice,
    missing or extra members, object dtypes, dtypes or shapes other than declared, dimensions that
    disagree between members, a member whose stored size differs from what its header declares.
    """
    declared = CLIP_FORMATS[layout]
    found: list[tuple[str, np.dtype, tuple[int, ...]]] = []
    problems: list[str] = []
    try:
        with zipfile.ZipFile(f) as zf:
            infos = zf.infolist()
            names = [i.filename for i in infos]
            for info in infos:
                if not info.filename.endswith(".npy") or "/" in info.filename or names.count(info.filename) > 1:
                    problems.append(f"member {info.filename!r} is not a single '<name>.npy' array")
                    continue
                with zf.open(info) as member:
                    shape, _fortran, dtype, offset = _read_header(member)
                name = info.filename[:-4]
                found.append((name, dtype, shape))
                if dtype.hasobject:
                    problems.append(f"member {name!r} has dtype {dtype.str} (Python objects, loaded by "
                                    f"unpickling); clips hold plain arrays only")
                    continue
                expected = offset + math.prod(shape) * dtype.itemsize
                if info.file_size != expected:
                    problems.append(f"member {name!r}: header declares {dtype.str} {list(shape)} "
                                    f"({expected} bytes with the header), the member holds {info.file_size} bytes")
    except (zipfile.BadZipFile, zipfile.LargeZipFile, ValueError, OSError, EOFError) as e:
        raise InvalidSourceError(f"{where}: not a readable .npz file ({type(e).__name__}: {e})") from e
    have = {n for n, _, _ in found}
    missing, extra = sorted(set(declared) - have - OPTIONAL_MEMBERS), sorted(have - set(declared))
    if missing:
        problems.append(f"missing member(s) {missing}")
    if extra:
        problems.append(f"member(s) {extra} are not part of the {layout} format")
    dims: dict[str, tuple[int, str]] = {}
    for name, dtype, shape in sorted(found):
        fmt = declared.get(name)
        if fmt is None or dtype.hasobject:
            continue
        if not fmt.dtype_ok(dtype):
            problems.append(f"member {name!r} has dtype {dtype.str}, expected {fmt.dtype}")
        if len(shape) != len(fmt.shape):
            problems.append(f"member {name!r} has shape {list(shape)}, expected {list(fmt.shape)}")
            continue
        for axis, (size, want) in enumerate(zip(shape, fmt.shape)):
            if isinstance(want, int):
                if size != want:
                    problems.append(f"member {name!r} has shape {list(shape)}, expected {list(fmt.shape)}")
                    break
            elif want in dims and dims[want][0] != size:
                problems.append(f"member {name!r} has {want}={size} on axis {axis} but {dims[want][1]} has "
                                f"{want}={dims[want][0]} (shape {list(fmt.shape)})")
                break
            else:
                dims.setdefault(want, (size, name))
    if problems:
        raise InvalidSourceError(f"{where}: does not match the declared {layout} clip format "
                                 f"(docs/formats.md): " + "; ".join(problems))
    return sorted(found)


# ---- statistics tables --------------------------------------------------------------------------

def check_stats_table(name: str, data: bytes, where: str) -> None:
    """Refuse a ``stats/{name}.parquet`` that pyarrow cannot read or that lacks the columns the
    gates validate (:mod:`drivetrack.gates.tables`)."""
    import pyarrow.parquet as pq

    from drivetrack.gates.tables import OBJECT_COLUMNS, REJECTION_COLUMNS, SEGMENT_COLUMNS

    required = {"objects": OBJECT_COLUMNS, "segments": SEGMENT_COLUMNS, "rejections": REJECTION_COLUMNS}[name]
    try:
        schema = pq.read_schema(io.BytesIO(data))
    except Exception as e:  # pyarrow raises several types for bad files
        raise InvalidSourceError(f"{where}: cannot be read as parquet ({e})") from e
    missing = [c for c in required if c not in schema.names]
    if missing:
        raise InvalidSourceError(f"{where}: lacks column(s) {missing} (found {schema.names})")


def clips_of_unfinished_segments(clips: list[str], segments_table: bytes | None, where: str) -> list[str]:
    """Clip data files (v2 tables, npz clips) whose segment is not recorded as ``done`` in
    ``stats/segments.parquet`` (failed, or not recorded at all), each with the reason. ``clips``:
    relative paths."""
    if not clips:
        return []
    if segments_table is None:
        return [f"{c}: no stats/segments.parquet records whether its segment finished" for c in clips]
    import pyarrow.parquet as pq

    table = pq.read_table(io.BytesIO(segments_table), columns=["split", "segment", "status"]).to_pydict()
    by_split: dict[str, list[tuple[str, str]]] = {}
    for split, segment, status in zip(table["split"], table["segment"], table["status"]):
        by_split.setdefault(str(split), []).append((str(segment), str(status)))
    for rows in by_split.values():
        rows.sort(key=lambda r: -len(r[0]))  # the longest matching segment name wins
    out = []
    for rel in clips:
        table = parse_table_path(rel)
        if table:
            split = table[1]
            match = next(((seg, st) for seg, st in by_split.get(split, []) if seg == table[2]), None)
        else:
            _layout, split = parse_clip_path(rel)
            stem = rel.rsplit("/", 1)[1]
            match = next(((seg, st) for seg, st in by_split.get(split, []) if stem.startswith(f"waymo_{seg}_")), None)
        if match is None:
            out.append(f"{rel}: its segment is not in {where} (split {split})")
        elif match[1] != "done":
            out.append(f"{rel}: segment {match[0]} is recorded as {match[1]!r} in {where}")
    return out
