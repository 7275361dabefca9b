"""What a run records about its inputs and code: the code version and source file checksums.

One place for both, used by ``run.json`` (:mod:`drivetrack.annotate`), the release manifest
(:mod:`drivetrack.release.manifest`) and the content keys of the release flow
(:mod:`drivetrack.release.keys`).
"""
from __future__ import annotations

import hashlib
import os
import subprocess
from pathlib import Path

import fsspec

from drivetrack.storage import is_local

__all__ = ["code_version", "code_version_text", "source_checksums"]

_HASH_CHUNK = 8 << 20


def code_version(repo_dir: str | Path | None = None) -> dict:
    """``drivetrack.__version__`` plus the git commit of the source tree if there is one:
    ``{"drivetrack": str, "git_commit": str | None (full hash), "git_dirty": bool | None}``."""
    import drivetrack

    out: dict = {"drivetrack": drivetrack.__version__, "git_commit": None, "git_dirty": None}
    cwd = Path(repo_dir) if repo_dir else Path(drivetrack.__file__).resolve().parent
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True,
                                text=True, timeout=10)
        if commit.returncode == 0:
            out["git_commit"] = commit.stdout.strip()
            dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                                   cwd=cwd, capture_output=True, text=True, timeout=10)
            if dirty.returncode == 0:
                out["git_dirty"] = bool(dirty.stdout.strip())
    except (OSError, subprocess.SubprocessError):
        pass
    return out


def code_version_text(version: dict | None = None) -> str:
    """:func:`code_version` as one string, ``0.1.0`` or ``0.1.0+g<12 hex>[.dirty]`` (run.json)."""
    version = code_version() if version is None else version
    text = version["drivetrack"]
    if version.get("git_commit"):
        text += f"+g{version['git_commit'][:12]}" + (".dirty" if version.get("git_dirty") else "")
    return text


def _sha256(fs, path: str) -> str:
    digest = hashlib.sha256()
    with fs.open(path, "rb") as handle:
        while chunk := handle.read(_HASH_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def source_checksums(source_files: dict[str, str], storage_options: dict | None = None, *,
                     store_tags: bool = False, memo: dict | None = None) -> dict[str, str]:
    """Component -> checksum of each source file URL, in component order.

    Default: the sha256 hex digest of the bytes (streamed in 8 MiB chunks). ``store_tags`` (the
    content keys of the release flow, cheap on object stores): local files give
    ``sha256:<hex>`` memoised in ``memo`` on (size, mtime); object stores give
    ``<size>:<checksum>`` with the checksum the store reports (S3 ETag, GCS md5/crc32c), no
    download. Raises OSError naming the file and component when a file cannot be read.
    """
    memo = {} if memo is None else memo
    out = {}
    for component, url in sorted(source_files.items()):
        fs, path = fsspec.core.url_to_fs(str(url), **(storage_options or {}))
        try:
            if not store_tags:
                out[component] = _sha256(fs, path)
            elif is_local(fs):
                st = os.stat(path)
                tag = f"{st.st_size}:{st.st_mtime_ns}"
                hit = memo.get(path)
                if not (hit and hit[0] == tag):
                    memo[path] = (tag, "sha256:" + _sha256(fs, path))
                out[component] = memo[path][1]
            else:
                info = fs.info(path)
                tag = info.get("ETag") or info.get("md5Hash") or info.get("crc32c") or info.get("checksum") \
                    or info.get("LastModified") or info.get("mtime")
                out[component] = f"{info.get('size')}:{str(tag).strip(chr(34))}"
        except OSError as error:
            raise OSError(f"could not hash source file {url} (component {component}): {error}") from error
    return out
