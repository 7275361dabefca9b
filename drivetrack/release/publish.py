"""Transactional publish of a release.

Store layout for dataset ``D`` (all paths relative to the store root)::

    D/{version}/...            the release: data files, README.md, croissant.json, SHA256SUMS, manifest.json
    D/versions.json            index of published versions (updated by compare-and-swap)
    D/latest.json              pointer to the highest published release (compare-and-swap)
    D/_txn/{version}.json      claim of a publish in progress (created exclusively; removed at the end)
    D/_staging/{version}/...   staged files of a publish in progress

A publish (write-audit-publish):

0. before anything is written: checks the version string; lists the source without following
   links and refuses anything that is not a regular file of the output contract
   (:mod:`drivetrack.release.contents`); runs the gates when no report is given; checks the gate
   report (:class:`GatesFailedError` if the gates failed and no reason to accept was given,
   :class:`GateBindingError` if it does not name this content); checks every clip's ``.npz``
   headers against the declared formats, the statistics tables' schemas, and that no clip
   belongs to a segment not recorded as done;
1. refuses a version that already has a manifest (:class:`VersionExistsError`);
2. claims the version by creating ``_txn/{version}.json`` exclusively: of two publishes of one
   version, exactly one gets the claim, the other fails with :class:`ConcurrentPublishError`;
3. uploads and hashes every file concurrently into ``_staging/{version}/`` (streamed in 8 MiB
   chunks), then re-reads every staged object and checks size and sha256, and checks that the
   staged statistics tables and clips are byte for byte those the gate report validated;
4. writes README.md, croissant.json and SHA256SUMS into staging, moves everything into
   ``{version}/`` (rename locally, server-side copy on S3) and checks sizes;
5. commits by creating ``{version}/manifest.json`` exclusively (a version exists exactly when its
   manifest exists; before that, readers see no version);
6. adds the version to ``versions.json`` and moves ``latest.json`` with compare-and-swap on their
   previous value, then removes the claim and the staging prefix.

A failure between 2 and 5 raises :class:`PublishInterruptedError`; nothing is visible. Run the
same publish with ``resume=True`` (reuses staged files whose sha256 matches) or ``gc`` to clean.
"""
from __future__ import annotations

import hashlib
import os
import socket
import time
import uuid
from dataclasses import dataclass, field
from typing import Callable

import fsspec

from drivetrack.gates.binding import binding_problems, check_binding_shape
from drivetrack.outputs import CLIPS, DRIVETRACK, TAPVID3D, clip_glob, clips_of, parse_clip_path, parse_table_path
from drivetrack.release import cards as _cards
from drivetrack.release import contents as _contents
from drivetrack.release.errors import (CasConflictError, ConcurrentPublishError, GateBindingError,
                                       GatesFailedError, InvalidSourceError, PublishConflictError,
                                       PublishInterruptedError, StagingCheckError,
                                       VersionExistsError)
from drivetrack.release.manifest import (CARD_NAME, CROISSANT_NAME, MANIFEST_FORMAT, MANIFEST_NAME,
                                         RESERVED_NAMES, SUMS_NAME, FileEntry, check_dataset,
                                         check_release_path, check_version, code_version,
                                         counts_from_files, dump_manifest, read_run_json,
                                         render_sha256sums, seal_manifest, sha256_bytes, sha256_stream,
                                         splits_from_paths, statistics_from_parquet)
from drivetrack.release.pointers import (_json_bytes, _now, _read_json, _run_pool, claim_path,
                                         finish_committed_version, hash_object, staging_prefix,
                                         version_prefix)
from drivetrack.release.store import Store, iter_chunks, open_store

DEFAULT_DATASET = "drivetrack-waymo"
DEFAULT_WORKERS = 8

Progress = Callable[[str, dict], None]
"""``progress(event, info)``: events ``planned`` ({"files", "bytes"}), ``uploaded`` (per file),
``staged``, ``checked``, ``promoted``, ``committed``. Used for progress display and, in tests, to inject faults between steps."""


@dataclass
class PublishResult:
    """What a publish did. ``mb_per_s`` is source bytes / wall time of upload+hash+check."""

    dataset: str
    version: str
    store_url: str
    version_url: str
    manifest_sha256: str
    files: int
    bytes: int
    seconds: float
    mb_per_s: float
    latest: str | None
    reused_files: int = 0
    warnings: list[str] = field(default_factory=list)


# ---- source folder ------------------------------------------------------------------------

class _Source:
    """The folder to publish (local path or fsspec URL)."""

    def __init__(self, source: str | os.PathLike, storage_options: dict | None = None):
        src = os.fspath(source)
        if "://" in src and not src.startswith("file://"):
            self.fs, self.root = fsspec.core.url_to_fs(src, **(storage_options or {}))
            self.local = False
        else:
            self.fs, self.root = None, os.path.abspath(src.removeprefix("file://"))
            self.local = True
        self.url = src
        self.storage_options = storage_options

    def list(self) -> dict[str, int]:
        """``{relative path: size}`` of the release members; refuses (:class:`InvalidSourceError`,
        naming every offending path) links, hidden and special files and unknown files."""
        if self.local:
            if not os.path.isdir(self.root):
                raise InvalidSourceError(f"source folder {self.root} does not exist or is not a folder")
            return _contents.list_local_folder(self.root)
        found = self.fs.find(self.root, detail=True, withdirs=True)
        base = self.root.rstrip("/")
        entries = {p[len(base):].lstrip("/"): info for p, info in found.items()}
        entries.pop("", None)
        _contents.check_listed(self.url, {rel: str(info.get("type")) for rel, info in entries.items()})
        return dict(sorted((rel, int(info["size"])) for rel, info in entries.items()
                           if info.get("type") == "file"))

    def open(self, rel: str):
        if self.local:
            return _contents.open_local_nofollow(self.root, rel)
        return self.fs.open(f"{self.root.rstrip('/')}/{rel}", "rb")

    def read(self, rel: str) -> bytes:
        with self.open(rel) as f:
            return f.read()

    def where(self, rel: str) -> str:
        return os.path.join(self.root, rel) if self.local else f"{self.url.rstrip('/')}/{rel}"


# ---- checks before anything is written -------------------------------------------------------

def check_gate_report(gate_report: dict, accept_failed_gates: str | None) -> None:
    """Check a gate report on its own (its binding to the data is checked by the publish).

    Raises :class:`GateBindingError` for a report that is not one ``run_gates`` wrote (no or an
    edited binding, no gate evaluated, a verdict that contradicts its results, a configuration
    that does not hash to its fingerprint) and :class:`GatesFailedError` if the gates failed and
    no acceptance reason is given.
    """
    if accept_failed_gates is not None and not str(accept_failed_gates).strip():
        raise ValueError("accept_failed_gates must be a non-empty reason (it is recorded in the release)")
    if gate_report is None:
        raise ValueError("gate_report is None: publish_release runs the gates itself when it gets no "
                         "report; check_gate_report needs the report")
    if not isinstance(gate_report, dict) or "success" not in gate_report or \
            not isinstance(gate_report.get("results"), list):
        raise GateBindingError("gate_report must be a dict with 'success' (bool) and 'results' (list); got "
                               f"{type(gate_report).__name__} with keys "
                               f"{sorted(gate_report) if isinstance(gate_report, dict) else None}")
    problems = check_binding_shape(gate_report.get("binding"), "gate report")
    results = gate_report["results"]
    if not results:
        problems.append("gate report: no gate was evaluated ('results' is empty)")
    elif not all(isinstance(r, dict) and isinstance(r.get("success"), bool) for r in results):
        problems.append("gate report: every result must be an object with a boolean 'success'")
    elif bool(gate_report["success"]) != all(r["success"] for r in results):
        problems.append(f"gate report: 'success' is {gate_report['success']} but "
                        f"{sum(not r['success'] for r in results)} of {len(results)} results failed")
    if not problems:
        from drivetrack.gates.config import config_sha256

        cfg, fp = gate_report.get("config"), gate_report.get("config_sha256")
        try:
            found = config_sha256(cfg) if isinstance(cfg, dict) else None
        except Exception:  # noqa: BLE001 - any unhashable config is a mismatch
            found = None
        if found is None or found != fp or gate_report["binding"].get("config_sha256") != fp:
            problems.append(f"gate report: config_sha256 {fp} does not match its configuration (hashes to "
                            f"{found}) or its binding ({gate_report['binding'].get('config_sha256')})")
    if problems:
        raise GateBindingError("the gate report cannot be trusted for this publish; run `drivetrack gates "
                               "OUT` (or publish without --gate-report):\n  " + "\n  ".join(problems))
    if not gate_report["success"] and not accept_failed_gates:
        summary = _cards.summarize_gates(gate_report, None)
        failed = [r["name"] for r in summary["results"] if r["success"] is False]
        raise GatesFailedError(
            f"quality gates failed ({summary['failed']} of {len(summary['results'])}: "
            f"{', '.join(failed[:10]) or 'see report'}); nothing was published. Fix the data or publish "
            f"with accept_failed_gates='<reason>' (CLI: --accept-failed-gates REASON)")


# ---- publish -----------------------------------------------------------------------------------

def publish_release(source_dir: str | os.PathLike, store_url: str | os.PathLike, version: str, *,
                    dataset: str = DEFAULT_DATASET, storage_options: dict | None = None,
                    gate_report: dict | None = None, accept_failed_gates: str | None = None,
                    config: dict | None = None, card: dict | None = None, resume: bool = False,
                    workers: int = DEFAULT_WORKERS, progress: Progress | None = None,
                    source_storage_options: dict | None = None,
                    gates_config: str | dict | None = None, publish_npz: bool = False) -> PublishResult:
    """Publish the folder ``source_dir`` as ``{store_url}/{dataset}/{version}/`` (see module doc).

    ``gate_report``: the report of ``drivetrack.gates.run_gates`` on this content
    (``GateReport.to_dict()`` or ``validation/gates.json``); its binding must match what is
    staged. ``None`` runs the gates now (``run_gates(source_dir, gates_config)``, which writes
    ``source_dir/validation/``); there is no publish without gates. ``accept_failed_gates``:
    publish although gates failed, with this reason recorded in the manifest and the card.
    ``config`` is recorded in the manifest (``config.publish``); ``card`` (or ``config["card"]``)
    overrides the card defaults (:data:`drivetrack.release.cards.DEFAULT_CARD`).

    The release holds the v2 tables (``clips/``, ``frames/``). ``publish_npz``: also publish the
    clips as npz files (``tracks/``, ``tapvid3d/``), exported into ``source_dir`` from its tables
    (:func:`drivetrack.compact.export.export_clips`) first; without it, npz files in the source
    are left out of the release.
    """
    # 0. checks before anything is written
    check_version(version)
    check_dataset(dataset)
    if accept_failed_gates is not None and not str(accept_failed_gates).strip():
        raise ValueError("accept_failed_gates must be a non-empty reason (it is recorded in the release)")
    card_opts = {**_cards.DEFAULT_CARD, **((config or {}).get("card") or {}), **(card or {})}
    source = _Source(source_dir, source_storage_options)
    if publish_npz:
        from drivetrack.compact.export import FORMATS, export_clips

        export_clips(source.url, list(FORMATS), source.url, storage_options=source_storage_options)
    sizes = source.list()
    if not publish_npz:
        sizes = {p: n for p, n in sizes.items() if not parse_clip_path(p)}
    if not sizes:
        raise InvalidSourceError(f"source folder {source.where('')} holds no files: nothing to publish")
    # the content: names, npz headers, tables, finished segments (refused before the gates run)
    for rel in sizes:
        check_release_path(rel, source.where(rel))
        if rel in RESERVED_NAMES:
            raise InvalidSourceError(
                f"{source.where(rel)}: the release writes {rel} itself; remove or rename it in the source")
    run = read_run_json(source.read("run.json") if "run.json" in sizes else None, source.where("run.json"))
    stats_files = {p.split("/", 1)[1]: source.read(p) for p in sizes
                   if p.startswith("stats/") and p.count("/") == 1 and p.endswith(".parquet")}
    for name, data in stats_files.items():
        _contents.check_stats_table(name.rsplit(".", 1)[0], data, source.where(f"stats/{name}"))
    paths = list(sizes)
    clips = [p for p in paths if parse_table_path(p) or parse_clip_path(p)]
    _contents.refuse(source.where(""), _contents.clips_of_unfinished_segments(
        clips, stats_files.get("segments.parquet"), "stats/segments.parquet"),
        "clips of segments not recorded as done in stats/segments.parquet; delete them or annotate "
        "those segments again")
    # Reads the clips tables (columns, frame references) and the .npy headers of every npz clip; a
    # bad clip file fails here, before anything is written.
    clip_counts = _check_tables(source, paths)
    npz_configs = _check_clips(source, paths, splits_from_paths(paths), workers)

    # the gates: the given report, or a run now; either way bound to this content
    gates_ran_by = "report"
    if gate_report is None:
        from drivetrack.gates import run_gates

        gate_report = run_gates(source.url, gates_config).to_dict()
        gates_ran_by = "publish"
        before = {p: n for p, n in sizes.items() if not p.startswith("validation/")}
        sizes = source.list()  # the gates wrote validation/
        after = {p: n for p, n in sizes.items() if not p.startswith("validation/")}
        if after != before:
            changed = sorted(set(before.items()) ^ set(after.items()))
            raise InvalidSourceError(f"{source.where('')}: files changed while the gates ran "
                                     f"({', '.join(p for p, _ in changed[:10])}); nothing was published")
    check_gate_report(gate_report, accept_failed_gates)
    # The binding without hashing the clips: the same tables (sha256 of the bytes read above), the
    # same clip paths and sizes. The clips' sha256 are compared on the staged bytes (step 3).
    _check_binding(gate_report, {f"stats/{n}": sha256_bytes(d) for n, d in stats_files.items()},
                   {p: (sizes[p], None) for p in clips if parse_table_path(p)}, source.where(""))
    statistics = statistics_from_parquet(stats_files)

    store = open_store(store_url, storage_options)
    vpre, claim = version_prefix(dataset, version), claim_path(dataset, version)
    manifest_rel = f"{vpre}/{MANIFEST_NAME}"

    # 1. never overwrite a published version
    if store.exists(manifest_rel):
        if resume:  # killed after its commit: finish the pointers and clean-up, change nothing else
            return _finish_committed(store, source, sizes, dataset, version, workers)
        raise VersionExistsError(
            f"{store.url_of(vpre)} is already published (manifest exists); published versions are "
            f"immutable: choose a new version")

    # 2. claim the version
    created, t_created = _now()
    txid = uuid.uuid4().hex
    claim_doc = {"dataset": dataset, "version": version, "txid": txid, "host": socket.gethostname(),
                 "pid": os.getpid(), "started": created, "started_unix": t_created, "source": source.url}
    claim_bytes = _json_bytes(claim_doc)
    try:
        store.put_if_absent(claim, claim_bytes)
    except FileExistsError:
        holder, token = _read_json(store, claim)
        if not resume or holder is None:
            if store.exists(manifest_rel):
                raise VersionExistsError(f"{store.url_of(vpre)} was published meanwhile; published "
                                         f"versions are immutable") from None
            raise ConcurrentPublishError(
                f"version {version} of {dataset} in {store.url} is being published by another process "
                f"(transaction {holder and holder.get('txid')}, host {holder and holder.get('host')}, "
                f"pid {holder and holder.get('pid')}, started {holder and holder.get('started')}). "
                f"If that publish was interrupted, resume it (resume=True / --resume) or clean it up "
                f"(`drivetrack gc {store.url} --dataset {dataset}`)") from None
        claim_doc["resumed_from"] = holder.get("txid")
        claim_bytes = _json_bytes(claim_doc)
        try:
            store.compare_and_swap(claim, claim_bytes, token)
        except CasConflictError:
            raise ConcurrentPublishError(
                f"version {version} of {dataset}: another process took over the claim {store.url_of(claim)} "
                f"while this one tried to resume") from None

    def still_ours(step: str) -> None:
        holder, _ = _read_json(store, claim)
        if holder is None or holder.get("txid") != txid:
            raise ConcurrentPublishError(
                f"version {version} of {dataset}: the claim {store.url_of(claim)} was taken over or removed "
                f"(now {holder and holder.get('txid')}) before {step}; this publish stopped without committing")

    try:
        if store.exists(manifest_rel):
            store.delete(claim)
            raise VersionExistsError(f"{store.url_of(vpre)} was published meanwhile; published versions "
                                     f"are immutable")
        result = _publish_claimed(
            store=store, source=source, sizes=sizes, dataset=dataset, version=version, created=created,
            run=run, statistics=statistics, stats_files=stats_files, npz_configs=npz_configs, clip_counts=clip_counts,
            config=config, card_opts=card_opts, gates_ran_by=gates_ran_by,
            gate_report=gate_report, accept_failed_gates=accept_failed_gates, resume=resume,
            workers=workers, progress=progress, still_ours=still_ours)
    except (PublishConflictError, InvalidSourceError, GateBindingError):
        raise
    except Exception as e:
        raise PublishInterruptedError(
            f"publish of {dataset} {version} to {store.url} was interrupted: {type(e).__name__}: {e}. "
            f"No version is visible (no manifest was committed). Resume with the same command and "
            f"--resume (resume=True), or clean up with `drivetrack gc {store.url} --dataset {dataset} "
            f"--older-than 0`") from e
    return result


def _publish_claimed(*, store: Store, source: _Source, sizes: dict[str, int], dataset: str, version: str,
                     created: str, run: dict | None, statistics: dict, stats_files: dict, npz_configs: dict,
                     clip_counts: dict,
                     config: dict | None, gates_ran_by: str,
                     card_opts: dict, gate_report: dict, accept_failed_gates: str | None,
                     resume: bool, workers: int, progress: Progress | None, still_ours) -> PublishResult:
    vpre, spre = version_prefix(dataset, version), staging_prefix(dataset, version)
    claim = claim_path(dataset, version)
    emit = progress or (lambda event, info: None)
    t0 = time.perf_counter()
    if not resume:  # leftovers of an earlier, cleaned-up attempt are not ours to reuse
        store.delete_tree(spre)
        store.delete_tree(vpre)
    staged_now = set(store.find(spre)) if resume else set()
    final_now = set(store.find(vpre)) if resume else set()

    # 3. upload + hash concurrently, then check what was staged
    def upload(rel: str) -> tuple[FileEntry, str]:
        where = source.where(rel)
        if resume and (rel in staged_now or rel in final_now):
            with source.open(rel) as f:
                digest, n = sha256_stream(f)
            for prefix, state in ((vpre, "promoted"), (spre, "staged")):
                if rel in (final_now if state == "promoted" else staged_now):
                    if store.size(f"{prefix}/{rel}") == n and hash_object(store, f"{prefix}/{rel}")[0] == digest:
                        emit("uploaded", {"path": rel, "bytes": n, "reused": True})
                        return FileEntry(rel, n, digest), f"reused-{state}"
        h = hashlib.sha256()
        n = 0
        try:
            with source.open(rel) as fi, store.open_write(f"{spre}/{rel}") as fo:
                for chunk in iter_chunks(fi):
                    h.update(chunk)
                    fo.write(chunk)
                    n += len(chunk)
        except Exception as e:
            raise OSError(f"uploading {where} to {store.url_of(f'{spre}/{rel}')} failed: "
                          f"{type(e).__name__}: {e}") from e
        if n != sizes[rel]:
            raise StagingCheckError(f"{where} changed size during the upload ({sizes[rel]} -> {n} bytes)")
        emit("uploaded", {"path": rel, "bytes": n, "reused": False})
        return FileEntry(rel, n, h.hexdigest()), "uploaded"

    emit("planned", {"files": len(sizes), "bytes": sum(sizes.values())})
    uploaded = _run_pool(upload, list(sizes), workers)
    entries = [e for e, _ in uploaded]
    state = {e.path: s for e, s in uploaded}
    emit("staged", {"staging": store.url_of(spre), "files": len(entries)})

    def check(entry: FileEntry) -> str | None:
        if state[entry.path] != "uploaded":
            return None
        rel = f"{spre}/{entry.path}"
        try:
            digest, n = hash_object(store, rel)
        except FileNotFoundError:
            return f"{entry.path}: staged object {store.url_of(rel)} is missing"
        if n != entry.size or digest != entry.sha256:
            return (f"{entry.path}: staged object {store.url_of(rel)} has {n} bytes, sha256 {digest}; "
                    f"uploaded {entry.size} bytes, sha256 {entry.sha256}")
        return None

    problems = [p for p in _run_pool(check, entries, workers) if p]
    if problems:
        raise StagingCheckError(f"{len(problems)} staged object(s) do not match the upload: "
                                + "; ".join(problems[:5]))
    t_data = time.perf_counter() - t0
    # the gate report's binding against exactly the staged bytes
    try:
        _check_binding(gate_report, {e.path: e.sha256 for e in entries if e.path.startswith("stats/")},
                       {e.path: (e.size, e.sha256) for e in entries if parse_table_path(e.path)},
                       source.where(""))
    except GateBindingError:
        store.delete_tree(spre)
        store.delete(claim)
        raise
    emit("checked", {"files": len(entries)})

    # 4. cards and checksums, staged then promoted with the data
    paths = [e.path for e in entries]
    splits = splits_from_paths(paths)
    counts = counts_from_files(entries, splits, clip_counts)
    gates = _cards.summarize_gates(gate_report, accept_failed_gates)
    gates["ran_by"] = gates_ran_by
    gates["binding_sha256"] = gate_report["binding"]["sha256"]
    code = code_version()
    parquet_columns = _parquet_columns(stats_files)
    croissant = _cards.croissant_bytes(_cards.build_croissant(
        dataset=dataset, version=version, created=created, card=card_opts, data_files=entries,
        npz_configs=npz_configs, parquet_columns=parquet_columns, url=store.url_of(vpre)))
    readme = _cards.build_hf_card(
        dataset=dataset, version=version, created=created, card=card_opts, paths=paths, splits=splits,
        counts=counts, statistics=statistics, gates=gates, run=run, code=code, store_url=store.url).encode()
    meta = [FileEntry(CARD_NAME, len(readme), sha256_bytes(readme)),
            FileEntry(CROISSANT_NAME, len(croissant), sha256_bytes(croissant))]
    sums = render_sha256sums(entries + meta)
    meta.append(FileEntry(SUMS_NAME, len(sums), sha256_bytes(sums)))
    for name, data in ((CARD_NAME, readme), (CROISSANT_NAME, croissant), (SUMS_NAME, sums)):
        store.write_bytes(f"{spre}/{name}", data)
        state[name] = "uploaded"
    all_entries = sorted(entries + meta, key=lambda e: e.path)

    still_ours("promoting the staged files")

    def promote(entry: FileEntry) -> None:
        rel = f"{vpre}/{entry.path}"
        if state[entry.path] != "reused-promoted":
            store.move(f"{spre}/{entry.path}", rel)
        found = store.size(rel)
        if found != entry.size:
            raise StagingCheckError(f"{store.url_of(rel)} has {found} bytes after promotion, expected {entry.size}")
        store.make_read_only(rel)

    _run_pool(promote, all_entries, workers)
    emit("promoted", {"version": store.url_of(vpre)})

    # 5. commit: the manifest, created exclusively, last
    run_info = {k: v for k, v in (run or {}).items() if k not in ("config", "segments")}
    manifest = seal_manifest({
        "format": MANIFEST_FORMAT,
        "dataset": dataset,
        "version": version,
        "created": created,
        "code_version": code,
        "run": run_info or None,
        "config": {"annotation": (run or {}).get("config"), "publish": config},
        "segments": (run or {}).get("segments") or [],
        "counts": counts,
        "statistics": statistics,
        "gates": gates,
        "source": source.url,
        "files": [e.to_json() for e in all_entries],
    })
    still_ours("committing the manifest")
    try:
        store.put_if_absent(f"{vpre}/{MANIFEST_NAME}", dump_manifest(manifest))
    except FileExistsError:
        raise VersionExistsError(f"{store.url_of(vpre)} was committed by another publish first") from None
    store.make_read_only(f"{vpre}/{MANIFEST_NAME}")
    emit("committed", {"manifest_sha256": manifest["manifest_sha256"]})

    # 6. pointers (compare-and-swap) and clean-up; the version is already published here
    warnings: list[str] = []
    latest = finish_committed_version(store, dataset, manifest, warnings)
    total = sum(e.size for e in entries)
    return PublishResult(
        dataset=dataset, version=version, store_url=store.url, version_url=store.url_of(vpre),
        manifest_sha256=manifest["manifest_sha256"], files=len(all_entries), bytes=total,
        seconds=time.perf_counter() - t0, mb_per_s=total / 1e6 / max(t_data, 1e-9), latest=latest,
        reused_files=sum(1 for s in state.values() if s.startswith("reused")), warnings=warnings)


def _finish_committed(store: Store, source: _Source, sizes: dict[str, int], dataset: str, version: str,
                      workers: int) -> PublishResult:
    """``resume`` of a version whose manifest is already committed (the publish was killed after its
    commit): if the committed files are exactly the source's (paths, sizes, sha256), repair
    ``versions.json``/``latest.json`` and remove the claim and staging left behind; else the version
    belongs to other content and :class:`VersionExistsError` is raised. Never writes the version."""
    from drivetrack.release.manifest import manifest_entries, parse_manifest

    t0 = time.perf_counter()
    vpre = version_prefix(dataset, version)
    rel = f"{vpre}/{MANIFEST_NAME}"
    manifest = parse_manifest(store.read_bytes(rel), store.url_of(rel))
    committed = {p: e for p, e in manifest_entries(manifest).items() if p not in RESERVED_NAMES}

    def differs(path: str) -> str | None:
        e = committed.get(path)
        if e is None:
            return f"{source.where(path)} is not in the committed release"
        with source.open(path) as f:
            digest, n = sha256_stream(f)
        if (n, digest) != (e.size, e.sha256):
            return (f"{source.where(path)} has {n} bytes, sha256 {digest}; the committed file has "
                    f"{e.size} bytes, sha256 {e.sha256}")
        return None

    problems = [p for p in _run_pool(differs, list(sizes), workers) if p]
    problems += [f"{store.url_of(f'{vpre}/{p}')} is not in the source" for p in committed if p not in sizes]
    if problems:
        raise VersionExistsError(
            f"{store.url_of(vpre)} is already published with other content ({len(problems)} difference(s): "
            f"{'; '.join(problems[:3])}); published versions are immutable: choose a new version")
    warnings = [f"{store.url_of(vpre)} was already committed (an interrupted publish of this content); "
                f"finished its index, latest pointer and clean-up"]
    latest = finish_committed_version(store, dataset, manifest, warnings)
    total = sum(e.size for e in committed.values())
    seconds = time.perf_counter() - t0
    return PublishResult(
        dataset=dataset, version=version, store_url=store.url, version_url=store.url_of(vpre),
        manifest_sha256=manifest["manifest_sha256"], files=len(manifest["files"]), bytes=total,
        seconds=seconds, mb_per_s=total / 1e6 / max(seconds, 1e-9), latest=latest,
        reused_files=len(manifest["files"]), warnings=warnings)


def _check_binding(gate_report: dict, tables: dict[str, str], clips: dict[str, tuple[int, str | None]],
                   where: str) -> None:
    problems = binding_problems(gate_report["binding"], tables, clips)
    if problems:
        raise GateBindingError(
            f"{where}: the gate report does not describe this content (binding "
            f"{gate_report['binding']['sha256'][:16]}); nothing was published. Run the gates on this "
            f"folder again (`drivetrack gates OUT`, or publish without --gate-report):\n  "
            + "\n  ".join(problems))


def _check_tables(source: _Source, paths: list[str]) -> dict[str, int]:
    """Check the v2 tables: every clips table readable with the layout's columns, every frame a clip
    refers to a row of its frames table (errors name the file, the clip and the frame). Returns
    the number of clips per split."""
    from drivetrack.compact.read import check_frame_references, clip_ids
    from drivetrack.release.errors import InvalidSourceError as _Invalid

    rels = sorted(p for p in paths if (parsed := parse_table_path(p)) and parsed[0] == CLIPS)
    if source.local:
        fs, root = fsspec.filesystem("file"), source.root.rstrip("/")
    else:
        fs, root = source.fs, source.root.rstrip("/")
    _contents.refuse(source.where(""), check_frame_references(fs, root, rels),
                     "clips tables that cannot be read or refer to frames their frames tables lack")
    counts: dict[str, int] = {}
    for rel in rels:
        try:
            counts[parse_table_path(rel)[1]] = counts.get(parse_table_path(rel)[1], 0) + len(
                clip_ids(fs, f"{root}/{rel}", rel))
        except ValueError as error:
            raise _Invalid(f"{source.where(rel)}: {error}") from error
    return counts


def _check_clips(source: _Source, paths: list[str], splits: list[str], workers: int):
    """Check every clip's ``.npz`` headers (:func:`drivetrack.release.contents.check_clip_npz`);
    returns the Croissant record sets ``{layout: (globs, merged array specs)}``."""
    out = {}
    for layout in (DRIVETRACK, TAPVID3D):
        files = [c for s in splits for c in clips_of(paths, layout, s)]
        if not files:
            continue

        def check(rel: str, layout=layout):
            with source.open(rel) as f:
                return [_cards.ArraySpec(name, dtype.str, shape)
                        for name, dtype, shape in _contents.check_clip_npz(f, source.where(rel), layout)]

        specs = _run_pool(check, files, workers)
        out[layout] = ([clip_glob(layout, s) for s in splits], _cards.merge_specs(specs))
    return out


def _parquet_columns(stats_files: dict[str, bytes]) -> dict[str, list[tuple[str, str]]]:
    import io

    import pyarrow.parquet as pq

    out = {}
    for name, data in stats_files.items():
        schema = pq.read_schema(io.BytesIO(data))
        out[f"stats/{name}"] = [(f.name, str(f.type)) for f in schema]
    return out
