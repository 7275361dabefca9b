"""Writing files through fsspec: atomically, with parents created, errors naming the URL.

One place for the "write a local temporary file, then move or upload it" pattern, so that a
reader never sees a half-written file (local: ``os.replace`` in the same folder; remote:
``put_file`` of a complete file), and for the project's npz writer and its header-first reader
(:class:`NpzReader`, :func:`read_npz_headers`: check what a member declares before allocating it).
"""
from __future__ import annotations

import contextlib
import io
import json
import math
import os
import tempfile
import zipfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import NamedTuple

import fsspec
import numpy as np

__all__ = ["is_local", "atomic_local_path", "write_bytes", "write_json", "write_parquet", "read_json",
           "write_npz", "StreamedArray", "NPZ_DATE_TIME", "NpyHeader", "NpzReader",
           "read_npz_headers", "PARTIAL_PREFIX"]

#: Name prefix of the temporary files atomic local writes create beside their target (removed by
#: :func:`drivetrack.tidy.remove_partial_files` when a killed process left them).
PARTIAL_PREFIX = ".partial-"

#: Fixed timestamp of every npz member, so identical arrays give identical bytes (and sha256).
NPZ_DATE_TIME = (1980, 1, 1, 0, 0, 0)


def _file_mode() -> int:
    """Mode of a new regular file under this process's umask (``open`` would give it).

    ``tempfile.mkstemp`` creates files 0600 whatever the umask; the files it stands in for are
    outputs that other users (a web server, a release publisher) must read. Read once at import;
    ``os.umask`` only reads by setting, so it is restored at once.
    """
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


#: Permission bits of the files written atomically here (``0o666`` minus the umask at import).
FILE_MODE = _file_mode()


def is_local(fs) -> bool:
    """Whether the fsspec filesystem ``fs`` is the local disk (paths are OS paths)."""
    protocols = fs.protocol if isinstance(fs.protocol, tuple) else (fs.protocol,)
    return "file" in protocols or "local" in protocols


@contextlib.contextmanager
def atomic_local_path(url: str, suffix: str = "", storage_options: dict | None = None):
    """Yield a local path to write; on success it becomes ``url`` (any fsspec URL) whole.

    Parents are created. Any error while writing or moving raises OSError naming ``url``,
    except a ValueError (bad data, which its message names) that propagates as it is; the
    temporary file is always removed.
    """
    fs, path = fsspec.core.url_to_fs(str(url), **(storage_options or {}))
    parent = path.rsplit("/", 1)[0] if "/" in path else ""
    local = is_local(fs)
    if local:
        os.makedirs(parent or ".", exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=PARTIAL_PREFIX, suffix=suffix, dir=parent or ".")
    else:
        fd, tmp = tempfile.mkstemp(prefix="drivetrack-", suffix=suffix)
    os.fchmod(fd, FILE_MODE)
    os.close(fd)
    try:
        yield tmp
        if local:
            os.replace(tmp, path)
        else:
            if parent:
                fs.makedirs(parent, exist_ok=True)
            fs.put_file(tmp, path)
    except ValueError:
        raise
    except Exception as error:
        raise OSError(f"could not write {url}: {error}") from error
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def write_bytes(url: str, data: bytes, storage_options: dict | None = None) -> str:
    """Write ``data`` at ``url`` (any fsspec URL) whole or not at all; returns ``url``.

    Local: a temporary file in the same folder, then ``os.replace``; object stores: one
    ``put_file`` of a complete local file. Parents are created; errors raise OSError naming ``url``.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TypeError(f"{url}: write_bytes needs bytes, got {type(data).__name__}")
    with atomic_local_path(url, "", storage_options) as tmp:
        with open(tmp, "wb") as handle:
            handle.write(data)
    return url


def write_json(url: str, doc, *, indent: int | None = 1, sort_keys: bool = False, default=None,
               storage_options: dict | None = None) -> str:
    """Write ``doc`` as JSON text (``json.dumps`` with these options, UTF-8) at ``url``,
    atomically (:func:`write_bytes`); returns ``url``. A value JSON cannot hold raises
    ValueError naming ``url`` and nothing is written."""
    try:
        text = json.dumps(doc, indent=indent, sort_keys=sort_keys, default=default)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{url}: cannot be written as JSON ({type(error).__name__}: {error})") from error
    return write_bytes(url, text.encode("utf-8"), storage_options)


def write_parquet(url: str, table, storage_options: dict | None = None) -> str:
    """Write a pandas DataFrame (without its index) or a pyarrow Table as parquet at ``url``,
    atomically (:func:`write_bytes`); returns ``url``."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    buffer = io.BytesIO()
    try:
        if isinstance(table, pa.Table):
            pq.write_table(table, buffer)
        else:
            table.to_parquet(buffer, index=False)
    except (TypeError, ValueError, pa.ArrowException) as error:
        raise ValueError(f"{url}: cannot be written as parquet ({type(error).__name__}: {error})") from error
    return write_bytes(url, buffer.getvalue(), storage_options)


def read_json(url: str, storage_options: dict | None = None, *, missing_ok: bool = False):
    """The JSON document at ``url``. A missing file: None with ``missing_ok``, else
    FileNotFoundError naming ``url``. A file that is not valid UTF-8 JSON is an error, never
    None: ValueError naming ``url`` (a record written by :func:`write_json` is never half there)."""
    fs, path = fsspec.core.url_to_fs(str(url), **(storage_options or {}))
    try:
        data = fs.cat_file(path)
    except FileNotFoundError:
        if missing_ok:
            return None
        raise FileNotFoundError(f"{url} does not exist") from None
    try:
        return json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{url}: not a valid JSON document ({type(error).__name__}: {error})") from None


@dataclass(frozen=True)
class StreamedArray:
    """An array produced in pieces at write time, for :func:`write_npz` (never held whole).

    Attributes:
        shape: the whole array's shape (at least one dimension).
        dtype: its dtype (no object dtype).
        chunks: ``chunks()`` yields C-order pieces along axis 0 whose concatenation is the
            array: each piece has ``dtype`` exactly and shape ``(k,) + shape[1:]``, the k summing
            to ``shape[0]``. Called once per write.
    """
    shape: tuple
    dtype: np.dtype
    chunks: Callable[[], Iterable[np.ndarray]]

    def __post_init__(self):
        object.__setattr__(self, "shape", tuple(int(s) for s in self.shape))
        object.__setattr__(self, "dtype", np.dtype(self.dtype))
        if not self.shape:
            raise ValueError("StreamedArray needs at least one dimension (it is produced along axis 0)")


def _write_array(member, url: str, key: str, value) -> None:
    """One ``.npy`` member: ``np.lib.format.write_array``'s bytes, the data streamed when lazy."""
    if isinstance(value, np.ndarray):
        np.lib.format.write_array(member, np.ascontiguousarray(value), allow_pickle=False)
        return
    header = {"descr": np.lib.format.dtype_to_descr(value.dtype), "fortran_order": False, "shape": value.shape}
    try:   # the version write_array picks: 1.0 unless the header does not fit
        np.lib.format.write_array_header_1_0(member, header)
    except ValueError:
        np.lib.format.write_array_header_2_0(member, header)
    rows, tail = 0, value.shape[1:]
    for i, chunk in enumerate(value.chunks()):
        if not isinstance(chunk, np.ndarray) or chunk.dtype != value.dtype or chunk.shape[1:] != tail \
                or rows + chunk.shape[0] > value.shape[0]:
            got = (f"{chunk.dtype} {chunk.shape}" if isinstance(chunk, np.ndarray) else type(chunk).__name__)
            raise ValueError(f"{url}: array {key!r} is declared {value.dtype} {value.shape}, but chunk {i} "
                             f"(after {rows} rows) is {got}")
        rows += chunk.shape[0]
        member.write(np.ascontiguousarray(chunk).reshape(-1).view(np.uint8))
    if rows != value.shape[0]:
        raise ValueError(f"{url}: array {key!r} is declared {value.dtype} {value.shape}, but its chunks "
                         f"gave {rows} rows")


def write_npz(url: str, arrays: dict[str, np.ndarray | StreamedArray], compresslevel: int = 1,
              storage_options: dict | None = None) -> str:
    """Write ``arrays`` as a compressed npz at ``url``, atomically and deterministically.

    The file is what ``np.savez_compressed`` writes (a zip of deflated ``<key>.npy`` members)
    with a chosen deflate level (level 1 is several times faster than numpy's fixed 6 on video
    frames) and fixed member timestamps. Arrays stream to the file (nothing is buffered whole);
    a :class:`StreamedArray` is produced chunk by chunk while it is written, and gives the same
    bytes as the whole array would. A chunk of the wrong dtype or shape, or chunks that do not
    add up to the declared shape, raise ValueError naming ``url`` and the key, and nothing is
    written. Object arrays are refused: the file must load with ``allow_pickle=False``. Returns
    ``url``.
    """
    for key, value in arrays.items():
        if isinstance(value, StreamedArray):
            bad = value.dtype == object
        else:
            bad = not isinstance(value, np.ndarray) or value.dtype == object
        if bad:
            raise ValueError(f"{url}: array {key!r} is {type(value).__name__}"
                             f"{' of dtype object' if getattr(value, 'dtype', None) == object else ''}; "
                             f"only plain numpy arrays can be written without pickle")
    with atomic_local_path(url, ".npz", storage_options) as tmp:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=compresslevel) as archive:
            for key, value in arrays.items():
                info = zipfile.ZipInfo(f"{key}.npy", date_time=NPZ_DATE_TIME)
                info.compress_type = zipfile.ZIP_DEFLATED
                # the member's deflate level (ZipInfo attribute; public as compress_level from 3.13)
                setattr(info, "compress_level" if hasattr(info, "compress_level") else "_compresslevel",
                        compresslevel)
                with archive.open(info, "w", force_zip64=True) as member:
                    _write_array(member, url, key, value)
    return url


# ------------------------------------------------------------------------------------------------
# Reading npz files header first
# ------------------------------------------------------------------------------------------------

#: Deflate cannot expand data by more than about 1032:1 (258-byte matches in 2-bit codes); a
#: member declaring more uncompressed bytes than this bound allows lies in its zip directory.
_DEFLATE_MAX_RATIO = 1032


class NpyHeader(NamedTuple):
    """What one ``.npy`` member of an npz declares (read without touching its data).

    Attributes:
        dtype: the declared dtype (never an object dtype: those are refused).
        shape: the declared shape.
        fortran_order: the declared memory order.
        data_offset: bytes of magic and header before the data, in the uncompressed member.
        nbytes: bytes of data, ``prod(shape) * dtype.itemsize`` (checked equal to the member's
            uncompressed size minus ``data_offset``).
    """
    dtype: np.dtype
    shape: tuple
    fortran_order: bool
    data_offset: int
    nbytes: int


class _Counting:
    """A read-only stream wrapper that counts the bytes read (the npy header's length)."""

    def __init__(self, stream):
        self.stream, self.count = stream, 0

    def read(self, size: int = -1) -> bytes:
        data = self.stream.read(size)
        self.count += len(data)
        return data


class NpzReader:
    """An npz opened for reading member by member, each header checked before its data.

    ``NpzReader(source, where)`` takes a path, a URL (through fsspec) or a seekable binary file
    object; ``where`` names it in errors (default: the path). Use as a context manager::

        with NpzReader(url) as npz:
            header = npz.header("tracks")          # NpyHeader, from the member's first bytes
            ... check header.dtype / header.shape against what the caller expects ...
            tracks = npz.load("tracks")            # allocates header.nbytes, then reads

    Every error is a ValueError naming the file and the member: not a zip, a member that is
    not an ``.npy`` array, a name present twice, a compression other than stored or deflate,
    an object (pickled) dtype, a negative dimension, a declared size that differs from the
    member's uncompressed size (``ZipInfo.file_size``) or that the compressed bytes cannot
    hold, truncated or corrupt data. Members are named as ``np.load`` names them (``tracks``
    for ``tracks.npy``). Only the members asked for are read.
    """

    def __init__(self, source, where: str | None = None, storage_options: dict | None = None):
        self.where = where if where is not None else str(getattr(source, "name", source))
        self._owned = None
        if isinstance(source, (str, os.PathLike)):
            fs, path = fsspec.core.url_to_fs(str(source), **(storage_options or {}))
            try:
                self._owned = fs.open(path, "rb")
            except FileNotFoundError:
                raise FileNotFoundError(f"{self.where} does not exist") from None
            handle = self._owned
        else:
            handle = source
        try:
            handle.seek(0, os.SEEK_END)
            self._size = handle.tell()
            handle.seek(0)
            self._zip = zipfile.ZipFile(handle)
        except Exception as error:
            self.close()
            raise ValueError(f"{self.where}: not a readable npz archive ({type(error).__name__}: {error})") \
                from error
        self._members: dict[str, zipfile.ZipInfo] = {}
        for info in self._zip.infolist():
            name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            if name in self._members:
                self.close()
                raise ValueError(f"{self.where}: member {name!r} appears twice in the archive "
                                 f"({self._members[name].filename}, {info.filename}); refusing to guess which")
            self._members[name] = info
        self._headers: dict[str, NpyHeader] = {}

    @property
    def files(self) -> list[str]:
        """Member names, as ``np.load(...).files`` gives them."""
        return list(self._members)

    def __contains__(self, name: str) -> bool:
        return name in self._members

    def __enter__(self) -> "NpzReader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if getattr(self, "_zip", None) is not None:
            self._zip.close()
        if self._owned is not None:
            self._owned.close()
            self._owned = None

    def _info(self, name: str) -> zipfile.ZipInfo:
        if name not in self._members:
            raise ValueError(f"{self.where}: has no member {name!r}; has {sorted(self._members)}")
        info = self._members[name]
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            raise ValueError(f"{self.where}: member {name!r} uses zip compression method {info.compress_type}; "
                             f"npz files are stored or deflated")
        if info.compress_size > self._size:
            raise ValueError(f"{self.where}: member {name!r} declares {info.compress_size:,} compressed bytes, "
                             f"more than the whole file ({self._size:,} bytes)")
        limit = info.compress_size if info.compress_type == zipfile.ZIP_STORED \
            else info.compress_size * _DEFLATE_MAX_RATIO + 1024
        if info.file_size > limit:
            raise ValueError(f"{self.where}: member {name!r} declares {info.file_size:,} uncompressed bytes from "
                             f"{info.compress_size:,} compressed bytes, more than "
                             f"{'stored' if info.compress_type == zipfile.ZIP_STORED else 'deflate'} data can hold")
        return info

    def header(self, name: str) -> NpyHeader:
        """The checked :class:`NpyHeader` of member ``name`` (reads only its first bytes)."""
        if name in self._headers:
            return self._headers[name]
        info = self._info(name)
        where = f"{self.where}: member {name!r}"
        try:
            with self._zip.open(info) as member:
                counting = _Counting(member)
                version = np.lib.format.read_magic(counting)
                if version == (1, 0):
                    shape, fortran_order, dtype = np.lib.format.read_array_header_1_0(counting)
                elif version == (2, 0):
                    shape, fortran_order, dtype = np.lib.format.read_array_header_2_0(counting)
                else:
                    raise ValueError(f"npy format version {version[0]}.{version[1]} is not supported (1.0, 2.0)")
        except (ValueError, EOFError, zipfile.BadZipFile, OSError) as error:
            raise ValueError(f"{where} is not a readable .npy array ({type(error).__name__}: {error})") from None
        dtype = np.dtype(dtype)
        if dtype.hasobject:
            raise ValueError(f"{where} has dtype {dtype} (pickled Python objects); refused: npz data must be "
                             f"plain numeric arrays that load without pickle")
        if any(int(d) < 0 for d in shape):
            raise ValueError(f"{where} declares a negative dimension in shape {tuple(shape)}")
        shape = tuple(int(d) for d in shape)
        nbytes = math.prod(shape) * dtype.itemsize
        stored = info.file_size - counting.count
        if nbytes != stored:
            raise ValueError(f"{where} declares {dtype} {shape} = {nbytes:,} bytes of data, but the member holds "
                             f"{stored:,} bytes after its header; refused before reading")
        header = NpyHeader(dtype, shape, bool(fortran_order), counting.count, nbytes)
        self._headers[name] = header
        return header

    def load(self, name: str) -> np.ndarray:
        """Member ``name`` as an array: its header is checked first (see :meth:`header`)."""
        header = self.header(name)
        where = f"{self.where}: member {name!r}"
        try:
            with self._zip.open(self._members[name]) as member:
                array = np.lib.format.read_array(member, allow_pickle=False)
        except (ValueError, EOFError, zipfile.BadZipFile, OSError) as error:
            raise ValueError(f"{where}: could not read its {header.dtype} {header.shape} data "
                             f"({type(error).__name__}: {error})") from None
        if array.shape != header.shape or array.dtype != header.dtype:
            raise ValueError(f"{where}: read {array.dtype} {array.shape}, header declared {header.dtype} "
                             f"{header.shape}")
        return array


def read_npz_headers(source, names: Iterable[str] | None = None, where: str | None = None,
                     storage_options: dict | None = None) -> dict[str, NpyHeader]:
    """``{member: NpyHeader(dtype, shape, ...)}`` of an npz, no array data read.

    ``source``: path, URL or seekable binary file; ``names``: only these members (default all).
    Raises ValueError naming the file and member on anything :class:`NpzReader` refuses.
    """
    with NpzReader(source, where, storage_options) as npz:
        return {name: npz.header(name) for name in (npz.files if names is None else names)}
