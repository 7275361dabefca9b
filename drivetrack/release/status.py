"""Per-segment, per-stage status of a release build: the model, its transitions and the
``status.json`` / ``status.html`` files, pure core (no Prefect). What the pages show (HTML,
markdown, the quality read from the tables) is :mod:`drivetrack.release.status_pages`.

The release flow (``flows/release.py``) owns one :class:`ReleaseStatus`, updates it as jobs
finish, mirrors it to Prefect artifacts and writes both files into the annotation folder, so
that they are published inside the release and served by ``drivetrack status STORE``.

States: ``pending`` (not started), ``running``, ``done``, ``failed`` (with its error), and
``skipped`` (not run because an earlier stage of the same segment failed). A ``done`` stage may
be ``cached``: its content-keyed result of an earlier run was reused.
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone

from typing import TYPE_CHECKING

import fsspec

if TYPE_CHECKING:
    from drivetrack.release.status_pages import ReleaseQuality

__all__ = ["STATES", "SEGMENT_STAGES", "RELEASE_STAGES", "StageStatus", "SegmentStatus", "ReleaseStatus",
           "write_status", "read_status", "read_release_status", "StatusError", "STATUS_JSON", "STATUS_HTML",
           "mark_from_record", "mark_failed", "merge_progress", "gate_outcome"]

STATES = ("pending", "running", "done", "failed", "skipped")
SEGMENT_STAGES = ("ingest", "depth", "tracks", "write")
"""Per segment: read and validate the source, depth completion (GPU queue), per-object track
jobs, writing the clip files and the segment's tables."""
RELEASE_STAGES = ("list", "segments", "statistics", "previews", "gates", "publish")
"""Once per release: list segments, all segment jobs, merged statistics, gates, publish."""
STATUS_JSON = "status.json"
STATUS_HTML = "status.html"
FORMAT = "drivetrack-status/1"



class StatusError(ValueError):
    """A status document or state that does not follow the format; the message names it."""


def _check_state(state: str, where: str) -> str:
    if state not in STATES:
        raise StatusError(f"{where}: unknown state {state!r}; expected one of {', '.join(STATES)}")
    return state


def _utc(t: float | None) -> str | None:
    if t is None:
        return None
    try:
        return datetime.fromtimestamp(t, timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    except (OverflowError, OSError, ValueError, TypeError):
        return f"(bad time {t!r})"


@dataclass
class StageStatus:
    """One stage of one segment (or of the release). Times are unix seconds; ``seconds`` is the
    stage's own duration (``finished - started`` unless the job reported it); ``count`` counts
    what the stage produced, in ``unit`` (frames, depth batches, objects, files)."""
    state: str = "pending"
    started: float | None = None
    finished: float | None = None
    seconds: float | None = None
    count: int | None = None
    unit: str | None = None
    error: str | None = None
    cached: bool = False
    worker: str | None = None
    #: depth stage only: the completer(s) and device(s) that ran its batches (comma-joined), and per
    #: batch ``{"camera", "frames", "completer", "device", "worker", "seconds"}`` (the GPU queue's choice)
    completer: str | None = None
    device: str | None = None
    batches: list | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict, where: str = "stage") -> "StageStatus":
        if not isinstance(d, dict):
            raise StatusError(f"{where}: expected an object, found {type(d).__name__}")
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise StatusError(f"{where}: unknown fields {sorted(unknown)}")
        for k, v in d.items():
            kind = _FIELD_TYPES[k]
            if v is not None and not (isinstance(v, kind) and not (kind is not bool and isinstance(v, bool))):
                raise StatusError(f"{where}: field {k!r} must be {kind.__name__ if isinstance(kind, type) else 'a number'}"
                                  f" or null, found {v!r}")
        s = cls(**d)
        _check_state(s.state, where)
        return s


_FIELD_TYPES = {"state": str, "started": (int, float), "finished": (int, float), "seconds": (int, float),
                "count": int, "unit": str, "error": str, "cached": bool, "worker": str, "completer": str,
                "device": str, "batches": list}


@dataclass
class SegmentStatus:
    split: str
    segment: str
    key: str | None = None
    stages: dict[str, StageStatus] = field(default_factory=lambda: {s: StageStatus() for s in SEGMENT_STAGES})

    @property
    def state(self) -> str:
        """failed if any stage failed; done if all are done; pending if none started; else running."""
        states = [s.state for s in self.stages.values()]
        if "failed" in states:
            return "failed"
        if all(s == "done" for s in states):
            return "done"
        if all(s == "pending" for s in states):
            return "pending"
        return "running"

    @property
    def error(self) -> str | None:
        for name, s in self.stages.items():
            if s.error:
                return f"{name}: {s.error}"
        return None

    @property
    def cached(self) -> bool:
        return all(s.cached for s in self.stages.values())

    @property
    def seconds(self) -> float:
        return float(sum(s.seconds or 0.0 for s in self.stages.values()))

    def to_dict(self) -> dict:
        return {"split": self.split, "segment": self.segment, "key": self.key, "state": self.state,
                "error": self.error, "cached": self.cached,
                "stages": {k: v.to_dict() for k, v in self.stages.items()}}

    @classmethod
    def from_dict(cls, d: dict, where: str = "segment") -> "SegmentStatus":
        try:
            split, segment = d["split"], d["segment"]
        except (KeyError, TypeError) as e:
            raise StatusError(f"{where}: missing field {e}") from None
        if not isinstance(split, str) or not isinstance(segment, str):
            raise StatusError(f"{where}: split and segment must be strings, found {split!r}, {segment!r}")
        where = f"{where} {split}/{segment}"
        if not isinstance(d.get("stages") or {}, dict):
            raise StatusError(f"{where}: 'stages' must be an object, found {type(d['stages']).__name__}")
        stages = {k: StageStatus.from_dict(v, f"{where} stage {k}") for k, v in (d.get("stages") or {}).items()}
        return cls(split=split, segment=segment, key=d.get("key"), stages=stages)


@dataclass
class ReleaseStatus:
    """Everything the dashboard shows. Mutate through :meth:`update` / :meth:`update_release`
    so that ``updated`` moves and unknown segments, stages or states are refused."""
    dataset: str
    version: str
    source: str | None = None
    store: str | None = None
    created: float = field(default_factory=time.time)
    updated: float = field(default_factory=time.time)
    fingerprint: str | None = None
    published: bool = False
    message: str | None = None
    stages: dict[str, StageStatus] = field(default_factory=lambda: {s: StageStatus() for s in RELEASE_STAGES})
    segments: list[SegmentStatus] = field(default_factory=list)
    previews: list[str] = field(default_factory=list)   # release-relative paths (drivetrack show)

    # ---- mutation -----------------------------------------------------------------------
    def add_segment(self, split: str, segment: str, key: str | None = None) -> SegmentStatus:
        if self.find(split, segment) is not None:
            raise StatusError(f"segment {split}/{segment} is already in the status of {self.version}")
        s = SegmentStatus(split=split, segment=segment, key=key)
        self.segments.append(s)
        self.updated = time.time()
        return s

    def find(self, split: str, segment: str) -> SegmentStatus | None:
        for s in self.segments:
            if s.split == split and s.segment == segment:
                return s
        return None

    def update(self, split: str, segment: str, stage: str, state: str, **fields) -> StageStatus:
        """Set one segment stage's state and fields; ``running`` stamps ``started``, ``done`` and
        ``failed`` stamp ``finished`` and ``seconds`` unless given."""
        seg = self.find(split, segment)
        if seg is None:
            raise StatusError(f"no segment {split}/{segment} in the status of {self.version}")
        if stage not in seg.stages:
            raise StatusError(f"segment {split}/{segment}: unknown stage {stage!r}; expected one of "
                              f"{', '.join(seg.stages)}")
        return self._set(seg.stages[stage], state, f"segment {split}/{segment} stage {stage}", fields)

    def update_release(self, stage: str, state: str, **fields) -> StageStatus:
        if stage not in self.stages:
            raise StatusError(f"unknown release stage {stage!r}; expected one of {', '.join(self.stages)}")
        return self._set(self.stages[stage], state, f"release stage {stage}", fields)

    def _set(self, st: StageStatus, state: str, where: str, fields: dict) -> StageStatus:
        _check_state(state, where)
        unknown = set(fields) - set(StageStatus.__dataclass_fields__)
        if unknown:
            raise StatusError(f"{where}: unknown fields {sorted(unknown)}")
        now = time.time()
        st.state = state
        for k, v in fields.items():
            setattr(st, k, v)
        if state == "running" and "started" not in fields:
            st.started = now
        if state in ("done", "failed") and "finished" not in fields:
            st.finished = now
        if state in ("done", "failed") and "seconds" not in fields and st.started is not None:
            st.seconds = max(0.0, (st.finished or now) - st.started)
        if state == "pending":
            st.started = st.finished = st.seconds = None
        self.updated = now
        return st

    # ---- summaries ----------------------------------------------------------------------
    def counts(self) -> dict[str, int]:
        """Segments per state (every state present, zero included)."""
        out = {s: 0 for s in STATES}
        for seg in self.segments:
            out[seg.state] += 1
        return out

    def stage_counts(self) -> dict[str, dict[str, int]]:
        """Per segment stage: segments per state."""
        out = {name: {s: 0 for s in STATES} for name in SEGMENT_STAGES}
        for seg in self.segments:
            for name, st in seg.stages.items():
                out.setdefault(name, {s: 0 for s in STATES})[st.state] += 1
        return out

    @property
    def state(self) -> str:
        states = [s.state for s in self.stages.values()]
        if "failed" in states:
            return "failed"
        if all(s in ("done", "skipped") for s in states):
            return "done"
        if all(s == "pending" for s in states):
            return "pending"
        return "running"

    def table_rows(self) -> list[dict]:
        """One flat row per segment (the Prefect table artifact)."""
        rows = []
        for seg in self.segments:
            row = {"split": seg.split, "segment": seg.segment, "state": seg.state,
                   "cached": seg.cached, "seconds": round(seg.seconds, 2)}
            for name, st in seg.stages.items():
                row[name] = st.state + (f" {st.count} {st.unit or ''}".rstrip() if st.count is not None else "")
            row["error"] = seg.error or ""
            rows.append(row)
        return rows

    def to_dict(self) -> dict:
        return {"format": FORMAT, "dataset": self.dataset, "version": self.version, "source": self.source,
                "store": self.store, "created": self.created, "created_utc": _utc(self.created),
                "updated": self.updated, "updated_utc": _utc(self.updated), "fingerprint": self.fingerprint,
                "published": self.published, "message": self.message, "state": self.state,
                "counts": self.counts(), "stage_counts": self.stage_counts(),
                "stages": {k: v.to_dict() for k, v in self.stages.items()},
                "segments": [s.to_dict() for s in self.segments], "previews": list(self.previews)}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1, allow_nan=False)

    @classmethod
    def from_dict(cls, d: dict, where: str = "status.json") -> "ReleaseStatus":
        if not isinstance(d, dict):
            raise StatusError(f"{where}: expected a JSON object, found {type(d).__name__}")
        if d.get("format") != FORMAT:
            raise StatusError(f"{where}: format {d.get('format')!r}, expected {FORMAT!r}")
        for k in ("dataset", "version"):
            if not isinstance(d.get(k), str):
                raise StatusError(f"{where}: field {k!r} must be a string, found {d.get(k)!r}")
        for k in ("source", "store", "fingerprint", "message"):
            if d.get(k) is not None and not isinstance(d[k], str):
                raise StatusError(f"{where}: field {k!r} must be a string or null, found {d[k]!r}")
        for k in ("created", "updated"):
            if d.get(k) is not None and (not isinstance(d[k], (int, float)) or isinstance(d[k], bool)):
                raise StatusError(f"{where}: field {k!r} must be unix seconds, found {d[k]!r}")
        for k, kind in (("stages", dict), ("segments", list), ("previews", list)):
            if not isinstance(d.get(k) or kind(), kind):
                raise StatusError(f"{where}: field {k!r} must be a JSON {kind.__name__}, found {d[k]!r}")
        return cls(dataset=d["dataset"], version=d["version"], source=d.get("source"), store=d.get("store"),
                   created=d.get("created") or 0.0, updated=d.get("updated") or 0.0,
                   fingerprint=d.get("fingerprint"), published=bool(d.get("published")),
                   message=d.get("message"),
                   stages={k: StageStatus.from_dict(v, f"{where}: release stage {k}")
                           for k, v in (d.get("stages") or {}).items()},
                   segments=[SegmentStatus.from_dict(s, f"{where}: segment") for s in d.get("segments") or []],
                   previews=[str(p) for p in d.get("previews") or []])


# ---- transitions from the work folder's records (the release flow's board) ---------------------

def _stage_fields(info: dict) -> dict:
    return {k: v for k, v in info.items() if k in StageStatus.__dataclass_fields__ and k != "state"}


def merge_progress(status: ReleaseStatus, split: str, segment: str, doc: dict | None) -> None:
    """Copy a running job's live stage states (its progress record) into ``status``."""
    if not doc:
        return
    for name, info in (doc.get("stages") or {}).items():
        if name in SEGMENT_STAGES:
            status.update(split, segment, name, info["state"], **_stage_fields(info))


def mark_from_record(status: ReleaseStatus, split: str, segment: str, rec: dict, cached: bool) -> None:
    """Every stage of a segment ``done`` from its completion record (``cached``: reused)."""
    for name in SEGMENT_STAGES:
        info = (rec.get("stages") or {}).get(name, {})
        status.update(split, segment, name, "done", cached=cached, **_stage_fields(info))


def mark_failed(status: ReleaseStatus, split: str, segment: str, progress: dict | None, error: str) -> str:
    """A failed segment: the stage that failed (from its progress record; else the first one not
    done) gets ``error``, the later stages are ``skipped``. Returns the failed stage's name."""
    stages = (progress or {}).get("stages") or {}
    failed_at = next((n for n in SEGMENT_STAGES if stages.get(n, {}).get("state") == "failed"), None)
    if failed_at is None:  # failed before or between recorded stages
        failed_at = next((n for n in SEGMENT_STAGES if stages.get(n, {}).get("state") != "done"), SEGMENT_STAGES[0])
    after = False
    for name in SEGMENT_STAGES:
        if name == failed_at:
            info = stages.get(name, {})
            status.update(split, segment, name, "failed", error=error,
                          **({"started": info["started"]} if info.get("started") else {}))
            after = True
        elif after:
            status.update(split, segment, name, "skipped")
    return failed_at


def gate_outcome(report: dict, accepted: str | None = None) -> dict:
    """The ``gates`` release stage's state and fields from a gate report
    (:meth:`drivetrack.gates.GateReport.to_dict`): ``done`` when it passed, else ``failed`` with
    the number of failed gates (and the reason they were accepted, if any)."""
    results = report.get("results", [])
    n_failed = sum(1 for r in results if not r.get("success", True))
    ok = bool(report.get("success"))
    return {"state": "done" if ok else "failed", "count": len(results), "unit": "gates",
            "error": None if ok else f"{n_failed} gates failed" + (f" (accepted: {accepted})" if accepted else "")}


# ---- files -------------------------------------------------------------------------------------

def write_status(out_url: str, status: ReleaseStatus, *, storage_options: dict | None = None,
                 refresh_s: int | None = None, quality: ReleaseQuality | None = None) -> tuple[str, str]:
    """Write ``status.json`` and ``status.html`` (with ``quality`` beside the states when given)
    into the folder ``out_url`` (any fsspec URL), each atomically
    (:func:`drivetrack.storage.write_bytes`), so that a reader never sees half a file. Returns
    both paths."""
    from drivetrack.release.status_pages import render_status_html
    from drivetrack.storage import write_bytes

    fs, root = fsspec.core.url_to_fs(str(out_url), **(storage_options or {}))
    root = root.rstrip("/")
    base = str(out_url).rstrip("/")
    out = []
    for name, text in ((STATUS_JSON, status.to_json()), (STATUS_HTML, render_status_html(status, refresh_s=refresh_s,
                                                                                   quality=quality))):
        write_bytes(f"{base}/{name}", text.encode("utf-8"), storage_options)
        out.append(f"{root}/{name}")
    return out[0], out[1]


def read_status(url: str, *, storage_options: dict | None = None) -> ReleaseStatus:
    """Read a ``status.json`` (file URL, or a folder holding one)."""
    fs, path = fsspec.core.url_to_fs(str(url), **(storage_options or {}))
    if fs.isdir(path):
        path = f"{path.rstrip('/')}/{STATUS_JSON}"
    try:
        with fs.open(path, "r", encoding="utf-8") as f:
            doc = json.load(f)
    except FileNotFoundError:
        raise FileNotFoundError(f"no {STATUS_JSON} at {url}") from None
    except json.JSONDecodeError as e:
        raise StatusError(f"{path}: not valid JSON ({e})") from e
    return ReleaseStatus.from_dict(doc, where=str(path))


def read_release_status(store_url: str, version: str = "latest", dataset: str = "drivetrack-waymo", *,
                        storage_options: dict | None = None) -> tuple[str, bytes, ReleaseStatus]:
    """Resolve ``version`` (``latest`` allowed) in a release store and return
    ``(version, status.html bytes, status)``. Raises ``VersionNotFoundError`` for an unknown
    version and FileNotFoundError naming the path when the release holds no status page."""
    from drivetrack.release import open_store
    from drivetrack.release.catalog import resolve_version
    from drivetrack.release.manifest import check_version

    store = open_store(store_url, storage_options)
    v = resolve_version(store, dataset, version)
    check_version(v)
    if not store.exists(f"{dataset}/{v}/manifest.json"):
        from drivetrack.release import VersionNotFoundError
        raise VersionNotFoundError(f"{store.url_of(f'{dataset}/{v}')} is not published (no manifest.json)")
    rel_html, rel_json = f"{dataset}/{v}/{STATUS_HTML}", f"{dataset}/{v}/{STATUS_JSON}"
    for rel in (rel_html, rel_json):
        if not store.exists(rel):
            raise FileNotFoundError(f"{store.url_of(rel)} does not exist: release {v} was not built by the "
                                    f"release flow (no status page)")
    try:
        doc = json.loads(store.read_bytes(rel_json))
    except ValueError as e:   # JSONDecodeError, UnicodeDecodeError
        raise StatusError(f"{store.url_of(rel_json)}: not valid JSON ({e})") from e
    return v, store.read_bytes(rel_html), ReleaseStatus.from_dict(doc, where=store.url_of(rel_json))
