"""Reading a store: versions, manifests, verification, diffs and garbage collection."""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field

from drivetrack.names import is_valid_name
from drivetrack.release.errors import InvalidVersionError, ManifestError, ReleaseError, VersionNotFoundError
from drivetrack.release.manifest import (MANIFEST_NAME, SemVer, check_dataset, manifest_entries,
                                         parse_manifest, sha256_stream)
from drivetrack.release.pointers import (_read_json, add_to_index, claim_path, latest_path, move_latest,
                                         staging_prefix, version_prefix)
from drivetrack.release.publish import DEFAULT_DATASET, DEFAULT_WORKERS
from drivetrack.release.store import TMP_DIR, Store, open_store


def _as_store(store: Store | str, storage_options: dict | None) -> Store:
    return store if isinstance(store, Store) else open_store(store, storage_options)


def _is_version(name: str) -> bool:
    try:
        SemVer.parse(name)
    except ValueError:
        return False
    return True


def _committed_versions(store: Store, dataset: str) -> list[str]:
    """Versions with a manifest, by scanning the store (the source of truth; the index is a cache)."""
    found = []
    for name in store.list_dirs(dataset):
        if name.startswith("_"):
            continue
        try:
            SemVer.parse(name)
        except ValueError:
            continue
        if store.exists(f"{dataset}/{name}/{MANIFEST_NAME}"):
            found.append(name)
    return sorted(found, key=SemVer.parse)


def next_version(latest: str | None) -> str:
    """The version an ``auto`` release gets: the next patch after ``latest`` (its pre-release
    and build parts dropped: ``1.2.3-rc.1`` -> ``1.2.4``), ``0.1.0`` when nothing is published.
    Raises InvalidVersionError when ``latest`` is not a semantic version."""
    if latest is None:
        return "0.1.0"
    try:
        v = SemVer.parse(latest)
    except InvalidVersionError:
        raise InvalidVersionError(f"latest version {latest!r} is not a semantic version x.y.z: give an explicit "
                                  f"version") from None
    return str(SemVer(v.major, v.minor, v.patch + 1))


def resolve_version(store: Store, dataset: str, version: str) -> str:
    """``latest`` -> the version ``latest.json`` points at; any other string is returned checked.

    The version read from ``latest.json`` is checked too: it is store data that becomes a path.
    """
    check_dataset(dataset)
    if version != "latest":
        SemVer.parse(version)
        return version
    doc, _ = _read_json(store, latest_path(dataset))
    if doc is None:
        raise VersionNotFoundError(f"{store.url_of(dataset)} has no latest.json: no version published")
    found = doc.get("version") if isinstance(doc, dict) else None
    try:
        SemVer.parse(found)
    except ValueError as e:
        raise ManifestError(f"{store.url_of(latest_path(dataset))}: 'version' is {found!r}, not a semantic "
                            f"version; repair it with `drivetrack gc`") from e
    return found


def read_manifest(store: Store | str, version: str, dataset: str = DEFAULT_DATASET,
                  storage_options: dict | None = None) -> dict:
    """The committed manifest of a version (its top-level hash checked)."""
    check_dataset(dataset)
    store = _as_store(store, storage_options)
    version = resolve_version(store, dataset, version)
    rel = f"{version_prefix(dataset, version)}/{MANIFEST_NAME}"
    try:
        data = store.read_bytes(rel)
    except FileNotFoundError:
        hint = ""
        if store.exists(claim_path(dataset, version)):
            hint = (" A publish of it is in progress or was interrupted (claim "
                    f"{store.url_of(claim_path(dataset, version))}); resume it or run `drivetrack gc`.")
        available = _committed_versions(store, dataset)
        raise VersionNotFoundError(
            f"version {version} of {dataset} is not published in {store.url} (no {rel})."
            f"{hint} Published: {', '.join(available) or 'none'}") from None
    manifest = parse_manifest(data, store.url_of(rel))
    if manifest["version"] != version or manifest["dataset"] != dataset:
        raise ManifestError(f"{store.url_of(rel)} describes {manifest['dataset']} {manifest['version']}, "
                            f"not {dataset} {version}")
    return manifest


def list_versions(store: Store | str, dataset: str = DEFAULT_DATASET,
                  storage_options: dict | None = None) -> list[dict]:
    """Published versions in semver order: ``[{version, created, manifest_sha256, files, bytes, latest}]``.

    Found by scanning for manifests; ``versions.json`` only fills in the summary fields.
    """
    check_dataset(dataset)
    store = _as_store(store, storage_options)
    index, _ = _read_json(store, f"{dataset}/versions.json")
    by_version = {v["version"]: v for v in (index or {}).get("versions", [])}
    latest, _ = _read_json(store, latest_path(dataset))
    out = []
    for v in _committed_versions(store, dataset):
        entry = dict(by_version.get(v) or {})
        if not entry:
            m = read_manifest(store, v, dataset)
            entry = {"version": v, "created": m["created"], "manifest_sha256": m["manifest_sha256"],
                     "files": len(m["files"]), "bytes": sum(f["size"] for f in m["files"])}
        entry["indexed"] = v in by_version
        entry["latest"] = bool(latest and latest.get("version") == v)
        out.append(entry)
    return out


# ---- verify ----------------------------------------------------------------------------------

@dataclass
class VerifyReport:
    """Result of re-hashing a release against its manifest. ``ok`` iff nothing is missing, extra or corrupt."""

    dataset: str
    version: str
    url: str
    manifest_sha256: str
    files_checked: int
    bytes: int
    seconds: float
    mb_per_s: float
    missing: list[str] = field(default_factory=list)
    extra: list[str] = field(default_factory=list)
    corrupt: list[dict] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not (self.missing or self.extra or self.corrupt)

    def to_json(self) -> dict:
        d = asdict(self)
        d["ok"] = self.ok
        return d


def verify_release(store: Store | str, version: str, dataset: str = DEFAULT_DATASET, *,
                   storage_options: dict | None = None, workers: int = DEFAULT_WORKERS,
                   progress=None) -> VerifyReport:
    """Re-hash every file of a release (streamed, concurrently) against its manifest.

    ``progress(event, info)``: ``planned`` ({"files", "bytes"}) once, then ``checked``
    ({"path", "bytes"}) per file hashed, from the hashing threads; for progress display.

    Raises :class:`VersionNotFoundError` / :class:`ManifestError` if there is no valid manifest;
    otherwise reports missing, extra and corrupt (size or sha256 mismatch) files.
    """
    check_dataset(dataset)
    store = _as_store(store, storage_options)
    version = resolve_version(store, dataset, version)
    manifest = read_manifest(store, version, dataset)
    expected = manifest_entries(manifest)
    vpre = version_prefix(dataset, version)
    t0 = time.perf_counter()
    present = store.find(vpre)
    present.pop(MANIFEST_NAME, None)
    missing = sorted(p for p in expected if p not in present)
    extra = sorted(p for p in present if p not in expected)

    emit = progress or (lambda event, info: None)

    def check(path: str) -> dict | None:
        try:
            return _check(path)
        finally:
            emit("checked", {"path": path, "bytes": expected[path].size})

    def _check(path: str) -> dict | None:
        e = expected[path]
        if present[path] != e.size:
            return {"path": path, "problem": "size", "expected": e.size, "found": present[path]}
        try:
            with store.open_read(f"{vpre}/{path}") as f:
                digest, n = sha256_stream(f)
        except FileNotFoundError:
            return {"path": path, "problem": "missing", "expected": e.sha256, "found": None}
        if n != e.size:
            return {"path": path, "problem": "size", "expected": e.size, "found": n}
        if digest != e.sha256:
            return {"path": path, "problem": "sha256", "expected": e.sha256, "found": digest}
        return None

    to_check = [p for p in expected if p in present]
    # Largest first, so one big file does not finish alone at the end.
    to_check.sort(key=lambda p: -expected[p].size)
    emit("planned", {"files": len(to_check), "bytes": sum(expected[p].size for p in to_check)})
    if to_check:
        with ThreadPoolExecutor(max_workers=max(1, min(workers, len(to_check)))) as pool:
            results = list(pool.map(check, to_check))
    else:
        results = []
    corrupt = sorted((r for r in results if r), key=lambda r: r["path"])
    nbytes = sum(expected[p].size for p in to_check)
    seconds = time.perf_counter() - t0
    return VerifyReport(dataset=dataset, version=version, url=store.url_of(vpre),
                        manifest_sha256=manifest["manifest_sha256"], files_checked=len(to_check),
                        bytes=nbytes, seconds=seconds, mb_per_s=nbytes / 1e6 / max(seconds, 1e-9),
                        missing=missing, extra=extra, corrupt=corrupt)


# ---- diff --------------------------------------------------------------------------------------

@dataclass
class DiffReport:
    """Files added, removed and changed (by sha256) from ``old`` to ``new``, and statistic deltas."""

    dataset: str
    old: str
    new: str
    added: list[str]
    removed: list[str]
    changed: list[str]
    unchanged: int
    deltas: dict

    def to_json(self) -> dict:
        return asdict(self)


def _numeric_leaves(obj, prefix: str = "") -> dict[str, float]:
    out: dict[str, float] = {}
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.update(_numeric_leaves(v, f"{prefix}.{k}" if prefix else str(k)))
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        out[prefix] = obj
    return out


def diff_versions(store: Store | str, old: str, new: str, dataset: str = DEFAULT_DATASET,
                  storage_options: dict | None = None) -> DiffReport:
    """Compare two published versions by their manifests (no data is read)."""
    check_dataset(dataset)
    store = _as_store(store, storage_options)
    a, b = read_manifest(store, old, dataset), read_manifest(store, new, dataset)
    fa, fb = manifest_entries(a), manifest_entries(b)
    meta = {"README.md", "croissant.json", "SHA256SUMS"}
    added = sorted(p for p in fb if p not in fa)
    removed = sorted(p for p in fa if p not in fb)
    changed = sorted(p for p in fa if p in fb and fa[p].sha256 != fb[p].sha256 and p not in meta)
    unchanged = sum(1 for p in fa if p in fb and fa[p].sha256 == fb[p].sha256)
    la = _numeric_leaves({"counts": a.get("counts") or {}, "statistics": a.get("statistics") or {}})
    lb = _numeric_leaves({"counts": b.get("counts") or {}, "statistics": b.get("statistics") or {}})
    deltas = {}
    for k in sorted(set(la) | set(lb)):
        va, vb = la.get(k), lb.get(k)
        if va != vb:
            deltas[k] = {"old": va, "new": vb,
                         "delta": (vb - va) if va is not None and vb is not None else None}
    return DiffReport(dataset=dataset, old=a["version"], new=b["version"], added=added, removed=removed,
                      changed=changed, unchanged=unchanged, deltas=deltas)


# ---- gc -------------------------------------------------------------------------------------------

def _collect_stale(store: Store, report: "GcReport", rel: str, now: float, older_than_s: float,
                   dry_run: bool) -> None:
    """Delete the local file ``rel`` (a lock or temporary) if it is at least ``older_than_s`` old."""
    import os

    try:
        age = now - os.stat(store.path(rel)).st_mtime
    except FileNotFoundError:
        return
    if age < older_than_s:
        return
    report.actions.append(f"{'would delete' if dry_run else 'deleted'} stale {store.url_of(rel)} (age {age:.0f} s)")
    if not dry_run:
        store.delete(rel)
        report.removed_objects += 1

@dataclass
class GcReport:
    """What ``gc`` found and did. ``actions`` are human-readable lines."""

    actions: list[str] = field(default_factory=list)
    removed_objects: int = 0
    skipped_recent: list[str] = field(default_factory=list)


def gc(store: Store | str, dataset: str | None = None, *, older_than_s: float = 3600.0,
       dry_run: bool = False, storage_options: dict | None = None) -> GcReport:
    """Clean up interrupted publishes and repair pointers.

    For each claim older than ``older_than_s`` (a publish that is still running must not be
    collected: keep the default unless you know none is): if the version has a manifest (the publish
    died after committing) the index and latest pointer are repaired; otherwise the partially
    promoted files of the uncommitted version are deleted. Then its staging prefix and claim are
    deleted. Staging prefixes without a claim and stale local lock files are deleted too, and every
    committed version missing from ``versions.json`` / ``latest.json`` is added. Committed versions
    are never touched.
    """
    if dataset is not None:
        check_dataset(dataset)
    store = _as_store(store, storage_options)
    report = GcReport()
    # Folders that are not valid dataset names (``_tmp``, ``.git``, a name with a newline) are
    # not datasets: never walked, never cleaned.
    datasets = [dataset] if dataset is not None else [d for d in store.list_dirs("") if is_valid_name("dataset", d)]
    now = time.time()

    def remove_tree(rel: str, why: str) -> None:
        files = store.find(rel)
        if not files:
            return
        report.actions.append(f"{'would delete' if dry_run else 'deleted'} {len(files)} object(s) under "
                              f"{store.url_of(rel)} ({why})")
        if not dry_run:
            report.removed_objects += store.delete_tree(rel)

    if store.is_local:  # temporaries of atomic writes (store-wide, see Store.local_tmp)
        for rel in store.find(TMP_DIR):
            _collect_stale(store, report, f"{TMP_DIR}/{rel}", now, older_than_s, dry_run)
    for ds in datasets:
        claims = {p[:-len(".json")]: p for p in store.find(f"{ds}/_txn") if p.endswith(".json")}
        for odd in sorted(v for v in claims if not _is_version(v)):  # names from the store: checked
            report.actions.append(f"ignored {ds}/_txn/{claims.pop(odd)!r}: not named after a version")
        for version, rel in sorted(claims.items()):
            doc, _ = _read_json(store, f"{ds}/_txn/{rel}")
            age = now - float((doc or {}).get("started_unix", 0))
            if age < older_than_s:
                report.skipped_recent.append(f"{ds} {version}: claim is {age:.0f} s old (< {older_than_s:.0f} s)")
                continue
            committed = store.exists(f"{version_prefix(ds, version)}/{MANIFEST_NAME}")
            if not committed:
                remove_tree(version_prefix(ds, version), "uncommitted files of an interrupted publish")
            remove_tree(staging_prefix(ds, version), "staging of an interrupted publish")
            report.actions.append(f"{'would delete' if dry_run else 'deleted'} claim "
                                  f"{store.url_of(claim_path(ds, version))} (age {age:.0f} s, "
                                  f"{'committed' if committed else 'not committed'})")
            if not dry_run:
                store.delete(claim_path(ds, version))
                report.removed_objects += 1
        for version in store.list_dirs(f"{ds}/_staging"):
            if not _is_version(version):
                report.actions.append(f"ignored {ds}/_staging/{version!r}: not named after a version")
            elif version not in claims:
                remove_tree(staging_prefix(ds, version), "staging without a claim")
        if store.is_local:
            # Stale lock files and temporaries left by killed processes (temporaries of older
            # drivetrack versions sat beside their target). A file listed in a committed manifest
            # is release data, whatever its name: never touched.
            committed_files: dict[str, set] = {}
            for rel in store.find(ds):
                if not (rel.endswith(".lock") or ".tmp-" in rel):
                    continue
                top, _, inner = rel.partition("/")
                if inner and top not in committed_files:
                    committed_files[top] = set()
                    if _is_version(top) and store.exists(f"{ds}/{top}/{MANIFEST_NAME}"):
                        try:
                            committed_files[top] = set(manifest_entries(read_manifest(store, top, ds))) | {MANIFEST_NAME}
                        except (ValueError, ReleaseError):
                            committed_files[top] = None  # unreadable manifest: leave the version alone
                protected = committed_files.get(top) if inner else set()
                if protected is None or inner in (protected or ()):
                    continue
                _collect_stale(store, report, f"{ds}/{rel}", now, older_than_s, dry_run)
        if not dry_run:  # empty transaction folders (local stores; only while empty)
            store.prune_empty(f"{ds}/_staging")
            store.prune_empty(f"{ds}/_txn")
        index, _ = _read_json(store, f"{ds}/versions.json")
        indexed = {v["version"] for v in (index or {}).get("versions", [])}
        for version in _committed_versions(store, ds):
            m = read_manifest(store, version, ds)
            if version not in indexed:
                report.actions.append(f"{'would add' if dry_run else 'added'} {ds} {version} to versions.json")
            if not dry_run:
                add_to_index(store, ds, m)
                move_latest(store, ds, m)
    return report
