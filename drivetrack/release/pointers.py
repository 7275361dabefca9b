"""The store's layout and its shared JSON pointers.

Where a version, its staging prefix and its claim live (``{dataset}/{version}/``,
``{dataset}/_staging/{version}/``, ``{dataset}/_txn/{version}.json``), and the two documents
every publish updates by compare-and-swap: ``{dataset}/versions.json`` (the index) and
``{dataset}/latest.json`` (the pointer). Used by publish, resume and gc (catalog).
"""
from __future__ import annotations

import json
import random
import time
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime, timezone
from typing import Callable

from drivetrack.release.errors import CasConflictError, ReleaseError
from drivetrack.release.manifest import SemVer, sha256_stream
from drivetrack.release.store import Store

__all__ = ["version_prefix", "staging_prefix", "claim_path", "index_path", "latest_path", "hash_object",
           "update_json_cas", "add_to_index", "move_latest", "finish_committed_version"]


# ---- layout ------------------------------------------------------------------------------

def version_prefix(dataset: str, version: str) -> str:
    return f"{dataset}/{version}"


def staging_prefix(dataset: str, version: str) -> str:
    return f"{dataset}/_staging/{version}"


def claim_path(dataset: str, version: str) -> str:
    return f"{dataset}/_txn/{version}.json"


def index_path(dataset: str) -> str:
    return f"{dataset}/versions.json"


def latest_path(dataset: str) -> str:
    return f"{dataset}/latest.json"


def _now() -> tuple[str, float]:
    t = time.time()
    return datetime.fromtimestamp(t, timezone.utc).isoformat(timespec="seconds").replace("+00:00", "Z"), t



def _run_pool(fn, items, workers: int):
    """Map ``fn`` over ``items`` on a thread pool; re-raise the first error after all finished."""
    if not items:
        return []
    with ThreadPoolExecutor(max_workers=max(1, min(workers, len(items)))) as pool:
        futures = [pool.submit(fn, it) for it in items]
        results, first_error = [], None
        for fut in futures:
            try:
                results.append(fut.result())
            except BaseException as e:  # noqa: BLE001 - collected and re-raised below
                first_error = first_error or e
                results.append(None)
    if first_error is not None:
        raise first_error
    return results


# ---- pointers ------------------------------------------------------------------------------

def hash_object(store: Store, rel: str) -> tuple[str, int]:
    with store.open_read(rel) as f:
        return sha256_stream(f)


def _read_json(store: Store, rel: str) -> tuple[dict | None, str | None]:
    data, token = store.read_with_token(rel)
    if data is None:
        return None, None
    try:
        return json.loads(data), token
    except json.JSONDecodeError as e:
        raise ReleaseError(f"{store.url_of(rel)} is not valid JSON ({e}); repair it with `drivetrack gc`") from e


def _json_bytes(doc: dict) -> bytes:
    return (json.dumps(doc, indent=1, sort_keys=True) + "\n").encode()


def update_json_cas(store: Store, rel: str, update: Callable[[dict | None], dict | None],
                    attempts: int = 100) -> dict | None:
    """Read-modify-write ``rel`` with compare-and-swap on its previous value, retrying on conflict.

    ``update(current)`` returns the new document, or ``None`` to leave the object unchanged.
    """
    for attempt in range(attempts):
        current, token = _read_json(store, rel)
        new = update(current)
        if new is None:
            return current
        try:
            store.compare_and_swap(rel, _json_bytes(new), token)
            return new
        except CasConflictError:
            time.sleep(random.uniform(0, 0.01 * min(attempt + 1, 10)))
    raise CasConflictError(f"{store.url_of(rel)}: gave up after {attempts} compare-and-swap conflicts")


def add_to_index(store: Store, dataset: str, manifest: dict) -> None:
    entry = {"version": manifest["version"], "created": manifest["created"],
             "manifest_sha256": manifest["manifest_sha256"], "files": len(manifest["files"]),
             "bytes": int(sum(f["size"] for f in manifest["files"]))}

    def update(doc):
        doc = doc or {"dataset": dataset, "versions": []}
        if any(v["version"] == entry["version"] for v in doc["versions"]):
            return None
        doc["versions"] = sorted(doc["versions"] + [entry], key=lambda v: SemVer.parse(v["version"]))
        doc["updated"] = _now()[0]
        return doc

    update_json_cas(store, index_path(dataset), update)


def move_latest(store: Store, dataset: str, manifest: dict) -> str | None:
    """Point ``latest.json`` at this version if it is the highest release; returns the latest version.

    Pre-releases become latest only while no release exists; the move is a compare-and-swap on
    the previous pointer, so concurrent publishes cannot move it backwards.
    """
    def rank(v: str):  # any release outranks any pre-release; then semver precedence
        sv = SemVer.parse(v)
        return (not sv.prerelease, sv)

    def update(doc):
        if doc is not None and rank(manifest["version"]) <= rank(doc["version"]):
            return None
        return {"dataset": dataset, "version": manifest["version"],
                "manifest_sha256": manifest["manifest_sha256"], "updated": _now()[0],
                "previous": doc["version"] if doc else None}

    doc = update_json_cas(store, latest_path(dataset), update)
    return doc["version"] if doc else None


def finish_committed_version(store: Store, dataset: str, manifest: dict, warnings: list[str]) -> str | None:
    """After a version's manifest is committed: add it to ``versions.json``, move ``latest.json``
    (both by compare-and-swap) and remove its staging prefix and claim. The version is published
    whatever happens here: a failure is appended to ``warnings`` (``drivetrack gc`` repairs it).
    Returns the latest version, or None when the pointers could not be updated."""
    version = manifest["version"]
    latest = None
    try:
        add_to_index(store, dataset, manifest)
        latest = move_latest(store, dataset, manifest)
    except Exception as e:  # noqa: BLE001 - the release is committed; gc repairs the pointers
        warnings.append(f"version committed, but updating versions.json/latest.json failed "
                        f"({type(e).__name__}: {e}); run `drivetrack gc {store.url} --dataset {dataset}` "
                        f"to repair them")
    try:
        store.delete_tree(staging_prefix(dataset, version))
        store.delete(claim_path(dataset, version))
        # Only while empty: concurrent publishes of other versions may be staging or hold claims.
        store.prune_empty(f"{dataset}/_staging")
        store.prune_empty(f"{dataset}/_txn")
    except Exception as e:  # noqa: BLE001
        warnings.append(f"version committed, but removing the staging prefix or claim failed ({e}); "
                        f"`drivetrack gc` removes them")
    return latest
