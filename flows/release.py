"""The ``release`` flow: list segments, per-segment jobs (ingestion, depth completion on the GPU
queue, per-object tracks, writing), statistics, gates, publish - staged by Prefect on Dask.

    python -m flows.release --version 1.2.3 --source data/synthetic --store ./store
    make release VERSION=1.2.3 [SOURCE=...] [STORE=...] [SEGMENTS='a b']

Tasks are thin and coarse: one Prefect task per segment (fine work fans out on Dask inside it,
see :mod:`flows.jobs`); the release-wide steps are one task each. Segment results are keyed on
content (:mod:`drivetrack.release.keys`): a re-run after an interruption or a change recomputes only the
segments whose key has no completion record. A failed segment is reported with its error and
does not stop the others; the gates decide whether the release publishes.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path

from flows import REPO  # sets Prefect/Dask environment defaults before Prefect is imported

from prefect import flow, get_run_logger, task  # noqa: E402
from prefect.artifacts import (create_markdown_artifact, create_progress_artifact, create_table_artifact,  # noqa: E402
                               update_progress_artifact)
from prefect.futures import wait  # noqa: E402

from drivetrack.release import keys, work as workdir  # noqa: E402
from drivetrack.release.catalog import next_version  # noqa: E402
from drivetrack.provenance import code_version  # noqa: E402
from drivetrack.release.assemble import release_run_record  # noqa: E402
from drivetrack.release.status import (ReleaseStatus, gate_outcome, mark_failed, mark_from_record,  # noqa: E402
                                       merge_progress, write_status)
from drivetrack.release.status_pages import read_quality, reused_markdown, segment_markdown  # noqa: E402
from flows import jobs  # noqa: E402
from flows.credentials import guarded_flow, resolve_options  # noqa: E402
from flows.runtime import ClusterConfig, dask_cluster, prefect_api  # noqa: E402

DEFAULT_DATASET = "drivetrack-waymo"
DEFAULT_WORK = str(REPO / "build" / "release-work")
STATUS_EVERY_S = 1.0


# ---- tasks -------------------------------------------------------------------------------------

@task(name="list-segments", retries=2, retry_delay_seconds=2,
      retry_condition_fn=lambda t, r, s: jobs.is_transient(s.result(raise_on_failure=False)))
def list_segments_task(source: str, splits: list[str], segments: list[str] | None,
                       storage_options: dict | None = None) -> list[tuple[str, str]]:
    """(split, segment) pairs to build; requested segments missing from every split are an error."""
    from drivetrack.waymo.reader import list_segments

    storage_options = resolve_options(storage_options)  # references -> values, here on the worker
    found = {split: list_segments(source, split, storage_options) for split in splits}
    if segments:
        wanted = []
        for seg in segments:
            hits = [split for split in splits if seg in found[split]]
            if not hits:
                raise ValueError(f"segment {seg!r} is not in {source} (splits {', '.join(splits)}; "
                                 f"found {sum(len(v) for v in found.values())} segments)")
            wanted += [(split, seg) for split in hits]
        return wanted
    pairs = [(split, seg) for split in splits for seg in found[split]]
    if not pairs:
        raise ValueError(f"no segments under {source} in splits {', '.join(splits)}")
    return pairs


@task(name="plan", retries=2, retry_delay_seconds=2,
      retry_condition_fn=lambda t, r, s: jobs.is_transient(s.result(raise_on_failure=False)))
def plan_task(source: str, pairs: list[tuple[str, str]], work: str, config_fp: str, code_fp: str,
              storage_options: dict | None = None) -> list[dict]:
    """Per segment: source checksums and content key, and its completion record if one exists."""
    memo_url = f"{work}/checksums.json"
    storage_options = resolve_options(storage_options)
    memo = {k: tuple(v) for k, v in (workdir.read_record(memo_url) or {}).items()}
    plan = []
    for split, seg in pairs:
        sums = keys.segment_checksums(source, split, seg, storage_options=storage_options, memo=memo)
        key = keys.segment_key(split, seg, sums, config_fp, code_fp)
        plan.append({"split": split, "segment": seg, "key": key, "checksums": sums,
                     "record": workdir.completion_record(work, split, seg, key)})
    workdir.write_record(memo_url, memo)
    return plan


def _segment_cache_key(context, parameters) -> str:
    """The content key, per work folder (a cached result is only good where its files are)."""
    return "drivetrack-segment-" + keys.sha256_json([parameters["work"], parameters["key"]])


@task(name="segment", task_run_name="segment {split}/{segment}", retries=2, retry_delay_seconds=[2, 10],
      retry_condition_fn=lambda t, r, s: jobs.is_transient(s.result(raise_on_failure=False)),
      cache_key_fn=_segment_cache_key, persist_result=True)
def segment_task(source: str, split: str, segment: str, key: str, work: str, config: dict,
                 storage_options: dict | None = None) -> dict:
    """One segment: a thin wrapper around :func:`flows.jobs.run_segment` (reuses a completion
    record with the same content key)."""
    rec = workdir.completion_record(work, split, segment, key)
    if rec is not None:
        return rec
    return jobs.run_segment(source, split, segment, key, work, config, storage_options)


@task(name="statistics")
def statistics_task(out: str, records: list[dict], failed: list[dict], run: dict, work: str) -> dict:
    """Assemble the release folder: every done segment's files, merged stats tables (failed
    segments as ``status=failed`` rows), ``run.json``."""
    from drivetrack.release.assemble import assemble_release_folder

    return assemble_release_folder(out, records, failed, run, work)


@task(name="previews")
def previews_task(out: str) -> list[str]:
    """Contact sheets and a short clip per split, written into the release folder (drivetrack show)."""
    from drivetrack.show import write_previews

    base = out.rstrip("/") + "/"
    return [u[len(base):] if u.startswith(base) else u for u in write_previews(out, per_split=3)]


@task(name="gates")
def gates_task(out: str, gates_config) -> dict:
    from drivetrack.gates import run_gates

    return run_gates(out, gates_config).to_dict()


@task(name="publish", retries=2, retry_delay_seconds=[2, 10],
      retry_condition_fn=lambda t, r, s: _publish_retryable(s.result(raise_on_failure=False)))
def publish_task(out: str, store: str, version: str, dataset: str, gate_report: dict,
                 accept_failed_gates: str | None, config: dict, storage_options: dict | None,
                 publish_npz: bool = False) -> dict:
    """Publish; a retry after an interrupted attempt resumes its staged files. ``publish_npz``: also
    export and publish the npz clips (release option, off by default)."""
    from prefect.context import TaskRunContext

    from drivetrack.release import publish_release

    ctx = TaskRunContext.get()
    resume = bool(ctx and ctx.task_run.run_count > 1)
    storage_options = resolve_options(storage_options, "store_options")
    res = publish_release(out, store, version, dataset=dataset, storage_options=storage_options,
                          gate_report=gate_report, accept_failed_gates=accept_failed_gates, config=config,
                          resume=resume, publish_npz=publish_npz)
    return {k: v for k, v in vars(res).items() if isinstance(v, (str, int, float, bool, type(None)))}


def _publish_retryable(exc) -> bool:
    from drivetrack.release import PublishInterruptedError

    return isinstance(exc, PublishInterruptedError) and jobs.is_transient(exc.__cause__)


# ---- status plumbing ---------------------------------------------------------------------------

class _Board:
    """The parent's single writer of the status: status.json/html in the work and release
    folders, and the Prefect table and progress artifacts."""

    def __init__(self, status: ReleaseStatus, out: str, work: str):
        self.status, self.out, self.work = status, out, work
        self.key = "release-" + "".join(c if c.isalnum() else "-" for c in status.version.lower())
        self.progress_id = None
        self.last_table = 0.0
        self.quality = None  # ReleaseQuality once the statistics and gates exist

    def flush(self, *, table: bool = False, final: bool = False) -> None:
        write_status(self.out, self.status, refresh_s=None if final else 5, quality=self.quality)
        n = len(self.status.segments)
        finished = sum(1 for s in self.status.segments if s.state in ("done", "failed"))
        pct = 100.0 * finished / n if n else 100.0
        try:
            if self.progress_id is None:
                self.progress_id = create_progress_artifact(pct, key=f"{self.key}-progress",
                                                            description=f"segments finished of {n}")
            else:
                update_progress_artifact(self.progress_id, pct)
            if table or final or time.monotonic() - self.last_table > 5:
                create_table_artifact(self.status.table_rows(), key=f"{self.key}-segments",
                                      description=self._describe())
                self.last_table = time.monotonic()
        except Exception as e:  # the UI is advisory; the files are the record
            get_run_logger().warning(f"could not update Prefect artifacts: {type(e).__name__}: {e}")

    def markdown(self, key_suffix: str, text: str, description: str) -> None:
        """One markdown artifact of this run (advisory, like the others)."""
        try:
            create_markdown_artifact(text, key=f"{self.key}-{key_suffix}", description=description)
        except Exception as e:
            get_run_logger().warning(f"could not create the Prefect artifact {key_suffix}: {type(e).__name__}: {e}")

    def segment_artifacts(self) -> None:
        """Per segment: stages, clips, tracks, quality and gate results (``self.quality``)."""
        try:
            self.quality = read_quality(self.out)
        except Exception as e:  # the summaries are advisory; the gates judge the tables
            get_run_logger().warning(f"could not read the quality tables of {self.out}: {jobs.failure_summary(e)}")
        for seg in self.status.segments:
            slug = "".join(c if c.isalnum() else "-" for c in seg.segment.lower())[:40].strip("-")
            tag = keys.sha256_json([seg.split, seg.segment])[:8]
            self.markdown(f"segment-{slug}-{tag}", segment_markdown(self.status, seg, self.quality),
                          f"{seg.split}/{seg.segment}: {seg.state}")

    def _describe(self) -> str:
        c = self.status.counts()
        return (f"{self.status.dataset} {self.status.version}: " + ", ".join(f"{k} {v}" for k, v in c.items() if v)
                + (f". {self.status.message}" if self.status.message else ""))

def _latest_published(store: str, dataset: str, storage_options: dict | None) -> tuple[str | None, dict | None]:
    """(latest version, its run.json) or (None, None) when nothing is published."""
    from drivetrack.release import VersionNotFoundError, open_store
    from drivetrack.release.catalog import resolve_version

    try:
        st = open_store(store, resolve_options(storage_options, "store_options"))
        v = resolve_version(st, dataset, "latest")
        rel = f"{dataset}/{v}/run.json"
        return v, (json.loads(st.read_bytes(rel)) if st.exists(rel) else {})
    except (VersionNotFoundError, FileNotFoundError):
        return None, None


def _refuse_published(store: str, dataset: str, version: str, storage_options: dict | None) -> None:
    """Fail before any work when the version exists (published versions are immutable)."""
    from drivetrack.release import VersionExistsError, check_version, open_store

    check_version(version)
    st = open_store(store, resolve_options(storage_options, "store_options"))
    if st.exists(f"{dataset}/{version}/manifest.json"):
        raise VersionExistsError(f"{st.url_of(f'{dataset}/{version}')} is already published; published versions "
                                 f"are immutable: choose a new version (or version='auto')")


# ---- flows -------------------------------------------------------------------------------------

class _Stop(Exception):
    """A release stage failed: the board has the error; the flow raises the original."""


@contextlib.contextmanager
def _release_stage(board: _Board, name: str, fail_message: str | None = None, *, optional: bool = False):
    """One release-wide stage on the board: running, then done (the body may set a count through
    the yielded dict) or failed with its error; a failed stage that is not ``optional`` ends the
    build with ``fail_message`` on the board and re-raises. An ``optional`` stage that fails is
    marked ``skipped`` with its error (previews never block a release)."""
    status = board.status
    status.update_release(name, "running")
    board.flush()
    out: dict = {}
    try:
        yield out
    except Exception as e:
        if optional:
            status.update_release(name, "skipped", error=jobs.failure_summary(e))
            get_run_logger().warning(f"{name} could not be made: {jobs.failure_summary(e)}")
            return
        status.update_release(name, "failed", error=jobs.failure_summary(e))
        status.message = fail_message
        board.flush(final=True)
        raise
    status.update_release(name, out.pop("state", "done"), **out)


def _run_segments(board: _Board, plan: list[dict], source: str, work: str, config: dict,
                  storage_options: dict | None) -> tuple[dict, list[dict]]:
    """Submit every segment without a completion record, poll their progress into the board
    until all are settled; returns (completion records by (split, segment), failed segments)."""
    status, logger = board.status, get_run_logger()
    records = {(p["split"], p["segment"]): p["record"] for p in plan if p["record"]}
    futures = {segment_task.submit(source, p["split"], p["segment"], p["key"], work, config, storage_options): p
               for p in plan if not p["record"]}
    failed: list[dict] = []
    pending = set(futures)
    while pending:
        done, pending = wait(list(pending), timeout=STATUS_EVERY_S)
        pending = set(pending)
        for p in (futures[f] for f in pending):
            merge_progress(status, p["split"], p["segment"], _progress(work, p["split"], p["segment"]))
        for f in done:
            p = futures[f]
            split, seg = p["split"], p["segment"]
            res = f.result(raise_on_failure=False)  # the record, or the exception of a failed run
            state = f.state
            if isinstance(res, dict) and res.get("status") == "done" and \
                    workdir.completion_record(work, split, seg, p["key"]) is not None:
                records[(split, seg)] = res
                mark_from_record(status, split, seg, res, cached=state.name == "Cached")
            elif isinstance(res, dict) and not p.get("refreshed"):
                # Prefect's cache knew the key but the work folder lost the files: recompute
                p["refreshed"] = True
                logger.warning(f"segment {split}/{seg}: cached result without files; recomputing")
                again = segment_task.with_options(refresh_cache=True).submit(
                    source, split, seg, p["key"], work, config, storage_options)
                futures[again] = p
                pending.add(again)
            else:
                error = jobs.failure_summary(res) if isinstance(res, BaseException) else (
                    "the task reported done but its completion record is missing (work folder cleaned?): "
                    "run again" if isinstance(res, dict) else f"{state.name}: {state.message}")
                stage = mark_failed(status, split, seg, _progress(work, split, seg), error)
                failed.append({"split": split, "segment": seg, "key": p["key"], "stage": stage, "error": error})
                logger.error(f"segment {split}/{seg} failed: {error}")
        board.flush(table=bool(done))
    return records, failed


def _progress(work: str, split: str, segment: str) -> dict | None:
    """A running job's progress record; a damaged one is logged (naming it) and shows no progress."""
    try:
        return workdir.read_record(workdir.progress_path(work, split, segment))
    except ValueError as e:
        get_run_logger().warning(str(e))
        return None


def _result(status: ReleaseStatus, out: str, failed: list[dict], fingerprint: str, run_id: str, **extra) -> dict:
    return {"version": status.version, "out": out, "counts": status.counts(), "failed": failed,
            "fingerprint": fingerprint, "flow_run_id": run_id, **extra}


# ---- flows -------------------------------------------------------------------------------------

@flow(name="release-build", log_prints=True)
def build(version: str, source: str, store: str, splits: list[str], segments: list[str] | None,
          config: dict, dataset: str, work: str, gates_config, accept_failed_gates: str | None,
          skip_unchanged: bool, storage_options: dict | None, store_options: dict | None,
          publish_npz: bool = False) -> dict:
    """The staged recipe; runs with the Dask task runner the ``release`` flow gives it."""
    from prefect.runtime import flow_run

    from drivetrack.annotate import AnnotateConfig

    logger, run_id = get_run_logger(), str(flow_run.id)  # the artifacts of this build hang off this run
    cfg = AnnotateConfig.from_dict(config or {})
    config, config_fp = cfg.to_dict(), cfg.fingerprint()
    code_out, code_all = keys.code_fingerprint(outputs_only=True), keys.code_fingerprint()
    latest, latest_run = _latest_published(store, dataset, store_options)
    version = next_version(latest) if version == "auto" else version
    _refuse_published(store, dataset, version, store_options)
    out = f"{work.rstrip('/')}/releases/{version}"
    status = ReleaseStatus(dataset=dataset, version=version, source=source, store=store)
    board = _Board(status, out, work)
    jobs_fs_reset(out)

    with _release_stage(board, "list", "could not list the source: nothing was built") as st:
        pairs = list_segments_task(source, splits, segments, storage_options)
        plan = plan_task(source, pairs, work, config_fp, code_out, storage_options)
        st.update(count=len(plan), unit="segments")
    for p in plan:
        status.add_segment(p["split"], p["segment"], p["key"])
        if p["record"]:
            mark_from_record(status, p["split"], p["segment"], p["record"], cached=True)
    n_cached = sum(1 for p in plan if p["record"])
    logger.info(f"{len(plan)} segments: {n_cached} reused (same content key), {len(plan) - n_cached} to compute")
    status.update_release("segments", "running")
    board.flush(table=True)
    # reused segments are never submitted, so Prefect has no task run (Cached or other) for them
    board.markdown("reused", reused_markdown(status), f"{n_cached} of {len(plan)} segments reused")
    records, failed = _run_segments(board, plan, source, work, config, storage_options)
    status.update_release("segments", "failed" if failed else "done", count=status.counts()["done"],
                          unit="segments done", error=f"{len(failed)} of {len(plan)} segments failed" if failed else None)
    board.flush(table=True)

    seg_rows = [{"split": s.split, "segment": s.segment, "key": s.key, "state": s.state} for s in status.segments]
    fingerprint = status.fingerprint = keys.release_fingerprint(dataset, seg_rows, config_fingerprint=config_fp,
                                                                gates=gates_config, code=code_all)
    run = release_run_record(config=config, config_fingerprint=config_fp, code_fingerprint=code_all,
                             release_fingerprint=fingerprint, dataset=dataset, version=version, source=source,
                             splits=splits, plan=plan, done=set(records), code_version=code_version(REPO))
    with _release_stage(board, "statistics", "statistics could not be assembled: nothing published") as st:
        stats = statistics_task(out, [records[k] | {"dir": workdir.segment_dir(work, *k, records[k]["key"])}
                                      for k in sorted(records)], failed, run, work)
        st.update(count=stats.get("files"), unit="files")

    if skip_unchanged and latest_run and latest_run.get("release_fingerprint") == fingerprint:
        for name in ("previews", "gates", "publish"):
            status.update_release(name, "skipped")
        status.message = (f"inputs, configuration and code are unchanged since {latest}: no new version "
                          f"(fingerprint {fingerprint[:16]})")
        board.segment_artifacts()
        board.flush(final=True)
        logger.info(status.message)
        return _result(status, out, failed, fingerprint, run_id, version=None, unchanged_since=latest,
                       published=False)

    with _release_stage(board, "previews", optional=True) as st:
        status.previews = previews_task(out)
        st.update(count=len(status.previews), unit="files")
    with _release_stage(board, "gates", "the gates could not run: nothing published") as st:
        report = gates_task(out, gates_config)
        st.update(gate_outcome(report, accept_failed_gates))
    board.segment_artifacts()

    # status.json/html go into the release itself: written as they will be once it is visible
    status.update_release("publish", "done")
    status.published, status.message = True, f"published {dataset} {version} to {store}"
    board.flush(table=True)  # the release folder's status files are final from here on
    try:
        res = publish_task(out, store, version, dataset, report, accept_failed_gates,
                           {"release_fingerprint": fingerprint, "source": source, "splits": splits,
                            "segments_failed": [f"{x['split']}/{x['segment']}" for x in failed],
                            "publish_npz": publish_npz},
                           store_options, publish_npz)
    except Exception as e:
        status.published, status.message = False, f"not published: {type(e).__name__}"
        status.update_release("publish", "failed", error=jobs.failure_summary(e))
        board.flush(final=True)
        logger.error(f"publish of {version} failed: {jobs.failure_summary(e)}")
        return _result(status, out, failed, fingerprint, run_id, published=False, error=jobs.failure_summary(e))
    status.update_release("publish", "done")
    board.flush(final=True)
    return _result(status, out, failed, fingerprint, run_id, published=True, store=store, dataset=dataset,
                   publish=res)


def jobs_fs_reset(out: str) -> None:
    """The release folder is rebuilt from the work folder on every run."""
    import fsspec

    fs, path = fsspec.core.url_to_fs(out)
    if fs.exists(path):
        fs.rm(path, recursive=True)
    fs.makedirs(path, exist_ok=True)


@guarded_flow(name="release", log_prints=True)
def release(version: str = "auto", source: str = str(REPO / "data" / "synthetic"), store: str = str(REPO / "store"),
            splits: list[str] | None = None, segments: list[str] | None = None, config: dict | None = None,
            dataset: str = DEFAULT_DATASET, work: str = DEFAULT_WORK, gates_config: dict | str | None = None,
            accept_failed_gates: str | None = None, skip_unchanged: bool = True,
            dask_address: str | None = None, n_workers: int | None = None, threads_per_worker: int | None = None,
            dask_processes: bool | None = None, storage_options: dict | None = None, store_options: dict | None = None,
            publish_npz: bool = False) -> dict:
    """Build and publish one release. ``version="auto"``: the next patch version, and nothing at
    all when inputs, configuration and code are unchanged since the latest release (scheduled
    regeneration). The Dask cluster: ``dask_address`` (an existing scheduler) or a local one of
    ``n_workers`` x ``threads_per_worker`` (environment ``DRIVETRACK_DASK_*`` otherwise);
    ``dask_processes=False`` keeps the local workers in this process (tests). ``publish_npz``: the
    release also holds the clips as DriveTrack and TAPVid-3D npz files (``drivetrack export``).
    ``storage_options`` (source) and ``store_options`` (store) hold no secrets, only references
    resolved on the workers (:mod:`flows.credentials`); a secret-looking value is refused."""
    from prefect_dask import DaskTaskRunner

    from flows.credentials import check_no_secrets

    # a deployment run's parameters come from the API, not through GuardedFlow: refuse them too
    check_no_secrets({"source": source, "store": store, "storage_options": storage_options,
                      "store_options": store_options, "config": config, "gates_config": gates_config},
                     "flow 'release' parameters")

    splits = list(splits or ["training"])
    cfg = ClusterConfig.from_env(address=dask_address, n_workers=n_workers, threads_per_worker=threads_per_worker,
                                 processes=dask_processes)
    with dask_cluster(cfg) as (client, address):
        get_run_logger().info(f"Dask scheduler {address}, dashboard {client.dashboard_link}, "
                              f"{len(client.scheduler_info()['workers'])} workers")
        runner = DaskTaskRunner(address=address)
        return build.with_options(task_runner=runner)(
            version=version, source=source, store=store, splits=splits, segments=segments, config=config or {},
            dataset=dataset, work=work, gates_config=gates_config, accept_failed_gates=accept_failed_gates,
            skip_unchanged=skip_unchanged, storage_options=storage_options, store_options=store_options,
            publish_npz=publish_npz)


# ---- command line (make release) ----------------------------------------------------------------

def synthesize_default_source(path: Path, segments: int = 3, frames: int = 30, seed: int = 7) -> str:
    """A small synthetic source (``drivetrack synth``), generated once."""
    from drivetrack.synth import SynthConfig, generate_segment

    split_dir = path / "training"
    if split_dir.is_dir() and any(split_dir.glob("camera_image/*.parquet")):
        return str(path)
    cfg = SynthConfig(seed=seed, frames=frames, preset="small")
    t0 = time.perf_counter()
    for i in range(segments):
        generate_segment(str(path), cfg, i)
    print(f"synthesised {segments} segments x {frames} frames into {path} in {time.perf_counter() - t0:.1f} s",
          flush=True)
    return str(path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m flows.release", description=__doc__.split("\n\n")[0])
    p.add_argument("--version", required=True, help="semantic version (x.y.z), or 'auto'")
    p.add_argument("--source", default=None, help="Waymo v2 root (default: synthesise into ./data/synthetic)")
    p.add_argument("--store", default="./store")
    p.add_argument("--segments", default=None, help="space- or comma-separated segment names (default: all)")
    p.add_argument("--splits", default="training")
    p.add_argument("--config", default=None, help="YAML/JSON file with the annotation configuration")
    p.add_argument("--dataset", default=DEFAULT_DATASET)
    p.add_argument("--work", default=DEFAULT_WORK)
    p.add_argument("--dask-address", default=None)
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--accept-failed-gates", default=None, metavar="REASON")
    p.add_argument("--npz", action="store_true",
                   help="also publish the clips as DriveTrack and TAPVid-3D npz files (drivetrack export)")
    args = p.parse_args(argv)
    source = args.source or synthesize_default_source(REPO / "data" / "synthetic")
    config = None
    if args.config:
        import yaml
        config = yaml.safe_load(Path(args.config).read_text())
    store = args.store if "://" in args.store else str(Path(args.store).resolve())
    segments = args.segments.replace(",", " ").split() if args.segments else None
    with prefect_api():
        result = release(version=args.version, source=source, store=store,
                         splits=args.splits.replace(",", " ").split(), segments=segments, config=config,
                         dataset=args.dataset, work=args.work, accept_failed_gates=args.accept_failed_gates,
                         dask_address=args.dask_address, n_workers=args.workers, threads_per_worker=args.threads,
                         skip_unchanged=args.version == "auto", publish_npz=args.npz)
    c = result.get("counts", {})
    print(f"\nsegments: {c.get('done', 0)} done, {c.get('failed', 0)} failed")
    for f in result.get("failed", []):
        print(f"  FAILED {f['split']}/{f['segment']}: {f['error']}")
    print(f"status page: {result['out']}/status.html")
    if result.get("published"):
        v = result["version"]
        print(f"released {args.dataset} {v} at {store}/{args.dataset}/{v}\n"
              f"verify it:   drivetrack verify {args.store} --version {v}\n"
              f"status page: drivetrack status {args.store} --version {v}")
        return 0
    if result.get("unchanged_since"):
        print(f"nothing to release: unchanged since {result['unchanged_since']}")
        return 0
    print(f"NOT released: {result.get('error', 'see the status page')}", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
