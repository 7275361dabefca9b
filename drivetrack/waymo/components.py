"""Open, read and validate one Waymo v2 component file through fsspec.

Layout: ``{root}/{split}/{component}/{segment}.parquet``; ``root`` may be a local path,
``file://``, ``s3://`` (s3fs) or ``gs://`` (gcsfs, when installed), with credentials and endpoints
in ``storage_options``. :class:`ComponentFile` checks every column it reads against the official
type (:func:`drivetrack.waymo.schema.types_compatible`), filters rows to the segment, refuses
duplicate keys and checks the content (:mod:`drivetrack.waymo.checks`). Every problem raises
:class:`WaymoFormatError` naming the file URL, segment, component, column, expected and found value.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Iterator, Sequence

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from drivetrack.names import check_name
from drivetrack.waymo.checks import check_content
from drivetrack.waymo.schema import COMPONENTS, KEY_SEGMENT, component as get_component, types_compatible

__all__ = ["WaymoFormatError", "ComponentFile", "LIDAR_BATCH_ROWS", "filesystem", "check_names",
           "component_url", "list_segments", "read_component"]

#: Rows decoded at once when streaming range-image components (bounds memory: one TOP row of
#: both returns is about 5 MB of float32).
LIDAR_BATCH_ROWS = 16


class WaymoFormatError(ValueError):
    """A Waymo v2 file does not match the official format.

    Attributes ``url``, ``segment``, ``component``, ``column``, ``expected``, ``found`` hold the
    details the message spells out.
    """

    def __init__(self, problem: str, *, url: str, segment: str, component: str, column,
                 expected=None, found=None):
        self.problem, self.url, self.segment, self.component = problem, url, segment, component
        self.column, self.expected, self.found = column, expected, found
        where = f"file {url}, segment {segment!r}, component {component!r}, column {column!r}"
        detail = ""
        if expected is not None or found is not None:
            detail = f"; expected {expected}, found {found}"
        super().__init__(f"{problem} ({where}{detail})")


# --------------------------------------------------------------------------------------------
# Storage


def filesystem(root: str, storage_options: dict | None):
    import fsspec.core

    fs, path = fsspec.core.url_to_fs(str(root), **(storage_options or {}))
    return fs, path.rstrip("/")


def _url(fs, path: str) -> str:
    return fs.unstrip_protocol(path) if "://" not in path else path


def check_names(split: str, segment: str | None = None) -> None:
    """Refuse split and segment names that cannot be part of a path (before any path is built)."""
    check_name("split", split, "the split argument")
    if segment is not None:
        check_name("segment", segment, f"split {split!r}")


def component_url(root: str, split: str, component: str, segment: str,
                  storage_options: dict | None = None) -> str:
    """Full URL of ``{root}/{split}/{component}/{segment}.parquet``."""
    check_names(split, segment)
    fs, base = filesystem(root, storage_options)
    return _url(fs, f"{base}/{split}/{component}/{segment}.parquet")


def list_segments(root: str, split: str, storage_options: dict | None = None) -> list[str]:
    """Sorted segment names present in any known component directory of ``split``.

    Raises FileNotFoundError naming the URL when the split directory does not exist, and
    :class:`drivetrack.names.InvalidNameError` naming the file when a file name is no valid
    segment id (it would become part of output paths). Files starting with ``.`` are skipped.
    """
    check_names(split)
    fs, base = filesystem(root, storage_options)
    split_path = f"{base}/{split}"
    if not fs.isdir(split_path):
        raise FileNotFoundError(f"no split directory {_url(fs, split_path)}")
    segments: set[str] = set()
    for name in COMPONENTS:
        comp_path = f"{split_path}/{name}"
        if not fs.isdir(comp_path):
            continue
        for entry in fs.ls(comp_path, detail=False):
            leaf = entry.rstrip("/").rsplit("/", 1)[-1]
            if leaf.endswith(".parquet") and not leaf.startswith("."):
                segments.add(check_name("segment", leaf[: -len(".parquet")],
                                        f"file {_url(fs, comp_path + '/' + leaf)}"))
    return sorted(segments)



class ComponentFile:
    """One opened, schema-checked component file of one segment."""

    def __init__(self, fs, base: str, split: str, component: str, segment: str):
        check_names(split, segment)
        self.comp = get_component(component)
        self.segment = segment
        self.path = f"{base}/{split}/{component}/{segment}.parquet"
        self.url = _url(fs, self.path)
        try:
            self._handle = fs.open(self.path, "rb")
        except FileNotFoundError:
            raise self.error("missing component file", column=list(self.comp.keys),
                             expected="a parquet file", found="no such file") from None
        try:
            self.parquet = pq.ParquetFile(self._handle)
            self.schema = self.parquet.schema_arrow
        except (pa.ArrowException, OSError) as exc:
            self.close()
            raise self.error("truncated or corrupt parquet file", column="(file footer)",
                             expected="a readable parquet file", found=str(exc)) from None

    def close(self):
        self._handle.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def error(self, problem: str, column, expected=None, found=None) -> WaymoFormatError:
        return WaymoFormatError(problem, url=self.url, segment=self.segment,
                                component=self.comp.name, column=column, expected=expected,
                                found=found)

    def columns(self, wanted: Sequence[str] | None) -> list[str]:
        """Key columns + ``wanted`` (default: every official column), validated."""
        names = list(self.comp.keys)
        for name in (wanted if wanted is not None else [c.name for c in self.comp.columns]):
            if name not in names:
                names.append(name)
        official = self.comp.by_name
        for name in names:
            if name not in official:
                raise self.error("not a column of the official schema", column=name,
                                 expected=f"one of {sorted(official)}", found=name)
            idx = self.schema.get_field_index(name)
            if idx < 0:
                raise self.error("missing column", column=name, expected=str(official[name].type),
                                 found="no such column")
            found = self.schema.field(idx).type
            if not types_compatible(official[name].type, found):
                raise self.error("wrong column type", column=name,
                                 expected=str(official[name].type), found=str(found))
        return names

    def read_keys(self) -> pa.Table:
        """The key columns of this segment's rows; checks presence and uniqueness."""
        keys = self.columns([])
        table = self._read(keys)
        table = self._filter(table)
        if table.num_rows == 0:
            raise self.error("segment absent from the component file", column=KEY_SEGMENT,
                             expected=repr(self.segment), found="no rows with that value")
        self._check_unique(table)
        return table

    def _read(self, columns: list[str]) -> pa.Table:
        try:
            return self.parquet.read(columns=columns)
        except (pa.ArrowException, OSError) as exc:
            raise self._read_error(exc, columns) from None

    def _read_error(self, exc: Exception, columns: list[str]) -> WaymoFormatError:
        """Name the failing column where possible (pyarrow reads them all at once)."""
        if "Expected all lists to be of size" in str(exc):
            # apache/arrow#35692: pyarrow < 23 cannot read null rows of a fixed_size_list column.
            for name in columns:
                if pa.types.is_fixed_size_list(self.schema.field(name).type):
                    try:
                        self.parquet.read(columns=[name])
                    except pa.ArrowException:
                        return self.error(
                            "null rows in a fixed_size_list column (this pyarrow cannot read "
                            "them, apache/arrow#35692)", column=name,
                            expected=str(self.comp.by_name[name].type) + " without null rows",
                            found=str(exc))
        return self.error("truncated or corrupt parquet file", column=columns,
                          expected="readable column chunks", found=str(exc))

    def _filter(self, data):
        mask = pc.fill_null(pc.equal(data[KEY_SEGMENT], self.segment), False)
        if pc.all(mask).as_py() is not False and data.num_rows:
            return data  # the usual case: one segment per file; filtering would copy it all
        return data.filter(mask)

    def _check_unique(self, keys: pa.Table) -> None:
        names = list(self.comp.keys)
        counts = keys.select(names).group_by(names).aggregate([([], "count_all")])
        dup = counts.filter(pc.greater(counts["count_all"], 1))
        if dup.num_rows:
            first = {n: dup[n][0].as_py() for n in names}
            raise self.error("duplicate key", column=names, expected="unique keys",
                             found=f"{dup['count_all'][0].as_py()} rows with {first}")

    def iter_batches(self, columns: list[str], batch_rows: int) -> Iterator[pa.Table]:
        """Validated tables of at most ``batch_rows`` rows of this segment (columns checked).

        The next batch is decoded and checked on a helper thread while the caller works on the
        current one (pyarrow decodes without holding the GIL), so at most two batches are held at
        once. Errors of either thread are raised here, in the caller's thread.
        """
        batches = self.parquet.iter_batches(batch_size=batch_rows, columns=columns)

        def next_table() -> pa.Table | None:
            for batch in batches:
                table = self._filter(pa.Table.from_batches([batch]))
                if table.num_rows:
                    check_content(self, table)
                    return table
            return None

        with ThreadPoolExecutor(1, thread_name_prefix=f"read-{self.comp.name}") as pool:
            pending = pool.submit(next_table)
            while True:
                try:
                    table = pending.result()
                except (pa.ArrowException, OSError) as exc:
                    raise self._read_error(exc, columns) from None
                if table is None:
                    return
                pending = pool.submit(next_table)
                yield table

    def read(self, columns: list[str]) -> pa.Table:
        table = self._filter(self._read(columns))
        if table.num_rows == 0:
            raise self.error("segment absent from the component file", column=KEY_SEGMENT,
                             expected=repr(self.segment), found="no rows with that value")
        self._check_unique(table)
        check_content(self, table)
        return table

    def row_keys(self, table: pa.Table, i: int) -> dict:
        return {n: table[n][i].as_py() for n in self.comp.keys if n != KEY_SEGMENT}


def _open(root, split, component, segment, storage_options):
    fs, base = filesystem(root, storage_options)
    return ComponentFile(fs, base, split, component, segment)


def read_component(root: str, split: str, component: str, segment: str,
                   columns: Sequence[str] | None = None,
                   storage_options: dict | None = None) -> pa.Table:
    """Rows of ``segment`` from ``{root}/{split}/{component}/{segment}.parquet``.

    Args:
        columns: full column names to read (default: every official column); the key columns
            are always included and come first.
    Returns:
        A pyarrow Table with the file's own arrow types (list child names and large variants are
        left as found; the decoders accept them all).
    Raises:
        WaymoFormatError: missing file, truncated/corrupt parquet, missing column, wrong type,
            segment absent, duplicate keys, NaN in a transform, empty range image, or a
            range-image shape that does not match its values length.
    """
    with _open(root, split, component, segment, storage_options) as f:
        return f.read(f.columns(columns))

