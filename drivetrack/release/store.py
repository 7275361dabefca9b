"""The release store: one URL-based storage layer over fsspec, plus conditional writes.

A store URL names a folder (``./store``, ``file:///abs/store``), an S3 prefix
(``s3://bucket/prefix``; endpoint and credentials from the standard AWS environment and config,
or ``endpoint_url=`` for S3-compatible servers) or a GCS prefix (``gs://bucket/prefix``, needs
gcsfs). Every path a :class:`Store` method takes is relative to the store root, ``/``-separated.

Besides plain reads and writes, publishing needs two conditional writes that object stores
offer natively and local folders emulate:

- :meth:`Store.put_if_absent`: create an object only if it does not exist (S3 ``If-None-Match: *``;
  local ``link(2)`` of a fully written temporary file, so the object is never seen half-written).
- :meth:`Store.compare_and_swap`: replace an object only if it still holds the value read before
  (S3 ``If-Match: <ETag>``; local: a lock file created with ``O_EXCL`` around read-compare-
  ``rename(2)``).

The backends are a registry keyed by fsspec protocol (:data:`CONDITIONAL_BACKENDS`).
"""
from __future__ import annotations

import hashlib
import os
import random
import re
import time
import uuid
from dataclasses import dataclass, field
from typing import Any, Iterator

import fsspec

from drivetrack.release.errors import (CasConflictError, LockTimeoutError, UnsafeStorePathError,
                                       UnsupportedStoreError)

TMP_DIR = "_tmp"
"""Folder under a local store's root that holds the temporary files of atomic writes."""

CHUNK_BYTES = 8 * 2**20
"""Streaming chunk size for hashing, uploads and downloads (8 MiB)."""

S3_BLOCK_BYTES = 16 * 2**20
"""Multipart part size of S3 uploads (S3 needs at least 5 MiB per part)."""


_PARENT_RETRIES = 20

_UNSAFE_CHARS = re.compile(r"[\x00-\x1f\x7f\\]")
"""Control characters and backslashes: never part of a store path."""


def check_store_path(rel, where: str) -> str:
    """Return ``rel`` if it is a safe path relative to a store root, else raise :class:`UnsafeStorePathError`.

    Safe: a ``str``, empty (the root itself) or ``/``-separated parts that are none of ``""``,
    ``.`` and ``..`` (so no absolute path, no ``a//b``, no trailing ``/``), without control
    characters or backslashes. Checked by every :class:`Store` method before it builds a path, so
    the store never reaches outside its root whatever name a caller passes (names are checked
    earlier too, with :mod:`drivetrack.names`; this is the second line).
    """
    if isinstance(rel, str) and (rel == "" or (
            _UNSAFE_CHARS.search(rel) is None
            and all(part not in ("", ".", "..") for part in rel.split("/")))):
        return rel
    raise UnsafeStorePathError(
        f"{where}: path {rel!r} is not allowed in a store (relative '/'-separated parts only: no "
        f"absolute path, no empty, '.' or '..' parts, no backslashes or control characters)")


def _with_parents(p: str, create):
    """Run ``create()`` (which makes the file ``p``) after creating ``p``'s parent folders.

    Local stores remove folders that become empty (:meth:`Store.prune_empty`), and another
    publish may do that between our ``makedirs`` and ``create``: the create then fails with
    ``FileNotFoundError``. Re-creating the parents and trying again is safe because the
    creates used here are either exclusive or replace whole files. Not needed for a rename or
    link from a temporary file in the same folder: that file keeps the folder non-empty.
    """
    for attempt in range(_PARENT_RETRIES):
        last = attempt == _PARENT_RETRIES - 1
        if attempt >= 2:  # step out of the way of a pruner that keeps winning
            time.sleep(random.uniform(0.0, 0.001 * attempt))
        try:
            os.makedirs(os.path.dirname(p), exist_ok=True)
        except (FileNotFoundError, FileExistsError):
            # makedirs races with a prune too: a parent vanished after its check (ENOENT), or
            # a folder existed at mkdir and was gone at the isdir check (EEXIST).
            if last:
                raise
            continue
        try:
            return create()
        except FileNotFoundError:
            # A missing source (``os.replace``) fails the same way: it is raised after the
            # retries (about 0.2 s in all).
            if last:
                raise


def iter_chunks(f, chunk_bytes: int = CHUNK_BYTES) -> Iterator[memoryview]:
    """Yield successive chunks of an open binary file, reusing one buffer when ``readinto`` exists.

    The yielded memoryview is only valid until the next iteration.
    """
    readinto = getattr(f, "readinto", None)
    if readinto is not None:
        buf = bytearray(chunk_bytes)
        view = memoryview(buf)
        while True:
            n = readinto(view)
            if not n:
                return
            yield view[:n]
    else:
        while True:
            data = f.read(chunk_bytes)
            if not data:
                return
            yield memoryview(data)


@dataclass
class Store:
    """An fsspec filesystem plus a root path; all release I/O goes through it.

    ``url`` is the normalised store URL, ``root`` the root path in fsspec's form for ``fs``
    (absolute local path, or ``bucket/prefix``).
    """

    url: str
    fs: Any
    root: str
    protocol: str
    storage_options: dict = field(default_factory=dict)

    # ---- paths -------------------------------------------------------------------------
    def path(self, rel: str) -> str:
        """fsspec path of ``rel`` (a ``/``-separated path relative to the store root; see
        :func:`check_store_path`, which raises :class:`UnsafeStorePathError` for anything else)."""
        check_store_path(rel, f"store {self.url}")
        return f"{self.root}/{rel}" if rel else self.root

    def url_of(self, rel: str) -> str:
        """Full URL of ``rel`` (for messages and cards); ``rel`` is checked as in :meth:`path`."""
        check_store_path(rel, f"store {self.url}")
        return f"{self.url}/{rel}" if rel else self.url

    @property
    def is_local(self) -> bool:
        return self.protocol == "file"

    def local_tmp(self, rel: str) -> str:
        """A fresh temporary file name for writing ``rel`` atomically on a local store.

        Temporaries live in ``{root}/_tmp/``, never beside their target: a process killed between
        writing one and renaming or linking it into place leaves nothing inside a release folder
        (where ``verify`` would count it as an extra file) or a dataset folder. ``link(2)`` and
        ``rename(2)`` from there need the store on one filesystem. ``gc`` removes stale ones.
        """
        name = rel.rsplit("/", 1)[-1]
        return os.path.join(self.root, TMP_DIR, f"{name}.tmp-{uuid.uuid4().hex}")

    def _check_inside(self, p: str) -> None:
        """Refuse a local delete whose real path (symlinks resolved) leaves the store root."""
        root = os.path.realpath(self.root)
        real = os.path.realpath(p)
        if real != root and not real.startswith(root + os.sep):
            raise UnsafeStorePathError(f"store {self.url}: {p} resolves to {real}, outside the store "
                                       f"root {root} (a symbolic link?); not deleting it")

    # ---- reads ---------------------------------------------------------------------------
    def exists(self, rel: str) -> bool:
        p = self.path(rel)
        if self.is_local:
            return os.path.exists(p)
        self.fs.invalidate_cache(p)
        if self.protocol == "s3":  # one HEAD, no directory listing fallback: objects only
            bucket, key, _ = self.fs.split_path(p)
            try:
                self.fs.call_s3("head_object", Bucket=bucket, Key=key)
                return True
            except FileNotFoundError:
                return False
        return self.fs.exists(p)

    def size(self, rel: str) -> int:
        p = self.path(rel)
        if self.is_local:
            return os.stat(p).st_size
        self.fs.invalidate_cache(p)
        return int(self.fs.info(p)["size"])

    def read_bytes(self, rel: str) -> bytes:
        p = self.path(rel)
        if self.is_local:
            with open(p, "rb") as f:
                return f.read()
        return self.fs.cat_file(p)

    def open_read(self, rel: str):
        """Open for streaming reads (sequential, chunk-sized ranged GETs on object stores)."""
        p = self.path(rel)
        if self.is_local:
            return open(p, "rb", buffering=0)
        return self.fs.open(p, "rb", block_size=CHUNK_BYTES, cache_type="none")

    def find(self, rel: str) -> dict[str, int]:
        """All files below ``rel``: ``{path relative to rel: size}`` (empty if ``rel`` is absent)."""
        base = self.path(rel)
        out: dict[str, int] = {}
        if self.is_local:
            if not os.path.isdir(base):
                return out
            for dirpath, _dirs, files in os.walk(base):
                for name in files:
                    full = os.path.join(dirpath, name)
                    out[os.path.relpath(full, base).replace(os.sep, "/")] = os.stat(full).st_size
            return out
        self.fs.invalidate_cache(base)
        try:
            found = self.fs.find(base, detail=True)
        except FileNotFoundError:
            return out
        for p, info in found.items():
            if info.get("type") == "directory":
                continue
            rel_p = p[len(base):].lstrip("/")
            if rel_p:
                out[rel_p] = int(info.get("size") or 0)
        return out

    def list_dirs(self, rel: str) -> list[str]:
        """Names of the immediate sub-folders of ``rel`` (sorted; empty if absent)."""
        base = self.path(rel)
        if self.is_local:
            if not os.path.isdir(base):
                return []
            return sorted(e.name for e in os.scandir(base) if e.is_dir())
        self.fs.invalidate_cache(base)
        try:
            entries = self.fs.ls(base, detail=True)
        except FileNotFoundError:
            return []
        return sorted(e["name"].rstrip("/").rsplit("/", 1)[-1] for e in entries
                      if e.get("type") == "directory")

    # ---- writes ----------------------------------------------------------------------------
    def open_write(self, rel: str):
        """Open for streaming writes, creating parents (multipart upload on S3)."""
        p = self.path(rel)
        if self.is_local:
            return _with_parents(p, lambda: open(p, "wb"))
        if self.protocol == "s3":
            return self.fs.open(p, "wb", block_size=S3_BLOCK_BYTES)
        return self.fs.open(p, "wb")

    def write_bytes(self, rel: str, data: bytes) -> None:
        """Unconditional write (staging only; committed objects go through the conditional writes)."""
        p = self.path(rel)
        if self.is_local:
            tmp = self.local_tmp(rel)
            with _with_parents(tmp, lambda: open(tmp, "wb")) as f:
                f.write(data)
            _with_parents(p, lambda: os.replace(tmp, p))
            return
        self.fs.pipe_file(p, data)

    def delete(self, rel: str) -> None:
        """Delete one object; absent is fine."""
        p = self.path(rel)
        try:
            if self.is_local:
                self._check_inside(os.path.dirname(p))
                os.unlink(p)
            else:
                self.fs.rm_file(p)
        except FileNotFoundError:
            pass

    def delete_tree(self, rel: str) -> int:
        """Delete every object below ``rel``; returns how many were deleted."""
        files = self.find(rel)
        if self.is_local:
            import shutil
            if os.path.isdir(self.path(rel)):
                self._check_inside(self.path(rel))
                shutil.rmtree(self.path(rel))
            # Parents stay even when empty: ``_staging`` is shared by concurrent publishes of
            # other versions, and removing it under them is a race. Callers prune explicitly.
            return len(files)
        if not files:
            return 0
        else:
            self.fs.rm([self.path(f"{rel}/{f}") for f in files])
        return len(files)

    def prune_empty(self, rel: str) -> None:
        """Remove the local folder ``rel`` and then its parents, each only while it is empty.

        Object stores have no empty folders, so this is a no-op there. ``rmdir(2)`` fails on a
        folder that is not empty, so a folder another publish has just written into stays; the
        writers re-create parents that vanish between their ``makedirs`` and their create.
        """
        if not self.is_local or not rel:
            return
        folder = self.path(rel)
        while folder.startswith(self.root + os.sep):
            try:
                os.rmdir(folder)
            except OSError:  # not empty, absent or not ours to remove: stop
                break
            folder = os.path.dirname(folder)

    def move(self, src: str, dst: str) -> None:
        """Move one object: ``rename(2)`` locally, server-side copy then delete on object stores."""
        ps, pd = self.path(src), self.path(dst)
        if self.is_local:
            _with_parents(pd, lambda: os.replace(ps, pd))
            return
        self.fs.cp_file(ps, pd)  # server-side copy, no listing
        self.fs.rm_file(ps)

    def make_read_only(self, rel: str) -> None:
        """Drop write permission on a committed local file (a guard; object stores skip this)."""
        if self.is_local:
            p = self.path(rel)
            os.chmod(p, os.stat(p).st_mode & ~0o222)

    # ---- conditional writes ------------------------------------------------------------
    def put_if_absent(self, rel: str, data: bytes) -> None:
        """Create ``rel`` with ``data`` only if it does not exist; else raise ``FileExistsError``."""
        _backend(self).put_if_absent(self, rel, data)

    def read_with_token(self, rel: str) -> tuple[bytes | None, str | None]:
        """Current content of ``rel`` and an opaque token of that content (``(None, None)`` if absent)."""
        return _backend(self).read_with_token(self, rel)

    def compare_and_swap(self, rel: str, data: bytes, expected_token: str | None) -> None:
        """Write ``data`` to ``rel`` only if its current token is ``expected_token``.

        ``expected_token=None`` means "only if absent". Raises :class:`CasConflictError` otherwise.
        """
        _backend(self).compare_and_swap(self, rel, data, expected_token)


# ---- conditional-write backends ---------------------------------------------------------

class LocalConditional:
    """Local folders: ``link(2)`` for create-only, a lock file plus ``rename(2)`` for CAS."""

    lock_timeout_s = 10.0

    @staticmethod
    def _write_tmp(store: Store, rel: str, data: bytes) -> str:
        tmp = store.local_tmp(rel)
        with _with_parents(tmp, lambda: open(tmp, "wb")) as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        return tmp

    def put_if_absent(self, store: Store, rel: str, data: bytes) -> None:
        p = store.path(rel)
        tmp = self._write_tmp(store, rel, data)
        try:
            # atomic and exclusive: fails with FileExistsError if p exists
            _with_parents(p, lambda: os.link(tmp, p))
        finally:
            os.unlink(tmp)

    def read_with_token(self, store: Store, rel: str) -> tuple[bytes | None, str | None]:
        try:
            with open(store.path(rel), "rb") as f:
                data = f.read()
        except FileNotFoundError:
            return None, None
        return data, hashlib.sha256(data).hexdigest()

    def compare_and_swap(self, store: Store, rel: str, data: bytes, expected_token: str | None) -> None:
        p = store.path(rel)
        lock = f"{p}.lock"
        while True:
            try:
                fd = _with_parents(lock, lambda: os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644))
                os.write(fd, f"{os.getpid()} {time.time():.3f}\n".encode())
                os.close(fd)
                break
            except FileExistsError:
                # Stale means one lock held too long (a killed writer), not a long wait: under
                # contention and slow fsync, many short-lived locks can keep a writer waiting
                # longer than lock_timeout_s while every holder makes progress.
                try:
                    age = time.time() - os.stat(lock).st_mtime
                except FileNotFoundError:
                    continue
                if age > self.lock_timeout_s:
                    raise LockTimeoutError(
                        f"lock file {lock} has been held for {age:.0f} s; if no publish is running "
                        f"it was left by a killed process: run `drivetrack gc {store.url}` or delete it")
                time.sleep(0.002)
        try:
            _current, token = self.read_with_token(store, rel)
            if token != expected_token:
                raise CasConflictError(
                    f"{store.url_of(rel)} changed underneath (expected token {expected_token}, "
                    f"found {token})")
            tmp = self._write_tmp(store, rel, data)
            os.replace(tmp, p)  # the lock file keeps p's folder from being pruned
        finally:
            os.unlink(lock)


def _s3_error_code(exc: BaseException) -> str | None:
    """The S3 error code behind an s3fs-translated exception, if any."""
    for e in (exc, exc.__cause__, exc.__context__):
        response = getattr(e, "response", None)
        if isinstance(response, dict):
            return response.get("Error", {}).get("Code")
    return None


class S3Conditional:
    """S3 (and S3-compatible servers): ``If-None-Match: *`` and ``If-Match: <ETag>`` on PUT."""

    def put_if_absent(self, store: Store, rel: str, data: bytes) -> None:
        p = store.path(rel)
        try:
            store.fs.pipe_file(p, data, mode="create")
        except FileExistsError:
            raise
        except OSError as e:
            if _s3_error_code(e) in ("PreconditionFailed", "ConditionalRequestConflict"):
                raise FileExistsError(f"{store.url_of(rel)} already exists") from e
            raise
        finally:
            store.fs.invalidate_cache(p)

    def read_with_token(self, store: Store, rel: str) -> tuple[bytes | None, str | None]:
        from fsspec.asyn import sync

        bucket, key, _ = store.fs.split_path(store.path(rel))

        async def _get():
            try:
                resp = await store.fs._call_s3("get_object", Bucket=bucket, Key=key)
            except FileNotFoundError:
                return None, None
            body = resp["Body"]
            try:
                data = await body.read()
            finally:
                body.close()
            return data, resp["ETag"]

        return sync(store.fs.loop, _get)

    def compare_and_swap(self, store: Store, rel: str, data: bytes, expected_token: str | None) -> None:
        if expected_token is None:
            try:
                self.put_if_absent(store, rel, data)
            except FileExistsError as e:
                raise CasConflictError(f"{store.url_of(rel)} appeared underneath (expected absent)") from e
            return
        p = store.path(rel)
        bucket, key, _ = store.fs.split_path(p)
        try:
            store.fs.call_s3("put_object", Bucket=bucket, Key=key, Body=data, IfMatch=expected_token)
        except (OSError, FileExistsError) as e:
            if _s3_error_code(e) in ("PreconditionFailed", "ConditionalRequestConflict", "NoSuchKey") \
                    or isinstance(e, (FileExistsError, FileNotFoundError)):
                raise CasConflictError(
                    f"{store.url_of(rel)} changed underneath (expected ETag {expected_token})") from e
            raise
        finally:
            store.fs.invalidate_cache(p)


class LockObjectConditional:
    """Generic object stores with exclusive create (fsspec ``mode="create"``, e.g. gcsfs):
    CAS as create-only lock object, read-compare-write, delete lock. Not exercised by the tests
    here (no gcsfs on the project machines)."""

    lock_timeout_s = 30.0

    def put_if_absent(self, store: Store, rel: str, data: bytes) -> None:
        store.fs.pipe_file(store.path(rel), data, mode="create")

    def read_with_token(self, store: Store, rel: str) -> tuple[bytes | None, str | None]:
        try:
            data = store.fs.cat_file(store.path(rel))
        except FileNotFoundError:
            return None, None
        return data, hashlib.sha256(data).hexdigest()

    def compare_and_swap(self, store: Store, rel: str, data: bytes, expected_token: str | None) -> None:
        lock = f"{rel}.lock"
        deadline = time.monotonic() + self.lock_timeout_s
        while True:
            try:
                self.put_if_absent(store, lock, f"{os.getpid()} {time.time():.3f}".encode())
                break
            except FileExistsError:
                if time.monotonic() > deadline:
                    raise LockTimeoutError(
                        f"lock object {store.url_of(lock)} held for more than {self.lock_timeout_s} s; "
                        f"run `drivetrack gc {store.url}` if no publish is running")
                time.sleep(0.05)
        try:
            _current, token = self.read_with_token(store, rel)
            if token != expected_token:
                raise CasConflictError(f"{store.url_of(rel)} changed underneath")
            store.fs.pipe_file(store.path(rel), data)
        finally:
            store.delete(lock)


CONDITIONAL_BACKENDS: dict[str, Any] = {
    "file": LocalConditional(),
    "s3": S3Conditional(),
    "gs": LockObjectConditional(),
    "gcs": LockObjectConditional(),
}
"""Conditional-write backend per fsspec protocol; a new store type is a new entry."""


def _backend(store: Store):
    try:
        return CONDITIONAL_BACKENDS[store.protocol]
    except KeyError:
        raise UnsupportedStoreError(
            f"store {store.url}: protocol {store.protocol!r} has no conditional-write backend "
            f"(supported: {', '.join(sorted(CONDITIONAL_BACKENDS))})") from None


def open_store(url: str | os.PathLike, storage_options: dict | None = None, *,
               endpoint_url: str | None = None) -> Store:
    """Open a store URL (``./store``, ``file://...``, ``s3://bucket/prefix``, ``gs://bucket/prefix``).

    ``storage_options`` go to the fsspec filesystem (for S3: ``key``, ``secret``,
    ``client_kwargs={"endpoint_url": ...}``, ...). ``endpoint_url`` is a shortcut for S3-compatible
    servers; without it, s3fs/botocore read ``AWS_ENDPOINT_URL``, credentials and region from the
    standard AWS environment variables and config files.
    """
    url = os.fspath(url)
    options = dict(storage_options or {})
    protocol, _, rest = url.partition("://")
    if not rest:
        protocol, rest = "file", url
    protocol = {"local": "file", "s3a": "s3", "gcs": "gs"}.get(protocol, protocol)
    if protocol == "file":
        root = os.path.abspath(os.path.expanduser(rest))
        return Store(url=f"file://{root}", fs=fsspec.filesystem("file"), root=root,
                     protocol="file", storage_options=options)
    if endpoint_url:
        if protocol != "s3":
            raise UnsupportedStoreError(f"endpoint_url is only for s3:// stores, got {url}")
        client_kwargs = dict(options.get("client_kwargs") or {})
        client_kwargs["endpoint_url"] = endpoint_url
        options["client_kwargs"] = client_kwargs
    if protocol == "gs":
        try:
            import gcsfs  # noqa: F401
        except ImportError as e:
            raise UnsupportedStoreError(
                f"store {url} needs gcsfs: pip install 'drivetrack[gcs]'") from e
    if protocol not in CONDITIONAL_BACKENDS:
        raise UnsupportedStoreError(
            f"store {url}: protocol {protocol!r} is not supported "
            f"(use a local folder, s3:// or gs://)")
    root = rest.strip("/")
    if not root:
        raise UnsupportedStoreError(f"store URL {url} names no bucket")
    fs = fsspec.filesystem(protocol, **options)
    return Store(url=f"{protocol}://{root}", fs=fs, root=root, protocol=protocol,
                 storage_options=options)
